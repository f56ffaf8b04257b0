"""What the loop needs to know about the scene's extent: the field's bounds, the frames with distinct geometry."""
from __future__ import annotations

import torch

from core.capture.base import Capture
from core.fields import SceneBounds

BOUNDS_MAX_POINTS = 200_000


def scene_bounds(capture: Capture) -> SceneBounds:
    """The field's box and time range: the capture's unprojected depth (subsampled to
    BOUNDS_MAX_POINTS), its camera positions and its times."""
    pts = torch.cat([capture.camera(i).unproject(capture.depth[i]).reshape(-1, 3) for i in distinct_geometry(capture)])
    if pts.shape[0] > BOUNDS_MAX_POINTS:
        pts = pts[torch.linspace(0, pts.shape[0] - 1, BOUNDS_MAX_POINTS).long()]
    return SceneBounds.from_points(pts, capture.times, capture.poses[:, :3, 3])


def distinct_geometry(capture: Capture) -> list[int]:
    """Frames whose geometry differs: frame 0 alone for a static camera with static depth."""
    return [0] if capture.static_camera and capture.num_frames > 0 and _depth_static(capture) else list(range(capture.num_frames))


def _depth_static(capture: Capture) -> bool:
    d = torch.nan_to_num(capture.depth, nan=-1.0)
    return bool((d == d[:1]).all())
