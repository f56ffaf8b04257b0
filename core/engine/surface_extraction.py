"""The observed surfaces a field carries (core.fields.components.surfaces): the frames' points with the
prior's linear view radiance (its clip rule applied), merged to at most `observed_surfaces`
points on a voxel grid.

* Static lighting: every MAX_SURFACE_VIEWS-th viewpoint of a moving camera (evenly over the
  frames; one view of a static camera), each point with its own frame's radiance, the points of
  all views averaged per voxel; a static camera's radiance is the mean over its frames.
* Lighting that changes, seen by a static camera: the one view's points with, per time knot
  (one per frame, as the field's other time curves), the radiance of the frame nearest the
  knot's time.
* Lighting that changes, seen by a moving camera: every frame's points (up to MAX_TIME_VIEWS
  frames), each cell's radiance at every knot from its readings at the times it was seen and how
  strongly it follows the room's change (core.capture.surface_course): a point's radiance is known
  only when its frame saw it, and holding it for the whole capture would freeze a switch.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from core.capture.base import Capture
from core.capture.surface_course import surface_course
from core.engine.emitter_detection import EmitterSources
from core.envmap import voxel_merge
from core.fields.components.normalization import SceneBounds
from core.fields.kinds.config import MAX_SURFACE_VALUES

MAX_SURFACE_VIEWS = 16  # viewpoints of a moving camera merged into the layer
MAX_TIME_VIEWS = 64  # frames of a moving camera read for each surface's course (changing light)
EMITTER_CLEARANCE = 2.0  # radii around an emitter's centre whose points the layer leaves to it


@dataclass
class SurfacePoints:
    points: torch.Tensor  # [M, 3] metres
    colors: torch.Tensor  # [M, K, 3] linear radiance per time knot

    @property
    def count(self) -> int:
        return self.points.shape[0]

    @property
    def knots(self) -> int:
        return self.colors.shape[1]

    def describe(self) -> dict:
        return {"points": self.count, "knots": self.knots}


def observed_surfaces(capture: Capture, view_radiance, bounds: SceneBounds, *, max_points: int, uses_time: bool,
                      knots: int, emitters: EmitterSources | None = None) -> SurfacePoints | None:
    """The layer's points for a capture (see the module docstring); `view_radiance(i)` is frame
    i's linear radiance [H, W, 3] at the capture's resolution; points within EMITTER_CLEARANCE
    radii of an emitter are left out (the field's emitters hold those lamps, energy exact); None
    when there is nothing to keep."""
    if max_points < 1:
        return None
    knots = knots if uses_time else 1
    max_points = min(max_points, MAX_SURFACE_VALUES // knots)
    if uses_time and not capture.static_camera:
        return _moving_surfaces(capture, view_radiance, bounds, max_points, knots, emitters)
    if capture.static_camera:
        points = _frame_points(capture, 0)
        if uses_time:
            frames = capture.nearest_frames(bounds.knot_times(knots)).tolist()  # one per knot
            colors = torch.stack([_frame_colors(view_radiance, f) for f in frames], 1)
        else:
            colors = torch.stack([_frame_colors(view_radiance, f) for f in range(capture.num_frames)]).mean(0)[:, None]
    else:
        frames = capture.spread_frames(MAX_SURFACE_VIEWS).tolist()
        points = torch.cat([_frame_points(capture, f) for f in frames])
        colors = torch.cat([_frame_colors(view_radiance, f) for f in frames])[:, None]
    ok = _kept(points, colors, emitters)
    if not bool(ok.any()):
        return None
    points, colors = voxel_merge(points[ok].double(), colors[ok].double(), max_points)
    return SurfacePoints(points.float(), colors.float().clamp_min(0.0))


def _moving_surfaces(capture: Capture, view_radiance, bounds: SceneBounds, max_points: int, knots: int,
                     emitters: EmitterSources | None) -> SurfacePoints | None:
    frames = capture.spread_frames(MAX_TIME_VIEWS).tolist()
    points = [_frame_points(capture, f) for f in frames]
    view = torch.cat([torch.full((p.shape[0],), v, dtype=torch.long) for v, p in enumerate(points)])
    points = torch.cat(points)
    colors = torch.cat([_frame_colors(view_radiance, f) for f in frames])
    ok = _kept(points, colors[:, None], emitters)
    if not bool(ok.any()):
        return None
    view_times = capture.times.double()[frames]
    points, colors = surface_course(points[ok], colors[ok], view[ok], view_times, bounds.knot_times(knots),
                                    max_points)
    return SurfacePoints(points, colors.clamp_min(0.0))


def _kept(points: torch.Tensor, colors: torch.Tensor, emitters: EmitterSources | None) -> torch.Tensor:
    """[N] bool: finite points and colours [N, K, 3], outside EMITTER_CLEARANCE radii of every emitter."""
    ok = torch.isfinite(points).all(-1) & torch.isfinite(colors).all((-1, -2))
    if emitters is not None and emitters.count:
        gap = (
            torch.cdist(points.double(), emitters.centres.double()) - EMITTER_CLEARANCE * emitters.radii.double()[None]
        )
        ok &= ~(gap < 0).any(-1)
    return ok


def _frame_points(capture: Capture, i: int) -> torch.Tensor:
    return capture.camera(i).unproject(capture.depth[i].float()).reshape(-1, 3).float()


def _frame_colors(view_radiance, i: int) -> torch.Tensor:
    return torch.as_tensor(view_radiance(i), dtype=torch.float32).reshape(-1, 3)
