"""Cameras and room for a multi-frame capture that came without poses: what loading calls.

`resolve_geometry(frames, intrinsics, depth=None, intrinsics_assumed=...)` runs tracking
(core.tracking.track) and returns what the capture needs:
* poses for the frames kept (frames tracking could not register are dropped and listed);
* intrinsics: the given ones, or, when they were ASSUMED and the camera panned at least
  tracking.geometry.min_self_calibration_span_deg, the focal length the pan's bundle adjustment refined
  (within tracking.geometry.self_calibration_hfov_range; recorded as the intrinsics' source);
* depth when none was given, consistent across frames (a world-fixed room, not one that
  turns with the camera): the Manhattan box fitted to the sparse points when structure from
  motion produced them (core.tracking.room), else the documented box room around the first
  camera; for a static camera, nothing (loading keeps its own default).
Everything chosen is in `metadata()` with the evidence, and every fallback is a warning.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from core.camera import Camera, Intrinsics
from core.tracking.config import tracking_config
from core.tracking.geometry import rotation_angle_deg
from core.tracking.room import RoomFitError, assumed_room, box_depth, fit_room
from core.tracking.track import TrackingResult, track_camera

ASSUMED_ROOM_SOURCE = ("assumed:box-room 5x3x4 m (+1 m behind), world-fixed around the first camera 1.5 m above "
                       "the floor, arbitrary scale")
WORLD_FIXED_ROOM_WARNING = ("no depth given: using the assumed box room, fixed in the world around the first camera "
                            "(arbitrary scale); probe placement and reprojection are approximate")


@dataclass
class CaptureGeometry:
    poses: torch.Tensor  # [K, 4, 4] float64 c2w of the kept frames
    keep: list[int]  # indices of the kept input frames
    intrinsics: Intrinsics
    tracking: TrackingResult
    intrinsics_source: str | None = None  # set when tracking changed the intrinsics
    depth: torch.Tensor | None = None  # [K, H, W] when no depth was given and the camera moves
    depth_source: str | None = None
    room: dict | None = None
    warnings: list[str] = field(default_factory=list)

    def metadata(self) -> dict:
        out = {"tracking": self.tracking.summary()}
        if self.intrinsics_source:
            out["intrinsics_source"] = self.intrinsics_source
        if self.room is not None:
            out["room"] = self.room
        return out


def _span_deg(poses: torch.Tensor) -> float:
    R0 = poses[0, :3, :3].numpy()
    return max(rotation_angle_deg(R0.T @ p[:3, :3].numpy()) for p in poses)


def _refined_intrinsics(tr: TrackingResult, k: Intrinsics, warn: list[str]) -> tuple[Intrinsics, str | None]:
    if tr.method != "rotation" or tr.focal_px is None:
        return k, None
    span = _span_deg(tr.poses)
    refined = Intrinsics(tr.focal_px, tr.focal_px * k.fy / k.fx, k.cx, k.cy, k.width, k.height)
    cfg = tracking_config().geometry
    lo, hi = cfg.self_calibration_hfov_range
    if span < cfg.min_self_calibration_span_deg or not (lo <= refined.hfov_deg <= hi):
        warn.append(f"the pan ({span:.0f} deg) did not fix the focal length (refined FOV {refined.hfov_deg:.1f} deg "
                    f"rejected): keeping the assumed {k.hfov_deg:.0f} deg")
        return k, None
    return refined, (f"tracking: focal length refined by the pan's bundle adjustment ({span:.0f} deg pan): "
                     f"{refined.hfov_deg:.1f} deg horizontal FOV instead of the assumed {k.hfov_deg:.0f} deg")


def room_depth(
    tr: TrackingResult, k: Intrinsics, poses: torch.Tensor, warn: list[str]
) -> tuple[torch.Tensor, str, dict]:
    """World-consistent depth [K, H, W] for the kept frames: fitted room, else the assumed one."""
    fit = None
    if tr.points is not None and tr.points.shape[0] >= tracking_config().geometry.min_room_points:
        try:
            fit = fit_room(tr.points.numpy(), poses[:, :3, 3].numpy(), scale_hint=1.0)
        except RoomFitError as exc:
            warn.append(f"room fitting failed ({exc}): using the assumed box room")
    if fit is not None:
        box = fit.box
        size = " x ".join(f"{float(s):.2f}" for s in box.size)
        scale = tr.scale.source if tr.scale else "unknown"
        source = (f"room-fit:Manhattan box {size} m from {tr.points.shape[0]} sparse points "
                  f"(faces: {', '.join(f'{k}={v}' for k, v in fit.sources.items())}; scale from {scale})")
        info = {"source": "fitted", **fit.as_dict()}
    else:
        box = assumed_room()
        source = ASSUMED_ROOM_SOURCE
        info = {"source": "assumed", **box.as_dict()}
        warn.append(WORLD_FIXED_ROOM_WARNING)
    return box_depth(box, [Camera(k, p) for p in poses]), source, info


def resolve_geometry(frames: torch.Tensor, intrinsics: Intrinsics, depth: torch.Tensor | None = None, *,
                     intrinsics_assumed: bool = False, use_pycolmap: bool | None = None) -> CaptureGeometry:
    """See the module docstring. `depth` [T, H, W] is the user's depth (metres) if any."""
    tr = track_camera(frames, intrinsics, depth, refine_focal=intrinsics_assumed, use_pycolmap=use_pycolmap)
    warn = list(tr.warnings)
    k, k_source = _refined_intrinsics(tr, intrinsics, warn)
    geo = CaptureGeometry(tr.poses, list(tr.kept), k, tr, k_source, warnings=warn)
    if depth is None and tr.method not in ("static", "failed:static-fallback"):
        geo.depth, geo.depth_source, geo.room = room_depth(tr, k, tr.poses, warn)
    return geo


def pose_errors(estimated: torch.Tensor, true: torch.Tensor) -> tuple[float, float]:
    """(max rotation error in degrees, max position error) between two pose sets [K, 4, 4]
    that share their world (both relative to their first frame)."""
    rot = max(rotation_angle_deg(e[:3, :3].numpy().T @ t[:3, :3].numpy()) for e, t in zip(estimated, true))
    pos = float(np.linalg.norm((estimated[:, :3, 3] - true[:, :3, 3]).numpy(), axis=1).max())
    return rot, pos if math.isfinite(pos) else math.inf
