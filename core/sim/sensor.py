"""The simulated sensor: HDR radiance -> LDR frames.

Without the `sensor` effect the sensor is ideal: LDR = conventions.tonemap(hdr, ev=0).
With it: exposure `sensor.ev`, the paper's tone map (which clips to [0, 1]), additive
Gaussian noise in LDR units (seeded by scene seed and frame, so re-renders are identical),
8-bit quantisation, and optionally an H.264 round trip through core.io's mp4 writer.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import torch

from core.conventions import tonemap
from core.sim.cost import CostReport
from core.sim.spec import SceneSpec


def exposure_ev(scene: SceneSpec) -> float:
    return scene.sensor.ev if scene.has("sensor") else 0.0


def sensor_frame(scene: SceneSpec, hdr: torch.Tensor, frame_index: int, cost: CostReport | None = None) -> torch.Tensor:
    """LDR [H, W, 3] in [0, 1] of one HDR frame (no video compression; see `sensor_sequence`)."""
    cost = cost if cost is not None else CostReport()
    with cost.track("sensor"):
        ldr = tonemap(hdr, exposure_ev(scene))
        sigma = scene.sensor.noise_sigma if scene.has("sensor") else 0.0
        if sigma > 0:
            g = torch.Generator().manual_seed((scene.seed * 1_000_003 + frame_index) & 0x7FFFFFFF)
            ldr = (ldr + sigma * torch.randn(ldr.shape, generator=g)).clamp(0.0, 1.0)
        return torch.round(ldr * 255.0) / 255.0  # what an 8-bit PNG stores


def video_round_trip(ldr: np.ndarray, fps: float, crf: int) -> np.ndarray:
    """Encode [T, H, W, 3] LDR frames as mp4 and decode them back (lossy), same shape."""
    from core.io.video import read_video, write_video

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
    ldr = np.stack([sensor_frame(scene, h, i, cost).numpy() for i, h in enumerate(hdr_frames)]).astype(np.float32)
    if scene.has("sensor") and scene.sensor.video_compression:
        with cost.track("sensor"):
            ldr = video_round_trip(ldr, scene.fps, scene.sensor.crf)
    return ldr
