"""Fixtures shared by the tests of the diffusion prior (loaded from conftest.py as a plugin).

Every fixture here is lazy: torch and the tiny model are imported and built only when a
test asks for them, so the rest of the suite pays nothing. A module opts into the thread
cap with `pytestmark = pytest.mark.usefixtures("one_thread")`.
"""
from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def one_thread():
    """The tiny model is too small to gain from intra-op threads; one thread avoids
    oversubscription (tens of times slower) when other jobs share the CPU."""
    import torch

    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    """The tiny random diffusion model on disk, in the same layout as real weights."""
    from core.priors.diffusion import build_tiny_model
    from core.priors.diffusion.tiny import TinyConfig

    return build_tiny_model(tmp_path_factory.mktemp("tiny_model"), TinyConfig(resolution=(32, 32)))


@pytest.fixture(scope="module")
def prior(tiny_dir):
    """The tiny model loaded through the local loader, as the engine loads real weights."""
    from core.priors.diffusion import DiffusionPrior

    return DiffusionPrior.from_pretrained(tiny_dir)
