"""Helpers for capture tests: nerfstudio captures as apps write them, and panorama-room clips
(real photographic texture, exact poses and depth; core.sim.panorama_room)."""
from __future__ import annotations

import io
import json
import math
import zipfile
from pathlib import Path

import numpy as np
import torch

from core.io.depth import encode_depth_png16
from core.io.images import encode_png

PANORAMA = Path(__file__).resolve().parents[1] / "assets" / "sample_panorama.hdr"


def write_nerfstudio(root: Path, ldr, depth, intr, poses, *, world=np.eye(4),  # noqa: B008 — only read
                     extra=None, with_depth=True) -> Path:
    """A nerfstudio capture: images/, depth/ (16-bit mm PNG), transforms.json (OpenGL c2w)."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "depth").mkdir(exist_ok=True)
    frames = []
    for i in range(len(ldr)):
        (root / f"images/frame_{i:05d}.png").write_bytes(encode_png(np.asarray(ldr[i])))
        fr = {"file_path": f"images/frame_{i:05d}.png", "transform_matrix": (world @ np.asarray(poses[i])).tolist()}
        if with_depth:
            (root / f"depth/frame_{i:05d}.png").write_bytes(encode_depth_png16(np.asarray(depth[i])))
            fr["depth_file_path"] = f"depth/frame_{i:05d}.png"
        frames.append(fr)
    meta = {"camera_model": "PINHOLE", "fl_x": intr.fx, "fl_y": intr.fy, "cx": intr.cx, "cy": intr.cy,
            "w": intr.width, "h": intr.height, "frames": frames, **(extra or {})}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def zip_dir(root: Path, prefix: str = "") -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for p in sorted(root.rglob("*")):
            if p.is_file():
                z.write(p, prefix + p.relative_to(root).as_posix())
    return buf.getvalue()


def panorama_clip(poses, width: int, height: int, hfov: float = 60.0, centre=(0.0, 0.0, 0.0), pano_height=None,
                  supersample: int = 2):
    """(LDR [T,H,W,3], depth [T,H,W], intrinsics) of the bundled panorama on the assumed box room."""
    from core.camera import Camera, Intrinsics
    from core.sim.panorama_room import PanoramaRoom, load_panorama, render_clip
    from core.tracking.room import assumed_room

    intr = Intrinsics.from_hfov(width, height, hfov)
    room = PanoramaRoom(load_panorama(PANORAMA, pano_height), assumed_room(), torch.tensor(centre))
    ldr, depth, _ = render_clip(room, [Camera(intr, p) for p in poses], supersample)
    return ldr, depth, intr


def walk_poses(n: int):
    """A 1.3 m walk across the room while turning 40 deg."""
    from core.sim.state import pose_from_yaw_pitch

    return [pose_from_yaw_pitch((-0.6 + 1.2 * i / (n - 1), 0.1 * math.sin(i / 4), -0.5 * i / (n - 1)),
                                20 - 40 * i / (n - 1), 0) for i in range(n)]


MANIFEST_ROOMS = (("a.hdr", "dev"), ("b.hdr", "test"), ("c.hdr", "extra"), ("d.hdr", "control"))


def write_manifest_rooms(root: Path, panorama_for) -> None:
    """A tiny ../shared/hdri: MANIFEST_ROOMS (three indoor splits and a control), panorama k
    from `panorama_for(k)` ([h, 2h, 3] linear), and their MANIFEST.tsv."""
    from core.io.hdr import write_hdr

    for k, (name, _) in enumerate(MANIFEST_ROOMS):
        write_hdr(root / name, panorama_for(k).numpy())
    (root / "MANIFEST.tsv").write_text("filename\tsplit\n" + "".join(f"{n}\t{s}\n" for n, s in MANIFEST_ROOMS))


def bright_ceiling_room(k: int, h: int = 32) -> torch.Tensor:
    """A flat room with a bright ceiling band of its own height and level per room k."""
    pano = torch.ones(h, 2 * h, 3)
    pano[: 4 + 2 * k] = 3.0 + 4 * k
    return pano
