"""Training-data export for the diffusion prior ("lightfield-balls" v1, docs/training-data.md).

Per viewpoint: a random camera in the room's free space at a random frame, N ~ U{1..9}
perfect mirror balls placed in the view frustum without touching geometry, the HDR view
with and without balls, the ball mask and the planar depth with balls. Balls are rendered
by the same ray caster (reflected rays see the scene and other balls); they cast no
shadows and add no indirect light, so outside the mask the two images are identical.
Pixels at ball edges are the mean of 3 x 3 sub-samples; the mask stores the coverage.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import torch

from core.camera import Camera
from core.conventions import frame_time, pixel_to_camera_ray
from core.sim.lamp_pixels import subpixel_rays
from core.sim.raycast import MIRROR, sphere_hits
from core.sim.render import context, geometry, render_view, trace
from core.sim.spec import SceneSpec, SceneSpecError
from core.sim.state import intrinsics_of, pose_from_yaw_pitch

TRAINING_FORMAT = "lightfield-balls"
TRAINING_VERSION = 1
MAX_BALLS = 9
CAMERA_ATTEMPTS = 20
BALL_SUPERSAMPLE = 3  # sub-samples per pixel side at ball pixels (anti-aliased edges and mask)


@dataclass(frozen=True)
class BallPlacement:
    """Ranges for random views and balls (metres, degrees, fractions of the image width)."""

    wall_clearance: float = 0.4
    camera_height: tuple[float, float] = (0.9, 1.9)
    pitch_deg: tuple[float, float] = (-25.0, 5.0)
    ball_depth: tuple[float, float] = (0.6, 4.0)
    diameter_fraction: tuple[float, float] = (0.07, 0.22)
    gap: float = 0.01  # minimum clearance between a ball and anything else
    tries_per_ball: int = 60


def _uniform(g: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=g, dtype=torch.float64))


def random_camera(scene: SceneSpec, g: torch.Generator, cfg: BallPlacement) -> Camera:
    geom = geometry(scene)
    k = intrinsics_of(scene.camera, scene.resolution)
    for _ in range(200):
        b = scene.room.boxes[int(torch.randint(len(scene.room.boxes), (), generator=g))]
        pos = [_uniform(g, b.lo[a] + cfg.wall_clearance, b.hi[a] - cfg.wall_clearance) for a in range(3)]
        pos[1] = _uniform(g, *cfg.camera_height)
        p = torch.tensor([pos], dtype=torch.float32)
        if (
            bool(geom.inside_room(p, cfg.wall_clearance * 0.5))
            and float(geom.distance_to_furniture(p)) > cfg.wall_clearance
        ):
            pose = pose_from_yaw_pitch(pos, _uniform(g, -180.0, 180.0), _uniform(g, *cfg.pitch_deg))
            return Camera(k, pose)
    raise SceneSpecError(
        f"scene {scene.name!r}: found no free camera position {cfg.wall_clearance} m from walls and furniture"
    )


def place_balls(
    scene: SceneSpec, camera: Camera, bg_depth: torch.Tensor, count: int, g: torch.Generator, cfg: BallPlacement
):
    """Up to `count` balls (centres [N, 3], radii [N]) inside the frustum, in front of the
    visible surface, clear of walls, furniture, lamps and each other."""
    geom = geometry(scene)
    k = camera.intrinsics
    lamps = [(torch.tensor(e.center), e.radius) for e in scene.emitters if e.kind == "lamp"]
    centers: list[torch.Tensor] = []
    radii: list[float] = []
    for _ in range(count):
        for _ in range(cfg.tries_per_ball):
            frac = _uniform(g, *cfg.diameter_fraction)
            r_px = 0.5 * frac * k.width
            if 2 * (r_px + 1) >= min(k.width, k.height):
                continue  # the ball does not fit in this image
            u = _uniform(g, r_px + 1, k.width - r_px - 1)
            v = _uniform(g, r_px + 1, k.height - r_px - 1)
            surface = float(bg_depth[min(int(v), k.height - 1), min(int(u), k.width - 1)])
            if not math.isfinite(surface):
                continue
            z = _uniform(g, cfg.ball_depth[0], min(cfg.ball_depth[1], surface))
            r = r_px * z / k.fx
            ray = z * pixel_to_camera_ray(
                torch.tensor(u, dtype=torch.float64), torch.tensor(v, dtype=torch.float64), k.fx, k.fy, k.cx, k.cy
            )
            c = (camera.c2w[:3, :3] @ ray + camera.c2w[:3, 3]).to(torch.float32)
            if z - r < 0.1 or z + r > surface - cfg.gap:
                continue
            cp = c[None]
            if not bool(geom.inside_room(cp, r + cfg.gap)) or float(geom.distance_to_furniture(cp)) <= r + cfg.gap:
                continue
            if any(float((c - lc).norm()) <= r + lr + cfg.gap for lc, lr in lamps):
                continue
            if any(float((c - oc).norm()) <= r + orad + cfg.gap for oc, orad in zip(centers, radii)):
                continue
            centers.append(c)
            radii.append(r)
            break
    if not centers:
        return torch.zeros(0, 3), torch.zeros(0)
    return torch.stack(centers), torch.tensor(radii, dtype=torch.float32)


@dataclass
class BallSample:
    image_with_balls: torch.Tensor  # [H, W, 3] linear HDR
    background: torch.Tensor  # [H, W, 3] linear HDR
    ball_mask: torch.Tensor  # [H, W] float coverage in [0, 1]
    depth_with_balls: torch.Tensor  # [H, W] planar metres, NaN where no surface
    centers: torch.Tensor  # [N, 3]
    radii: torch.Tensor  # [N]
    camera: Camera
    frame: int


def render_sample(scene: SceneSpec, index: int, cfg: BallPlacement = BallPlacement()) -> BallSample:
    """One training sample, deterministic in (scene.seed, index)."""
    g = torch.Generator().manual_seed((scene.seed * 2_654_435_761 + index * 97 + 1) & 0x7FFFFFFF)
    for _ in range(CAMERA_ATTEMPTS):  # a camera facing a nearby wall leaves no room for balls
        camera = random_camera(scene, g, cfg)
        frame = int(torch.randint(scene.frames, (), generator=g))
        ctx = context(scene, frame)
        bg = render_view(ctx, camera)
        count = int(torch.randint(1, MAX_BALLS + 1, (), generator=g))
        centers, radii = place_balls(scene, camera, bg.depth, count, g, cfg)
        if len(centers):
            break
    else:
        raise SceneSpecError(f"scene {scene.name!r}, sample {index}: no ball fits in {CAMERA_ATTEMPTS} random views")
    h, w = camera.intrinsics.height, camera.intrinsics.width
    origin, dirs = camera.pixel_rays()
    d = dirs.reshape(-1, 3)
    forward = -camera.c2w[:3, 2].to(torch.float32)
    t_ball = sphere_hits(centers, radii, origin.expand_as(d), d)[0]
    t_bg = bg.depth.reshape(-1) / (d @ forward)
    centre_on_ball = torch.isfinite(t_ball) & ~(t_ball >= torch.nan_to_num(t_bg, nan=float("inf")))
    depth = bg.depth.reshape(-1).clone()
    depth[centre_on_ball] = t_ball[centre_on_ball] * (d[centre_on_ball] @ forward)
    image, coverage = _antialiased_balls(ctx, camera, centers, radii, bg.hdr, centre_on_ball.reshape(h, w))
    return BallSample(image, bg.hdr, coverage, depth.reshape(h, w), centers, radii, camera, frame)


def _antialiased_balls(ctx, camera: Camera, centers, radii, background: torch.Tensor, centre_on_ball: torch.Tensor):
    """Pixels near the balls as the mean of s x s sub-samples (balls + scene); returns the
    image [H, W, 3] and the ball coverage [H, W] in [0, 1]. Pixels with zero coverage keep
    the background exactly."""
    k = camera.intrinsics
    near = torch.nn.functional.max_pool2d(centre_on_ball[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    pix = torch.nonzero(near.reshape(-1)).squeeze(1)
    image = background.reshape(-1, 3).clone()
    coverage = torch.zeros(k.height * k.width)
    if len(pix):
        s = BALL_SUPERSAMPLE
        d = subpixel_rays(camera, pix, s)
        res = trace(ctx, camera.position.to(torch.float32), d, (centers, radii))
        cov = (res.first_kind == MIRROR).float().reshape(len(pix), s * s).mean(1)
        mean = res.radiance.reshape(len(pix), s * s, 3).mean(1)
        hit = cov > 0
        image[pix[hit]] = mean[hit]
        coverage[pix] = cov
    return image.reshape(k.height, k.width, 3), coverage.reshape(k.height, k.width)


def write_sample(sample: BallSample, out: Path, scene_name: str, fps: float) -> None:
    from core.io.depth import write_depth_npz  # noqa: PLC0415 — core.io.depth pulls in av, cv2, OpenEXR, PIL: imported when used
    from core.io.exr import write_exr  # noqa: PLC0415 — core.io.exr pulls in av, cv2, OpenEXR, PIL: imported when used
    from core.io.images import write_png  # noqa: PLC0415 — core.io.images pulls in av, cv2, OpenEXR, PIL: imported when used

    out.mkdir(parents=True, exist_ok=True)
    write_exr(out / "image_with_balls.exr", sample.image_with_balls.numpy())
    write_exr(out / "background.exr", sample.background.numpy())
    write_png(out / "ball_mask.png", sample.ball_mask.numpy())  # 8-bit: round(255 * coverage)
    write_depth_npz(out / "depth_with_balls.npz", sample.depth_with_balls.numpy())
    u, v, _ = sample.camera.project(sample.centers.to(torch.float64))
    meta = {
        "balls": [
            {"center": c.tolist(), "radius": float(r), "pixel": [float(uu), float(vv)]}
            for c, r, uu, vv in zip(sample.centers, sample.radii, u, v)
        ],
        "intrinsics": sample.camera.intrinsics.as_dict(),
        "c2w": sample.camera.c2w.reshape(-1).tolist(),
        "source": {
            "renderer": "lightfield-sim",
            "scene": scene_name,
            "frame": sample.frame,
            "time": frame_time(sample.frame, fps),
        },
    }
    (out / "meta.json").write_text(json.dumps(meta, indent=2))


def write_training_export(
    scene: SceneSpec, out_dir: str | os.PathLike, views: int, cfg: BallPlacement = BallPlacement()
) -> dict:
    """Write `views` samples under out_dir/samples/ and out_dir/dataset.json; returns dataset.json."""
    if views < 1:
        raise SceneSpecError(f"views must be >= 1, got {views}")
    out = Path(out_dir)
    for i in range(views):
        write_sample(render_sample(scene, i, cfg), out / "samples" / f"{i:06d}", scene.name, scene.fps)
    w, h = scene.resolution
    doc = {"format": TRAINING_FORMAT, "version": TRAINING_VERSION, "count": views, "resolution": [h, w]}
    (out / "dataset.json").write_text(json.dumps(doc, indent=2))
    return doc

