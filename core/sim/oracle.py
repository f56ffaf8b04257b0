"""OracleSimPrior: the ground-truth chrome-ball render of a simulated scene.

An ORACLE: it reads the simulator's ground truth, so it is an upper bound for benchmarks
and a fixture for tests — never a default and meaningless for real captures. Balls show
the scene's exact radiance at each ball centre (the engine's probe-centre approximation)
for the reflected directions at the request's time, tone mapped at request.ev, composited
over the request's background; pixels outside the ball masks equal request.image.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from core.priors.base import PriorError, PriorRequest
from core.priors.known import KnownRadiancePrior
from core.sim.render import radiance_fn
from core.sim.spec import SceneSpec


def load_scene(source: SceneSpec | str | os.PathLike) -> SceneSpec:
    """A SceneSpec, a scene.json file, or a capture directory written by the simulator."""
    if isinstance(source, SceneSpec):
        return source
    path = Path(source)
    if path.is_dir():
        index = path / "capture.json"
        if not index.is_file():
            raise PriorError(f"oracle prior: {path} has no capture.json (not a simulated capture)")
        path = path / json.loads(index.read_text()).get("scene", "scene.json")
    if not path.is_file():
        raise PriorError(f"oracle prior: scene spec {path} not found")
    return SceneSpec.model_validate_json(path.read_text())


class OracleSimPrior:
    """Ground-truth ball renders for a simulated scene (see module docstring)."""

    name = "oracle"

    def __init__(self, scene: SceneSpec | str | os.PathLike, supersample: int = 1):
        self.scene = load_scene(scene)
        self._known = KnownRadiancePrior(radiance_fn(self.scene), supersample=supersample, label=f"simulator ground truth: {self.scene.name}")

    def bind(self, capture) -> None:
        return None

    def __call__(self, request: PriorRequest):
        return self._known(request)

    def describe(self) -> dict:
        return {
            "name": self.name,
            "oracle": True,
            "note": "upper bound: balls rendered from the simulator's ground truth",
            "scene": self.scene.name,
            "scene_seed": self.scene.seed,
            "supersample": self._known.supersample,
        }
