"""OracleSimPrior: the ground-truth chrome-ball render of a simulated scene.

An ORACLE: it reads the simulator's ground truth, so it is an upper bound for benchmarks
and a fixture for tests — never a default and meaningless for real captures. Balls show
the scene's exact radiance at each ball centre (the engine's probe-centre approximation)
for the reflected directions at the request's time, tone mapped at request.ev, composited
over the request's background; pixels outside the ball masks equal request.image. Its env
maps are the simulator's ground-truth maps at the probe centres (core.sim.render.render_envmap).
Registered as `oracle` when this module is imported.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import torch
from pydantic import ConfigDict, Field

from core.priors.base import Prior, PriorCapabilities, PriorConfig, PriorError, PriorRequest
from core.priors.known import KnownRadiancePrior
from core.priors.registry import prior_settings, register_prior
from core.sim.render import radiance_fn, render_envmap
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


class OracleSettings(PriorConfig):
    model_config = ConfigDict(arbitrary_types_allowed=True)

    scene: SceneSpec | Path | str = Field(
        description="a SceneSpec, a scene.json, or a capture directory of the simulator"
    )
    supersample: int = Field(1, ge=1, le=8)


@register_prior("oracle")
class OracleSimPrior(Prior):
    """Ground-truth ball renders for a simulated scene (see module docstring)."""

    Config = OracleSettings
    capabilities = PriorCapabilities(envmaps=True)

    def __init__(self, scene: SceneSpec | str | os.PathLike, **settings):
        s = prior_settings(self.name, {"scene": scene, **settings})
        self.scene = load_scene(s.scene)
        self._known = KnownRadiancePrior(radiance_fn(self.scene), supersample=s.supersample,
                                         label=f"simulator ground truth: {self.scene.name}")

    def __call__(self, request: PriorRequest):
        return self._known(request)

    def envmaps(self, centers: torch.Tensor, time: float, height: int) -> torch.Tensor:
        centers = torch.as_tensor(centers, dtype=torch.float32).reshape(-1, 3)
        return torch.stack([render_envmap(self.scene, c, float(time), int(height)) for c in centers])

    def describe(self) -> dict:
        return {
            "name": self.name,
            "oracle": True,
            "note": "upper bound: balls rendered from the simulator's ground truth",
            "scene": self.scene.name,
            "scene_seed": self.scene.seed,
            "supersample": self._known.supersample,
        }
