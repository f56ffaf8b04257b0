"""Where the chrome balls of one step go: stratified probe pixels and depths in front of the scene."""
from __future__ import annotations

import math

import torch

from core.capture.base import Capture
from core.conventions import median_valid_depth, valid_depth_mask
from core.engine.config import DistillConfig


def sample_probes(capture: Capture, frame_index: int, cfg: DistillConfig, gen: torch.Generator):
    """N probe pixels stratified over a grid of cells (one jittered sample per chosen cell)
    and planar depths strictly in front of the scene there.

    Depth ~ U[lo, hi'] x scene depth at the pixel, hi' = min(hi, 1 / (1 + R/z)): R/z is the
    ball's radius-to-depth ratio (fixed by intrinsics and the diameter rule), so the ball's
    far side stays in front of the surface along the ray. Invalid depth at a pixel uses the
    frame's median valid depth. Returns (pixels [N, 2] float64 (u, v), depths [N] float64).
    """
    H, W, n = capture.height, capture.width, cfg.n_probes
    gx = max(1, math.ceil(math.sqrt(n * W / H)))
    gy = max(1, math.ceil(n / gx))
    cells = torch.randperm(gx * gy, generator=gen)[:n]
    jitter = torch.rand(n, 2, generator=gen, dtype=torch.float64)
    u = ((cells % gx).double() + jitter[:, 0]) * (W / gx)
    v = ((cells // gx).double() + jitter[:, 1]) * (H / gy)
    u, v = u.clamp(0.5, W - 0.5), v.clamp(0.5, H - 0.5)
    depth = capture.depth[frame_index]
    d = depth[v.long().clamp(0, H - 1), u.long().clamp(0, W - 1)].double()
    d = torch.where(valid_depth_mask(d), d, torch.full_like(d, median_valid_depth(depth)))
    k = capture.intrinsics
    p = 0.5 * cfg.ball_diameter_fraction * min(H, W)
    r_over_z = p / math.sqrt(k.fx * k.fy + p * p)
    lo, hi = cfg.probe_depth_fraction
    hi = min(hi, 1.0 / (1.0 + r_over_z))
    lo = min(lo, hi)
    frac = lo + (hi - lo) * torch.rand(n, generator=gen, dtype=torch.float64)
    return torch.stack((u, v), -1), d * frac
