"""A prior that knows the answer: balls rendered exactly from a known radiance function.

Used by tests (the distillation loop must recover a known field) and as the base of the
simulator's oracle prior. Never a default for real captures.
"""
from __future__ import annotations

from typing import Any, Callable

import torch
from pydantic import ConfigDict, Field

from core.chrome_ball import BallRays, ball_reflection_rays, composite, render_balls
from core.conventions import equirect_directions, equirect_width, inverse_tonemap, tonemap
from core.priors.base import Prior, PriorCapabilities, PriorConfig, PriorRequest
from core.priors.registry import prior_settings, register_prior

RadianceXTD = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
BallRadiance = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def request_rays(request: PriorRequest, supersample: int = 1) -> BallRays:
    """The engine passes its ball rays in `extras['ball_rays']` so masks match exactly."""
    rays = request.extras.get("ball_rays")
    if isinstance(rays, BallRays):
        return rays
    p = request.probes
    return ball_reflection_rays(p.camera, p.centers, p.radii, supersample=supersample)


def request_background(request: PriorRequest) -> torch.Tensor:
    """Linear ball-free frame [H, W, 3]: `extras['frame_linear']` when the engine gives it,
    else the request image linearised at its ev (exact outside the balls; at anti-aliased
    ball edges it still contains a little of the current ball)."""
    bg = request.extras.get("frame_linear")
    if bg is not None:
        return bg.to(request.image.dtype)
    return inverse_tonemap(request.image.permute(1, 2, 0), request.ev)


def ball_target(request: PriorRequest, radiance: BallRadiance, supersample: int = 1) -> torch.Tensor:
    """Pseudo-target [3, H, W]: balls rendered with `radiance(directions, ball_index)`,
    composited over the background and tone mapped at request.ev; request.image outside."""
    p = request.probes
    rays = request_rays(request, supersample)
    with torch.no_grad():
        layer = render_balls(p.camera, p.centers, p.radii, radiance, rays=rays)
        out = tonemap(composite(request_background(request), layer), request.ev).permute(2, 0, 1)
        inside = layer.total_coverage > 0
        return torch.where(inside[None], out.to(request.image.dtype), request.image)


class KnownRadianceSettings(PriorConfig):
    model_config = ConfigDict(arbitrary_types_allowed=True)

    fn: Callable[..., Any] = Field(description="fn(x [B,3], t [B], d [B,3]) -> radiance [B,3] >= 0")
    supersample: int = Field(1, ge=1, le=8)
    label: str = "known radiance function"


@register_prior("known")
class KnownRadiancePrior(Prior):
    """Renders the balls exactly from fn(x [B,3], t [B], d [B,3]) -> radiance [B,3] >= 0,
    evaluated at each ball's centre (the probe-centre approximation the engine also uses)."""

    Config = KnownRadianceSettings
    capabilities = PriorCapabilities(envmaps=True, envmaps_anywhere=True)

    def __init__(self, fn: RadianceXTD, **settings):
        s = prior_settings(self.name, {"fn": fn, **settings})
        self.fn, self.supersample, self.label = s.fn, s.supersample, s.label

    def __call__(self, request: PriorRequest) -> torch.Tensor:
        p = request.probes
        centers = torch.as_tensor(p.centers, dtype=torch.float32)

        def radiance(directions: torch.Tensor, ball_index: torch.Tensor) -> torch.Tensor:
            x = centers[ball_index]
            t = torch.full((directions.shape[0],), float(p.time), dtype=torch.float32)
            return self.fn(x, t, directions).to(torch.float32)

        return ball_target(request, radiance, self.supersample)

    def envmaps(self, centers: torch.Tensor, time: float, height: int) -> torch.Tensor:
        """fn at each centre for every equirect direction (core.conventions layout)."""
        centers = torch.as_tensor(centers, dtype=torch.float32).reshape(-1, 3)
        dirs = equirect_directions(int(height)).reshape(-1, 3).to(torch.float32)
        n, k = centers.shape[0], dirs.shape[0]
        x = centers[:, None].expand(n, k, 3).reshape(-1, 3)
        d = dirs[None].expand(n, k, 3).reshape(-1, 3)
        t = torch.full((n * k,), float(time), dtype=torch.float32)
        with torch.no_grad():
            out = self.fn(x, t, d).to(torch.float32)
        return out.reshape(n, int(height), equirect_width(int(height)), 3)

    def describe(self) -> dict:
        return {"name": self.name, "source": self.label, "supersample": self.supersample}
