"""The simulated sensor: HDR radiance -> LDR frames.

Without the `sensor` effect the sensor is ideal: LDR = conventions.tonemap(hdr, ev=0).
With it: exposure `sensor.ev` (with `auto_exposure`, plus each frame's metered offset:
`frame_evs`), the paper's tone map (which clips to [0, 1]), additive
Gaussian noise in LDR units (seeded by scene seed and frame, so re-renders are identical),
8-bit quantisation, and optionally an H.264 round trip through core.io's mp4 writer.
"""
from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import torch

from core.conventions import tonemap
from core.exposure import luminance
from core.sim.cost import CostReport
from core.sim.spec import SceneSpec

AE_MID_GREY = 0.18  # auto-exposure meters the frame's mean linear luminance to this
AE_PIXEL_CAP = 4.0  # metered pixels are capped here (2^ev units): a tiny lamp must not set the exposure
AE_RANGE_STOPS = 4.0  # the metered offset stays within this many stops of `sensor.ev`


def exposure_ev(scene: SceneSpec) -> float:
    return scene.sensor.ev if scene.has("sensor") else 0.0


def frame_evs(scene: SceneSpec, hdr_frames: list[torch.Tensor]) -> list[float]:
    """Each frame's exposure: `sensor.ev`, and with `auto_exposure` an offset that moves
    `auto_exposure_speed` of the way each frame (frame 0: all the way) toward the one that
    meters the frame's mean luminance (pixels capped at AE_PIXEL_CAP) at AE_MID_GREY."""
    base = exposure_ev(scene)
    if not (scene.has("sensor") and scene.sensor.auto_exposure):
        return [base] * len(hdr_frames)
    return metered_evs(hdr_frames, base, scene.sensor.auto_exposure_speed)


def metered_evs(hdr_frames, base: float = 0.0, speed: float = 0.5) -> list[float]:
    """A phone-style auto-exposure's ev per HDR frame [H, W, 3] (see `frame_evs`)."""
    out, offset = [], None
    for hdr in hdr_frames:
        y = luminance(hdr) * 2.0 ** base
        metered = float(y.nan_to_num(0.0).clamp(0.0, AE_PIXEL_CAP).mean().clamp_min(1e-6))
        goal = min(max(math.log2(AE_MID_GREY / metered), -AE_RANGE_STOPS), AE_RANGE_STOPS)
        offset = goal if offset is None else offset + speed * (goal - offset)
        out.append(base + offset)
    return out


def sensor_frame(scene: SceneSpec, hdr: torch.Tensor, frame_index: int, cost: CostReport | None = None,
                 ev: float | None = None) -> torch.Tensor:
    """LDR [H, W, 3] in [0, 1] of one HDR frame at exposure `ev` (default the sensor's; no video
    compression; see `sensor_sequence`)."""
    cost = cost if cost is not None else CostReport()
    with cost.track("sensor"):
        ldr = tonemap(hdr, exposure_ev(scene) if ev is None else ev)
        sigma = scene.sensor.noise_sigma if scene.has("sensor") else 0.0
        if sigma > 0:
            g = torch.Generator().manual_seed((scene.seed * 1_000_003 + frame_index) & 0x7FFFFFFF)
            ldr = (ldr + sigma * torch.randn(ldr.shape, generator=g)).clamp(0.0, 1.0)
        return torch.round(ldr * 255.0) / 255.0  # what an 8-bit PNG stores


def video_round_trip(ldr: np.ndarray, fps: float, crf: int) -> np.ndarray:
    """Encode [T, H, W, 3] LDR frames as mp4 and decode them back (lossy), same shape."""
    from core.io.video import read_video, write_video  # noqa: PLC0415 — core.io.video pulls in av, cv2, OpenEXR, PIL: imported when used

    t, h, w, _ = ldr.shape
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sensor.mp4"
        write_video(path, ldr, fps, crf=crf)
        decoded = read_video(path).frames
    if len(decoded) != t:
        raise RuntimeError(f"video round trip returned {len(decoded)} frames for {t}")
    return np.ascontiguousarray(decoded[:, :h, :w, :3])  # the writer pads odd sizes


def sensor_sequence(scene: SceneSpec, hdr_frames: list[torch.Tensor], cost: CostReport | None = None) -> np.ndarray:
    """LDR frames [T, H, W, 3] float32 in [0, 1] of a whole sequence (with compression if set)."""
    cost = cost if cost is not None else CostReport()
    evs = frame_evs(scene, hdr_frames)
    ldr = np.stack(
        [sensor_frame(scene, h, i, cost, ev).numpy() for i, (h, ev) in enumerate(zip(hdr_frames, evs))]
    ).astype(np.float32)
    if scene.has("sensor") and scene.sensor.video_compression:
        with cost.track("sensor"):
            ldr = video_round_trip(ldr, scene.fps, scene.sensor.crf)
    return ldr
