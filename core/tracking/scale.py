"""Metres for a reconstruction whose scale is arbitrary (structure from motion).

In order of preference (the chosen rule is recorded as `scale_source`):
1. `depth`: the user gave depth maps: scale = median over observations of the depth map at
   the observed pixel / the point's planar depth in that camera (robust to holes/outliers);
2. `floor`: the sparse points contain a floor plane (core.tracking.room): scale puts the
   first camera ASSUMED_FLOOR_BELOW_M (1.5 m, the documented assumption) above it;
3. `room-assumption`: the median planar depth of the points the first camera sees equals
   the median depth of the documented box room seen from that camera.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from core.camera import Camera, Intrinsics
from core.conventions import valid_depth_mask
from core.tracking.config import tracking_config
from core.tracking.room import ASSUMED_FLOOR_BELOW_M, RoomFitError, assumed_room, fit_room


@dataclass(frozen=True)
class ScaleEstimate:
    scale: float  # metres per reconstruction unit
    source: str  # "depth" | "floor" | "room-assumption"
    evidence: dict = field(default_factory=dict)


def _planar_depths(
    poses: np.ndarray, k: Intrinsics, points: np.ndarray, observations
) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(frame position, pixels [M, 2], planar depth of the observed points [M]) per camera."""
    out = []
    pts = torch.from_numpy(points)
    for n, (_, uv, idx) in enumerate(observations):
        if len(idx) == 0:
            continue
        _, _, z = Camera(k, torch.from_numpy(poses[n])).project(pts[idx])
        out.append((n, uv, z.numpy()))
    return out


def scale_from_depth(
    poses, k: Intrinsics, points, observations, depth: torch.Tensor, frames: list[int]
) -> ScaleEstimate | None:
    """`depth` [T, H, W] at full resolution; `frames` maps observation positions to depth rows."""
    T, H, W = depth.shape
    sx, sy = W / k.width, H / k.height
    ratios = []
    for n, uv, z in _planar_depths(poses, k, points, observations):
        d = depth[frames[n]]
        r = np.clip((uv[:, 1] * sy).astype(int), 0, H - 1)
        c = np.clip((uv[:, 0] * sx).astype(int), 0, W - 1)
        dz = d[torch.from_numpy(r), torch.from_numpy(c)].double().numpy()
        ok = valid_depth_mask(torch.from_numpy(dz)).numpy() & (z > 0)
        ratios.append(dz[ok] / z[ok])
    ratios = np.concatenate(ratios) if ratios else np.zeros(0)
    if len(ratios) < tracking_config().geometry.min_depth_samples:
        return None
    s = float(np.median(ratios))
    spread = float(1.4826 * np.median(np.abs(ratios - s)) / s)
    return ScaleEstimate(s, "depth", {"samples": int(len(ratios)), "relative_spread": round(spread, 4)})


def scale_from_room(poses, k: Intrinsics, points, observations) -> ScaleEstimate:
    """The floor rule when the points show a floor, else the room-assumption rule."""
    try:
        fit = fit_room(points, poses[:, :3, 3])
    except RoomFitError:
        fit = None
    if fit is not None and fit.floor_found:
        q0 = poses[0, :3, 3] @ fit.box.axes.numpy()
        height = float(q0[1] - fit.box.lo[1])
        if height > 0:
            return ScaleEstimate(
                ASSUMED_FLOOR_BELOW_M / height,
                "floor",
                {"camera_height_units": round(height, 6), "assumed_camera_height_m": ASSUMED_FLOOR_BELOW_M},
            )
    first = [z for n, _, z in _planar_depths(poses, k, points, observations) if n == 0]
    z = first[0][first[0] > 0] if first else np.zeros(0)
    if len(z) == 0:  # the first camera sees no point: use all cameras' points
        z = np.concatenate([zz[zz > 0] for _, _, zz in _planar_depths(poses, k, points, observations)] or [np.ones(1)])
    room = assumed_room().depth(Camera(k, torch.eye(4, dtype=torch.float64)))
    s = float(room.median()) / float(np.median(z))
    return ScaleEstimate(s, "room-assumption", {"median_point_depth_units": round(float(np.median(z)), 6),
                                                "median_assumed_depth_m": round(float(room.median()), 4)})


def apply_scale(poses: np.ndarray, points: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be finite and > 0, got {scale}")
    out = poses.copy()
    out[:, :3, 3] *= scale
    return out, points * scale
