"""Where the web page's probes go: a clicked pixel + a depth along its ray -> a world point.

The page sends pixel positions as fractions (u, v) of the frame's width and height, so the
same click means the same ray at any display size. A probe's default depth puts a ball of
the size the page draws (INSERTION_DIAMETER_FRACTION) just in front of the surface seen at
that pixel: for a ball whose radius is k times its planar depth z (core.chrome_ball.ball_radius
makes k constant for a given image), the ball reaches planar depth z (1 + k), so it clears a
surface at z_s when z <= z_s / (1 + k). We keep a further FRONT_GAP of that radius free.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from core.chrome_ball import BallPlacementError, place_probe

# The ball size core.insertion draws (its place_objects default); the default
# depth must leave room for a ball of this size.
INSERTION_DIAMETER_FRACTION = 0.18
FRONT_GAP = 0.25  # extra clearance in ball radii between the ball and the surface
SURFACE_WINDOW = 2  # pixels each side searched when the clicked pixel has no valid depth
MAX_PROBE_DEPTH_M = 1.0e4


class ProbeError(ValueError):
    """A probe request is out of range (the message names the field)."""


@dataclass(frozen=True)
class ProbePlacement:
    u: float | None  # fraction of the width (outside [0, 1]: off the frame; None: behind the camera)
    v: float | None  # fraction of the height
    frame_index: int
    visible: bool  # in front of the camera and inside the frame
    surface_depth: float | None  # planar metres at the pixel (None: no valid depth near it)
    default_depth: float  # just in front of the surface
    depth: float  # planar depth of the probe centre (<= 0: behind the camera)
    x: tuple[float, float, float]  # world position of the probe centre (metres)
    radius: float  # radius of the ball the page draws there (metres; 0 when behind the camera)


def check_fraction(value: float, name: str) -> float:
    if not (math.isfinite(value) and 0.0 <= value <= 1.0):
        raise ProbeError(f"{name} must be a fraction of the frame in [0, 1], got {value}")
    return float(value)


def pixel_of(u: float, v: float, width: int, height: int) -> tuple[float, float]:
    """Continuous pixel coordinates of fractions (u, v), kept inside the outermost pixel centres
    (as core.insertion does, so the page's probe and its rendered ball coincide)."""
    return min(max(u * width, 0.5), width - 0.5), min(max(v * height, 0.5), height - 0.5)


def surface_depth(depth: np.ndarray, px: float, py: float, window: int = SURFACE_WINDOW) -> float | None:
    """Planar depth [H, W] at continuous pixel (px, py): the pixel's own value when valid,
    else the median of the valid values within `window` pixels, else None."""
    h, w = depth.shape
    col, row = min(int(px), w - 1), min(int(py), h - 1)
    value = float(depth[row, col])
    if math.isfinite(value) and value > 0:
        return value
    patch = depth[max(row - window, 0):row + window + 1, max(col - window, 0):col + window + 1]
    valid = patch[np.isfinite(patch) & (patch > 0)]
    return float(np.median(valid)) if valid.size else None


def fallback_depth(depth: np.ndarray) -> float:
    """Median valid depth of the frame, or 2 m for a frame without any (as insertion does)."""
    valid = depth[np.isfinite(depth) & (depth > 0)]
    return float(np.median(valid)) if valid.size else 2.0


def radius_ratio(camera, diameter_fraction: float = INSERTION_DIAMETER_FRACTION) -> float:
    """k = R / z of a ball drawn at `diameter_fraction` of the frame (independent of z)."""
    k = camera.intrinsics
    _, r = place_probe(camera, (k.width / 2.0, k.height / 2.0), 1.0, diameter_fraction)
    return float(r)


def front_of_surface(surface: float, k: float) -> float:
    return surface / (1.0 + (1.0 + FRONT_GAP) * k)


def place(preview, u: float, v: float, t: float, depth: float | None = None) -> ProbePlacement:
    """Probe at fractions (u, v) of the frame nearest t, at planar `depth` (default: just in
    front of the surface there)."""
    u, v = check_fraction(u, "u"), check_fraction(v, "v")
    if depth is not None and not (math.isfinite(depth) and 0.0 < depth <= MAX_PROBE_DEPTH_M):
        raise ProbeError(f"depth must be a planar distance in (0, {MAX_PROBE_DEPTH_M:g}] metres, got {depth}")
    index = preview.nearest_frame(t)
    camera = preview.camera(index)
    px, py = pixel_of(u, v, preview.width, preview.height)
    depth_map = preview.depth_map(index)
    surface = surface_depth(depth_map, px, py)
    k = radius_ratio(camera)
    default = front_of_surface(surface if surface is not None else fallback_depth(depth_map), k)
    used = default if depth is None else float(depth)
    try:
        centre, radius = place_probe(camera, (px, py), used, INSERTION_DIAMETER_FRACTION)
    except BallPlacementError as exc:
        raise ProbeError(f"depth: {exc}") from None
    return ProbePlacement(u=u, v=v, frame_index=index, visible=True, surface_depth=surface, default_depth=default,
                          depth=used, x=tuple(float(c) for c in centre.tolist()), radius=float(radius))


def locate(preview, x, t: float) -> ProbePlacement:
    """Where a probe fixed in the world at x appears in the frame nearest t. The page keeps
    probes fixed in the world, so with a moving camera a probe stays put as time changes."""
    point = tuple(float(c) for c in x)
    if len(point) != 3 or not all(math.isfinite(c) for c in point):
        raise ProbeError(f"x must be three finite numbers (metres), got {x}")
    index = preview.nearest_frame(t)
    camera = preview.camera(index)
    pu, pv, pz = (float(a[0]) for a in camera.project(torch.tensor([point], dtype=torch.float64)))
    in_front = pz > 0
    u, v = (pu / preview.width, pv / preview.height) if in_front else (None, None)
    visible = in_front and 0.0 <= u <= 1.0 and 0.0 <= v <= 1.0
    depth_map = preview.depth_map(index)
    surface = surface_depth(depth_map, *pixel_of(u, v, preview.width, preview.height)) if visible else None
    k = radius_ratio(camera)
    default = front_of_surface(surface if surface is not None else fallback_depth(depth_map), k)
    return ProbePlacement(u=u, v=v, frame_index=index, visible=visible, surface_depth=surface, default_depth=default,
                          depth=pz, x=point, radius=k * pz if in_front else 0.0)
