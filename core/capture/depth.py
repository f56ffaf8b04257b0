"""Depth of a capture when the user gave none, or gave an incomplete one: the assumed box
room and hole filling, and the validation of given depth (the per-frame median stand-in is
core.conventions.median_valid_depth: the previews use it too)."""
from __future__ import annotations

import math

import torch

from core.camera import Intrinsics
from core.capture.base import CaptureError
from core.conventions import pixel_to_camera_ray, valid_depth_mask

# Depth with fewer valid pixels than this (per frame) is hole-filled with a warning.
MIN_VALID_DEPTH_FRACTION = 0.5
ASSUMED_DEPTH_SOURCE = "assumed:box-room 5x3x4 m, camera 1.5 m above floor, arbitrary scale"


# ---------------------------------------------------------------------------------------
def assumed_box_depth(intr: Intrinsics, half_width: float = 2.5, floor: float = 1.5,
                      ceiling: float = 1.5, back: float = 4.0) -> torch.Tensor:
    """Planar depth [H, W] of a box room around a camera looking along -z at its origin.

    The ray through a pixel is s * (x, y, -1) with planar depth s; it hits the floor at
    s = floor / -y, the ceiling at ceiling / y, the side walls at half_width / |x| and the
    back wall at s = back; the nearest positive hit is the depth.
    """
    v, u = torch.meshgrid(torch.arange(intr.height, dtype=torch.float64) + 0.5,
                          torch.arange(intr.width, dtype=torch.float64) + 0.5, indexing="ij")
    ray = pixel_to_camera_ray(u, v, intr.fx, intr.fy, intr.cx, intr.cy)
    x, y = ray[..., 0], ray[..., 1]
    inf = torch.full_like(x, math.inf)
    s = torch.full_like(x, back)
    s = torch.minimum(s, torch.where(y < 0, floor / (-y).clamp_min(1e-12), inf))
    s = torch.minimum(s, torch.where(y > 0, ceiling / y.clamp_min(1e-12), inf))
    s = torch.minimum(s, torch.where(x.abs() > 0, half_width / x.abs().clamp_min(1e-12), inf))
    return s.float()


def fill_depth_holes(depth: torch.Tensor, max_iters: int = 64) -> torch.Tensor:
    """Fill invalid pixels of [H, W] depth by repeated 3x3 mean of valid neighbours (a
    diffusion fill). Keeps valid pixels unchanged. Requires at least one valid pixel."""
    d = depth.clone()
    valid = valid_depth_mask(d)
    kernel = torch.ones(1, 1, 3, 3, dtype=d.dtype)
    for _ in range(max_iters):
        if valid.all():
            break
        num = torch.nn.functional.conv2d(torch.where(valid, d, 0)[None, None], kernel, padding=1)[0, 0]
        cnt = torch.nn.functional.conv2d(valid.to(d.dtype)[None, None], kernel, padding=1)[0, 0]
        grow = ~valid & (cnt > 0)
        d = torch.where(grow, num / cnt.clamp_min(1), d)
        valid = valid | grow
    if not valid.all():  # disconnected leftovers: the median of what we have
        d = torch.where(valid, d, d[valid].median())
    return d



def check_depth_shape(shape: tuple[int, ...], T: int, H: int, W: int) -> None:
    """CaptureError(field='depth') unless depth of `shape` fits T frames of W x H: [H, W] or
    [1 or T, H, W] (one map for every frame, or one per frame)."""
    if len(shape) not in (2, 3):
        raise CaptureError("depth", f"expected [T, H, W] or [H, W], got shape {tuple(shape)}")
    if tuple(shape[-2:]) != (H, W):
        raise CaptureError("depth", f"depth size {shape[-1]}x{shape[-2]} does not match frame size {W}x{H}")
    maps = shape[0] if len(shape) == 3 else 1
    if maps not in (1, T):
        raise CaptureError("depth", f"{maps} depth maps for {T} frames (give 1 or {T})")


def resolve_depth(depth, T: int, H: int, W: int, intr: Intrinsics, source: str | None,
                  warn: list[str]) -> tuple[torch.Tensor, str]:
    """Per-frame depth [T, H, W] (NaN invalid) from the given depth, holes filled where most of
    a frame is invalid, or the assumed box room when none is given; and its source label."""
    if depth is None:
        warn.append("no depth given: using the assumed box-room geometry (arbitrary scale); "
                    "probe placement and reprojection are approximate")
        return assumed_box_depth(intr).expand(T, H, W).clone(), ASSUMED_DEPTH_SOURCE
    d = torch.as_tensor(depth, dtype=torch.float32)
    check_depth_shape(tuple(d.shape), T, H, W)
    d = (d[None] if d.ndim == 2 else d).expand(T, H, W).clone()
    valid = valid_depth_mask(d)
    if not valid.any():
        raise CaptureError("depth", "no valid pixels (all non-finite or <= 0)")
    filled = []
    for i in range(T):
        frac = float(valid[i].float().mean())
        if frac == 0.0:
            raise CaptureError("depth", f"frame {i} has no valid depth pixels")
        if frac < MIN_VALID_DEPTH_FRACTION:
            filled.append(i)
            d[i] = fill_depth_holes(d[i])
    if filled:
        warn.append(
            f"depth mostly invalid in {len(filled)} frame(s) (< {MIN_VALID_DEPTH_FRACTION:.0%} valid): holes filled by "
            "diffusion"
        )
    d = torch.where(valid_depth_mask(d), d, torch.full_like(d, float("nan")))
    return d, source or "file"


def surface_normals(points: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """Unit normals [H, W, 3] of a frame's unprojected points [H, W, 3], turned towards the
    camera centre [3] that saw them (the side the frame observed). Along each image axis the
    one-sided difference with the smaller step is used, so a pixel on a depth edge takes the
    tangent of its own surface instead of the jump to the one behind it. NaN where a point or
    both of its neighbours along an axis are invalid."""
    def tangent(axis: int) -> torch.Tensor:
        n = points.shape[axis]
        fwd = torch.diff(points, dim=axis, append=points.narrow(axis, n - 1, 1))  # last row: 0
        bwd = torch.diff(points, dim=axis, prepend=points.narrow(axis, 0, 1))  # first row: 0
        f_len = torch.nan_to_num(fwd.norm(dim=-1, keepdim=True), nan=math.inf)
        b_len = torch.nan_to_num(bwd.norm(dim=-1, keepdim=True), nan=math.inf)
        f_len = torch.where(f_len == 0, math.inf, f_len)  # a border's missing side
        b_len = torch.where(b_len == 0, math.inf, b_len)
        return torch.where(f_len <= b_len, fwd, bwd)

    n = torch.cross(tangent(1), tangent(0), dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    facing = (n * (centre.to(points.dtype) - points)).sum(-1, keepdim=True)
    return torch.where(facing < 0, -n, n)
