"""How much structure an env map has where the capture saw nothing (issue 12, "no rings").

The statistic: the mean absolute log-luminance difference between neighbouring equirect
pixels (horizontal and vertical neighbours, the horizontal ones weighted by sin(theta) so
that the crowded rows near the poles do not dominate), averaged separately over the
directions the camera observed and over those it did not. A field that extrapolates
smoothly has unobserved TV at or below the observed TV; rings from a high-frequency
direction encoding show up as unobserved TV well above it. `observed_directions` says which
directions a probe at the camera saw: those inside the camera's frustum.
"""
from __future__ import annotations

import torch

from core.camera import Camera
from core.conventions import equirect_directions, equirect_pixel_centres
from core.exposure import luminance


def observed_directions(camera: Camera, height: int) -> torch.Tensor:
    """[height, 2 height] bool: equirect directions inside the camera's field of view."""
    d = equirect_directions(height, dtype=torch.float64)
    u, v, z = camera.project(camera.position + d)
    k = camera.intrinsics
    return (z > 0) & (u >= 0) & (u <= k.width) & (v >= 0) & (v <= k.height)


def log_total_variation(env: torch.Tensor, region: torch.Tensor, floor: float = 1e-6) -> float:
    """Mean |neighbour difference| of log luminance of env [h, 2h, 3] over pixel pairs whose
    both pixels lie in `region` [h, 2h] (see module docstring); NaN when there is no pair."""
    h = env.shape[0]
    lum = torch.log(luminance(env.to(torch.float64)).clamp_min(0) + floor)
    theta, _ = equirect_pixel_centres(h, dtype=torch.float64)
    weight_row = torch.sin(theta)  # [h, 1]
    dx = (lum - torch.roll(lum, -1, dims=1)).abs() * weight_row
    in_x = region & torch.roll(region, -1, dims=1)
    dy = (lum[1:] - lum[:-1]).abs()
    in_y = region[1:] & region[:-1]
    wx, wy = (weight_row.expand_as(dx) * in_x), in_y.to(torch.float64)
    total = float((dx * in_x).sum() + (dy * in_y).sum())
    count = float(wx.sum() + wy.sum())
    return total / count if count > 0 else float("nan")


def ring_ratio(env: torch.Tensor, observed: torch.Tensor) -> dict:
    """{"tv_observed", "tv_unobserved", "ratio"} of one env map and its observed mask."""
    tv_o, tv_u = log_total_variation(env, observed), log_total_variation(env, ~observed)
    return {"tv_observed": tv_o, "tv_unobserved": tv_u, "ratio": tv_u / tv_o if tv_o > 0 else float("inf")}
