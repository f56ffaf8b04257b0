"""Walks through a panorama room with a fault injected where a stage would have made it (issue 62):
the captures of tests/test_fail_safe.py and bench.self_check_flags, with known answers.

A walk: FRAMES frames of a camera crossing a panorama room (core.sim.panorama_room: real texture,
exact depth and poses) while turning, at one exposure, as a capture app exports it (images, 16-bit
depth PNGs, transforms.json: `write_walk`). The faults, each as the files or the job's parameters
carry it: a track that registered nothing (every frame at the first pose), a track that drifts to
`deg` off by its last frame (the first frame anchors the world, as a tracker's does), depth at k
times its true scale, an exposure course the frames were not taken at, and frames from another
room after a cut.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from core.camera import Camera, Intrinsics
from core.sim.panorama_room import PanoramaRoom, ldr_clip, render_clip
from core.sim.state import pose_from_yaw_pitch
from core.tracking.room import assumed_room

FRAMES, WIDTH, HEIGHT, FPS = 8, 64, 48, 4.0
HFOV_DEG = 60.0


def walk_room(panorama: torch.Tensor, other: bool = False) -> PanoramaRoom:
    """The panorama's room; `other`: another room (the panorama turned half a turn and upside down,
    under a warm lamp)."""
    if other:
        panorama = torch.roll(panorama, panorama.shape[1] // 2, dims=1).flip(0) * torch.tensor([1.6, 1.0, 0.5])
    return PanoramaRoom(panorama, assumed_room(), torch.zeros(3))


def walk_poses(n: int = FRAMES) -> list[torch.Tensor]:
    """A 1.3 m walk across the room while turning 40 deg (c2w, float64)."""
    return [pose_from_yaw_pitch((-0.6 + 1.2 * i / (n - 1), 0.1 * math.sin(i / 4), -0.5 * i / (n - 1)),
                                20 - 40 * i / (n - 1), 0).double() for i in range(n)]


def intrinsics() -> Intrinsics:
    return Intrinsics.from_hfov(WIDTH, HEIGHT, HFOV_DEG)


def render_walk(panorama: torch.Tensor, rooms: list[bool]):
    """(frames [T, H, W, 3] in the engine's convention at one exposure, depth [T, H, W], intrinsics,
    true poses) of the walk, frame i in the other room where rooms[i]."""
    poses = walk_poses(len(rooms))
    parts = [render_clip(walk_room(panorama, other), [Camera(intrinsics(), p)], supersample=1)
             for other, p in zip(rooms, poses)]
    return ldr_clip(torch.cat([p[2] for p in parts])), torch.cat([p[1] for p in parts]), intrinsics(), poses


def yawed(pose: torch.Tensor, deg: float) -> torch.Tensor:
    """The pose turned by `deg` about the world's +y."""
    a = math.radians(deg)
    r = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=pose.dtype)
    out = pose.clone()
    out[:3, :3] = r @ pose[:3, :3]
    return out


def drifting(poses: list[torch.Tensor], deg: float) -> list[torch.Tensor]:
    """A track that drifts linearly to `deg` off by the last frame."""
    n = len(poses)
    return [yawed(p, deg * i / max(n - 1, 1)) for i, p in enumerate(poses)]


def write_walk(root: Path, ldr: torch.Tensor, depth: torch.Tensor, intr: Intrinsics, poses) -> Path:
    """The walk as a capture app's export: images/, depth/ (16-bit mm PNG), transforms.json (c2w)."""
    from core.io.depth import encode_depth_png16  # noqa: PLC0415 — core.io pulls in av, cv2, PIL: imported when used
    from core.io.images import encode_png  # noqa: PLC0415 — as above

    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "depth").mkdir(exist_ok=True)
    frames = []
    for i in range(len(ldr)):
        (root / f"images/frame_{i:05d}.png").write_bytes(encode_png(np.asarray(ldr[i])))
        (root / f"depth/frame_{i:05d}.png").write_bytes(encode_depth_png16(np.asarray(depth[i])))
        frames.append({"file_path": f"images/frame_{i:05d}.png", "depth_file_path": f"depth/frame_{i:05d}.png",
                       "transform_matrix": np.asarray(poses[i]).tolist()})
    meta = {"camera_model": "PINHOLE", "fl_x": intr.fx, "fl_y": intr.fy, "cx": intr.cx, "cy": intr.cy,
            "w": intr.width, "h": intr.height, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root
