"""Virtual object insertion: a chrome ball and a diffuse grey sphere lit by the light field,
composited into a frame. This is the picture a person looks at to judge an estimate.

Each inserted object is lit by the env map the field predicts at ITS centre and time: the
mirror ball shows L(c, t, reflected direction); the diffuse sphere (albedo ALBEDO) shows
albedo / pi * E(n), E the irradiance of that env map. Scene geometry in front of an object
(scene depth < object depth) hides it. No shadows are cast onto the scene.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from core.camera import Camera
from core.chrome_ball import BallLayer, ball_reflection_rays, composite, place_probe, render_balls
from core.conventions import equirect_directions, inverse_tonemap, median_valid_depth, tonemap, valid_depth_mask
from core.envmap import irradiance, sample_envmap

ALBEDO = 0.6
DEFAULT_POINTS = ((0.3, 0.7, None), (0.7, 0.7, None))
DEFAULT_DEPTH_FRACTION = 0.7  # of the scene depth at the pixel, when a point gives none
MAX_POINT_DEPTH_M = 1e4  # indoor scenes; beyond this float32 geometry degenerates


class InsertionError(ValueError):
    """A requested insertion point is malformed or cannot be placed."""


@dataclass(frozen=True)
class InsertionPoint:
    u: float  # fraction of the image width, 0 = left edge
    v: float  # fraction of the image height, 0 = top edge
    depth: float | None = None  # planar metres; None -> DEFAULT_DEPTH_FRACTION x scene depth


def parse_points(text: str | None) -> list[InsertionPoint]:
    """'u,v[,depth];...' with u, v in [0, 1] (fractions of width/height), depth in metres."""
    if not text:
        return [InsertionPoint(*p) for p in DEFAULT_POINTS]
    points = []
    for k, item in enumerate(s for s in text.split(";") if s.strip()):
        parts = [p.strip() for p in item.split(",")]
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise InsertionError(f"points[{k}] {item!r}: expected numbers 'u,v[,depth]'") from None
        if len(vals) not in (2, 3) or not all(math.isfinite(x) for x in vals):
            raise InsertionError(f"points[{k}] {item!r}: expected finite 'u,v[,depth]'")
        if not (0.0 <= vals[0] <= 1.0 and 0.0 <= vals[1] <= 1.0):
            raise InsertionError(f"points[{k}] {item!r}: u and v are fractions of the image in [0, 1]")
        if len(vals) == 3 and not 0 < vals[2] <= MAX_POINT_DEPTH_M:
            raise InsertionError(f"points[{k}] {item!r}: depth must be in (0, {MAX_POINT_DEPTH_M:g}] metres")
        points.append(InsertionPoint(vals[0], vals[1], vals[2] if len(vals) == 3 else None))
    if not points:
        raise InsertionError("points: no point given")
    return points


def place_objects(camera: Camera, depth: torch.Tensor, points: list[InsertionPoint], diameter_fraction: float = 0.18):
    """Centres [2N, 3] and radii [2N]: N mirror balls at the points, then N diffuse spheres
    just right of them (2.3 radii along the camera's right axis, same depth)."""
    k = camera.intrinsics
    fallback = median_valid_depth(depth)
    right = camera.c2w[:3, 0].to(torch.float32)
    balls, spheres, radii = [], [], []
    for p in points:
        uv = (min(max(p.u * k.width, 0.5), k.width - 0.5), min(max(p.v * k.height, 0.5), k.height - 0.5))
        z = p.depth
        if z is None:
            s = float(depth[int(uv[1]), int(uv[0])])
            z = DEFAULT_DEPTH_FRACTION * (s if math.isfinite(s) and s > 0 else fallback)
        c, r = place_probe(camera, uv, z, diameter_fraction)
        balls.append(c)
        spheres.append(c + 2.3 * r * right)
        radii.append(r)
    centers = torch.stack(balls + spheres)
    return centers, torch.tensor(radii + radii, dtype=torch.float32)


def insert_objects(frame_ldr: torch.Tensor, depth: torch.Tensor, camera: Camera, envmaps_at, t: float | None,
                   points: list[InsertionPoint], ev: float = 0.0) -> torch.Tensor:
    """Frame [H, W, 3] LDR with the objects composited (LDR). `envmaps_at(xs [P,3], t) -> [P,h,2h,3]`."""
    centers, radii = place_objects(camera, depth, points)
    n = len(points)
    env = envmaps_at(centers, t)  # [2N, h, 2h, 3]
    dirs = equirect_directions(max(8, env.shape[1] // 2))
    irr = torch.stack([irradiance(env[n + i], dirs) for i in range(n)]) * (ALBEDO / math.pi)
    rays = ball_reflection_rays(camera, centers, radii, supersample=2)

    def radiance(directions: torch.Tensor, ball_index: torch.Tensor) -> torch.Tensor:
        out = torch.zeros(directions.shape[0], 3)
        normals = rays.normal
        for b in range(2 * n):
            sel = ball_index == b
            if bool(sel.any()):
                out[sel] = sample_envmap(env[b], directions[sel]) if b < n else sample_envmap(irr[b - n], normals[sel])
        return out

    layer = render_balls(camera, centers, radii, radiance, rays=rays)
    scene_in_front = valid_depth_mask(depth) & (depth < layer.depth)
    keep = (~scene_in_front).to(layer.coverage.dtype)
    layer = BallLayer(layer.radiance * keep[..., None], layer.coverage * keep[None], layer.depth)
    return tonemap(composite(inverse_tonemap(frame_ldr, ev), layer), ev)
