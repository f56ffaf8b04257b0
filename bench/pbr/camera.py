"""A phone's camera in an AR session, and the four uploads of a session.

No privileged camera curve: each frame's linear radiance is exposed by a lagging auto-exposure
(the exposure follows a smoothed metered mean, in stops), gets sensor noise (shot + read, in
linear light, before the curve), is encoded with the sRGB curve (core.transfer.SRGB), quantised
to 8 bits and compressed with H.264 (core.io.video.write_video). The app knows its poses
(camera-to-world, row-major, the product's convention), intrinsics and each frame's exposure
(`frame_ev`, in stops: what ARKit's exposure duration x ISO gives); depth is either the renderer's
planar depth (a perfect sensor) or LiDAR-like (a 4x coarser grid, noise, holes, upsampled nearest
as an app does).

Variants (`VARIANTS`): `full-ar` (video, poses, intrinsics, depth, frame_ev), `monocular` (no
depth), `lidar` (LiDAR-like depth), `no-frame-ev` (full AR but frame_ev withheld: the product must
tell the exposure from the light).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

VARIANTS = ("full-ar", "monocular", "lidar", "no-frame-ev")
MID_GREY = 0.18  # the auto-exposure meters the frame's mean linear luminance to this
METER_CAP = 8.0  # metered pixels are capped at this x the frame's median (a lamp must not set it alone)
AE_SPEED = 0.3  # the exposure moves this fraction of the way to its goal per frame (it lags)
FULL_WELL = 1500.0  # electrons at the clip point: shot noise variance = signal / FULL_WELL
READ_NOISE = 0.002  # read noise, fraction of the clip point (linear)
CRF = 20
LIDAR_GRID = (256, 192)  # ARKit's sceneDepth; frames smaller than it get a 4x coarser grid
LIDAR_RANGE_M = 5.0
LIDAR_DROPOUT = 0.03


def luminance(rgb: np.ndarray) -> np.ndarray:
    return 0.2126 * rgb[..., 0] + 0.7152 * rgb[..., 1] + 0.0722 * rgb[..., 2]


def auto_exposure(hdr: np.ndarray, speed: float = AE_SPEED) -> list[float]:
    """Each frame's exposure in stops for linear frames [T, H, W, 3]: the goal meters the frame's
    mean luminance (pixels capped at METER_CAP x its median) to MID_GREY, and the exposure moves
    `speed` of the way to it per frame (frame 0 starts at its goal)."""
    evs: list[float] = []
    ev = None
    for frame in hdr:
        y = np.nan_to_num(luminance(frame.astype(np.float64)), nan=0.0).clip(min=0.0)
        cap = METER_CAP * max(float(np.median(y)), 1e-9)
        goal = math.log2(MID_GREY / max(float(np.minimum(y, cap).mean()), 1e-9))
        ev = goal if ev is None else ev + speed * (goal - ev)
        evs.append(ev)
    return evs


def sensor(hdr: np.ndarray, ev: float, seed: int) -> np.ndarray:
    """8-bit sRGB code values [H, W, 3] (uint8) of one linear frame exposed at `ev` stops."""
    import torch

    from core.transfer import SRGB

    rng = np.random.default_rng(seed)
    signal = np.clip(hdr.astype(np.float64), 0.0, None) * 2.0**ev
    sigma = np.sqrt(np.minimum(signal, 1.0) / FULL_WELL + READ_NOISE**2)
    noisy = np.clip(signal + sigma * rng.standard_normal(signal.shape), 0.0, 1.0)
    code = SRGB.from_linear(torch.from_numpy(noisy)).numpy()
    return np.round(code * 255.0).clip(0, 255).astype(np.uint8)


def lidar_grid(width: int, height: int) -> tuple[int, int]:
    gw, gh = LIDAR_GRID
    return (gw, gh) if width >= gw and height >= gh else (max(width // 4, 1), max(height // 4, 1))


def lidar_depth(depth: np.ndarray, seed: int) -> np.ndarray:
    """LiDAR-like planar depth [T, H, W] from the renderer's [T, H, W]: sampled on a coarser grid
    (the median of each cell), noise (0.5 cm + 1 % of the depth), holes (beyond LIDAR_RANGE_M, at
    depth edges where a cell spans more than 10 %, LIDAR_DROPOUT of the cells at random, and a
    blob per frame), then upsampled nearest to the frame's size, NaN where unknown."""
    t, h, w = depth.shape
    gw, gh = lidar_grid(w, h)
    rng = np.random.default_rng(seed)
    rows = (np.arange(gh + 1) * h / gh).astype(int)
    cols = (np.arange(gw + 1) * w / gw).astype(int)
    out = np.empty((t, h, w), np.float32)
    for i in range(t):
        low = np.full((gh, gw), np.nan)
        spread = np.zeros((gh, gw))
        for r in range(gh):
            for c in range(gw):
                cell = depth[i, rows[r]:rows[r + 1], cols[c]:cols[c + 1]]
                ok = cell[np.isfinite(cell)]
                if ok.size:
                    low[r, c] = np.median(ok)
                    spread[r, c] = (ok.max() - ok.min()) / max(ok.min(), 1e-6)
        low = low + (0.005 + 0.01 * low) * rng.standard_normal(low.shape)
        holes = (low > LIDAR_RANGE_M) | (spread > 0.1) | (rng.random(low.shape) < LIDAR_DROPOUT)
        br, bc = rng.integers(0, gh), rng.integers(0, gw)
        rr, cc = np.meshgrid(np.arange(gh), np.arange(gw), indexing="ij")
        holes |= (rr - br) ** 2 + (cc - bc) ** 2 <= (0.08 * gw) ** 2
        low[holes] = np.nan
        ri = np.minimum((np.arange(h) + 0.5) * gh / h, gh - 1).astype(int)
        ci = np.minimum((np.arange(w) + 0.5) * gw / w, gw - 1).astype(int)
        out[i] = low[ri][:, ci]
    return out


