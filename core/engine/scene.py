"""What the loop needs to know about the scene's extent: the field's bounds, the frames with distinct geometry."""
from __future__ import annotations

from dataclasses import replace

import torch

from core.capture.base import Capture
from core.fields import SceneBounds

BOUNDS_MAX_POINTS = 200_000


def scene_bounds(capture: Capture, time_normalisation_frames: int | None = None) -> SceneBounds:
    """The field's box and time range: the capture's unprojected depth (subsampled to
    BOUNDS_MAX_POINTS), its camera positions and its times (see `normalised_time` for
    `time_normalisation_frames`, DistillConfig's setting)."""
    pts = torch.cat([capture.camera(i).unproject(capture.depth[i]).reshape(-1, 3) for i in distinct_geometry(capture)])
    if pts.shape[0] > BOUNDS_MAX_POINTS:
        pts = pts[torch.linspace(0, pts.shape[0] - 1, BOUNDS_MAX_POINTS).long()]
    bounds = SceneBounds.from_points(pts, capture.times, capture.poses[:, :3, 3])
    return normalised_time(bounds, time_normalisation_frames, capture.fps)


def normalised_time(bounds: SceneBounds, frames: int | None, fps: float | None) -> SceneBounds:
    """The authors normalise time as if every clip had `frames` frames (30: t_n = 2 f / 29 - 1):
    the time range becomes [t0, t0 + (frames - 1) / fps] whatever the capture's length (later
    frames extrapolate). None, or a capture without a frame rate: the capture's own range."""
    if frames is None or not fps or fps <= 0:
        return bounds
    return replace(bounds, t1=bounds.t0 + (frames - 1) / float(fps))


def distinct_geometry(capture: Capture) -> list[int]:
    """Frames whose geometry differs: frame 0 alone for a static camera with static depth."""
    return (
        [0]
        if capture.static_camera and capture.num_frames > 0 and _depth_static(capture)
        else list(range(capture.num_frames))
    )


def _depth_static(capture: Capture) -> bool:
    d = torch.nan_to_num(capture.depth, nan=-1.0)
    return bool((d == d[:1]).all())
