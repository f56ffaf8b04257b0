"""The paper's diffusion prior: SD inpainting + depth ControlNet, exposure-conditioned.

Heavy imports (diffusers, transformers) happen on first attribute access, so importing
`core.priors.diffusion` costs nothing until a model is actually used.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "DiffusionPrior": "core.priors.diffusion.prior",
    "build_diffusion_prior": "core.priors.diffusion.prior",
    "ModelCard": "core.priors.diffusion.card",
    "CARD_FILENAME": "core.priors.diffusion.card",
    "load_components": "core.priors.diffusion.loading",
    "PriorComponents": "core.priors.diffusion.loading",
    "ExposureConditioner": "core.priors.diffusion.exposure",
    "ExposureEmbedding": "core.priors.diffusion.exposure",
    "build_tiny_model": "core.priors.diffusion.tiny",
    "TinyConfig": "core.priors.diffusion.tiny",
    "sample_balls": "core.priors.diffusion.sampling",
    "BallSamples": "core.priors.diffusion.sampling",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