def write_session(scene: dict, rgbd: np.ndarray, out_dir: Path) -> dict:
    """Write the session's uploads under out_dir: `session.mp4`, `depth.npz` (the renderer's planar
    depth), `lidar.npz`, and each variant's params JSON. Returns {"video", "evs", "ldr" (the
    decoded frames as the product reads them, [T, H, W, 3] float in [0, 1]), "variants": {name:
    {"depth": path or None, "params": dict}}}."""
    from bench.pbr.scenes import camera_poses, intrinsics
    from core.io.video import read_video, write_video

    out_dir.mkdir(parents=True, exist_ok=True)
    hdr, depth = rgbd[..., :3], rgbd[..., 3]
    evs = auto_exposure(hdr)
    seed = int.from_bytes(scene["name"].encode()[:4].ljust(4, b"\0"), "little")
    codes = np.stack([sensor(f, ev, seed * 1009 + i) for i, (f, ev) in enumerate(zip(hdr, evs))])
    fps = float(scene["camera"]["fps"])
    video = write_video(out_dir / "session.mp4", codes, fps, crf=CRF)
    ldr = read_video(video).frames[:, : codes.shape[1], : codes.shape[2], :3]
    np.savez_compressed(out_dir / "depth.npz", depth=depth.astype(np.float32))
    np.savez_compressed(out_dir / "lidar.npz", depth=lidar_depth(depth, seed + 7))
    k = intrinsics(scene)
    base = {"poses": [p.reshape(-1).tolist() for p in camera_poses(scene)],
            "intrinsics": {key: k[key] for key in ("fx", "fy", "cx", "cy")}, "fps": fps, "preset": "draft"}
    variants = {
        "full-ar": {"depth": out_dir / "depth.npz", "params": {**base, "frame_ev": [round(e, 5) for e in evs]}},
        "monocular": {"depth": None, "params": {**base, "frame_ev": [round(e, 5) for e in evs]}},
        "lidar": {"depth": out_dir / "lidar.npz", "params": {**base, "frame_ev": [round(e, 5) for e in evs]}},
        "no-frame-ev": {"depth": out_dir / "depth.npz", "params": dict(base)},
    }
    for name, v in variants.items():
        (out_dir / f"params-{name}.json").write_text(json.dumps(v["params"]))
    return {"video": video, "evs": evs, "ldr": np.asarray(ldr, np.float32) / (255.0 if ldr.dtype == np.uint8 else 1.0),
            "variants": variants}
