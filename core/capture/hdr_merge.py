"""HDR recovery for a still-lit scene filmed by a moving camera: every frame's radiance, merged
with what the other frames saw of the same surfaces.

An auto-exposure brackets for free: a lamp that clips in a frame exposed for the shadows is seen
darker in a frame exposed for the lamp, and a shadow lost in the black of a bright frame is
lifted in a dark one. With the light still, every frame's linear radiance (exposure removed) of
one surface point is a reading of one value, each as reliable as its LDR value is far from
clipping and from the black. `merge_frames` therefore replaces each frame's radiance by the
weighted mean, over the frames that see the same point, of their readings (Debevec & Malik's
merge, with the weights of `reading_weight`); where every frame clipped, by the highest of their
estimates (each frame's clip-rule estimate; the frame exposed darkest bounds the source from
below the most). The frames see a point where it projects inside them, in front of the camera,
with a depth within DEPTH_TOLERANCE of their own (the rest is occluded or another surface);
only frames whose views overlap (optical axes within their diagonal field of view) are looked
at. A frame's exposure must already be removed from `linear` (stated or estimated: core.capture
.autoexposure) or be the same for all frames.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from core.capture.base import Capture
from core.capture.highlights import CLIP_LDR

DEPTH_TOLERANCE = 0.05  # relative: a reading from another frame belongs to the same surface within this
DARK_LDR = 0.1  # LDR below which a reading's weight ramps down to 0 (8-bit quantisation and noise)
MIN_WEIGHT = 1e-3  # total weight under which a point counts as seen clipped everywhere


def reading_weight(ldr_luma: torch.Tensor, clipped_fraction: torch.Tensor) -> torch.Tensor:
    """How much a pixel's linear radiance is worth [...]: 0 where it clipped (the share of its area
    that did, squared off), ramping from 0 at black to 1 at DARK_LDR."""
    return (1.0 - clipped_fraction).clamp(0.0, 1.0) ** 2 * (ldr_luma / DARK_LDR).clamp(0.0, 1.0)


def capture_reading_weights(capture: Capture) -> torch.Tensor:
    """`reading_weight` [T, H, W] of a (resized) capture's pixels: the clipped share from its full
    resolution (area-averaged LDR hides which pixels clipped), the luma from its own frames."""
    src = capture.full_resolution or capture
    clipped = (src.frames.amax(-1) >= CLIP_LDR).float()
    if (src.height, src.width) != (capture.height, capture.width):
        clipped = F.interpolate(clipped[:, None], size=(capture.height, capture.width), mode="area")[:, 0]
    f = capture.frames
    luma = 0.2126 * f[..., 0] + 0.7152 * f[..., 1] + 0.0722 * f[..., 2]
    return reading_weight(luma, clipped)


def _overlapping(capture: Capture) -> list[list[int]]:
    """Per frame, the other frames whose optical axes are within the diagonal field of view."""
    k = capture.intrinsics
    diag = math.degrees(2 * math.atan(math.hypot(k.width / (2 * k.fx), k.height / (2 * k.fy))))
    axes = -capture.poses[:, :3, 2].to(torch.float64)  # cameras look along -z
    cos = (axes @ axes.T).clamp(-1.0, 1.0)
    near = torch.rad2deg(torch.acos(cos)) <= diag
    return [[j for j in range(capture.num_frames) if j != i and bool(near[i, j])] for i in range(capture.num_frames)]


def merge_frames(capture: Capture, linear: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Merged radiance [T, H, W, 3] of `capture` (its frames, depth and poses at the resolution of
    `linear` [T, H, W, 3], ev 0) from the readings' `weight` [T, H, W] (`reading_weight`)."""
    T, H, W, _ = linear.shape
    out = linear.clone()
    lin64, w64 = linear.to(torch.float64), weight.to(torch.float64)
    depth = capture.depth.to(torch.float64)
    for i, others in enumerate(_overlapping(capture)):
        pts = capture.camera(i).unproject(capture.depth[i]).reshape(-1, 3).to(torch.float64)  # [P, 3]
        num = lin64[i].reshape(-1, 3) * w64[i].reshape(-1, 1)
        den = w64[i].reshape(-1).clone()
        brightest = lin64[i].reshape(-1, 3).clone()
        for j in others:
            u, v, z = capture.camera(j).project(pts)
            grid = torch.stack([2.0 * u / W - 1.0, 2.0 * v / H - 1.0], -1).reshape(1, 1, -1, 2)
            inside = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H) & torch.isfinite(z)
            grid = torch.where(inside.reshape(1, 1, -1, 1), grid, torch.zeros_like(grid))
            d_j = F.grid_sample(depth[j][None, None].nan_to_num(0.0), grid, mode="nearest", align_corners=False)[
                0, 0, 0
            ]
            same = inside & (d_j > 0) & ((d_j - z).abs() <= DEPTH_TOLERANCE * z.abs())
            if not bool(same.any()):
                continue
            lin_j = F.grid_sample(lin64[j].permute(2, 0, 1)[None], grid, align_corners=False)[0, :, 0].T  # [P, 3]
            w_j = F.grid_sample(w64[j][None, None], grid, align_corners=False)[0, 0, 0] * same
            num += lin_j * w_j[:, None]
            den += w_j
            brighter = same & (lin_j.sum(-1) > brightest.sum(-1))
            brightest = torch.where(brighter[:, None], lin_j, brightest)
        merged = torch.where((den > MIN_WEIGHT)[:, None], num / den.clamp_min(MIN_WEIGHT)[:, None], brightest)
        ok = torch.isfinite(pts).all(-1)
        out[i] = torch.where(ok[:, None], merged, lin64[i].reshape(-1, 3)).reshape(H, W, 3).to(linear.dtype)
    return out
