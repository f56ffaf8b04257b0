"""The simulated sensor: HDR radiance -> the codes of the camera's files.

Every camera writes through a curve (core.sim.camera_curves; `sensor.curve`, drawn per scene by
default): the codes are `curve.encode(2^ev hdr)`, quantised to its bit depth. Without the
`sensor` effect the sensor is otherwise ideal: ev 0, no noise. With it: exposure `sensor.ev`
(with `auto_exposure`, plus each frame's metered offset: `frame_evs`), additive Gaussian
noise in code units (seeded by scene seed and frame, so re-renders are identical) before
quantisation, and optionally an H.264 round trip through core.io's mp4 writer.
"""
from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import torch

from core.conventions import expose
from core.exposure import luminance
from core.sim.camera_curves import STILL, CameraCurve, resolve
from core.sim.cost import CostReport
from core.sim.spec import SceneSpec

AE_MID_GREY = 0.18  # auto-exposure meters the frame's mean linear luminance to this
AE_PIXEL_CAP = 4.0  # metered pixels are capped here (2^ev units): a tiny lamp must not set the exposure
AE_RANGE_STOPS = 4.0  # the metered offset stays within this many stops of `sensor.ev`


def scene_curve(scene: SceneSpec) -> CameraCurve:
    """The camera curve of the scene's capture: `sensor.curve` ("drawn": by the scene's name,
    among the curves a capture directory's 8-bit PNG frames can hold)."""
    return resolve(scene.sensor.curve, scene.name, STILL)


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
    """The file's codes [H, W, 3] in [0, 1] of one HDR frame at exposure `ev` (default the
    sensor's), through the scene's camera curve, quantised to its bit depth (no video
    compression; see `sensor_sequence`)."""
    cost = cost if cost is not None else CostReport()
    curve = scene_curve(scene)
    with cost.track("sensor"):
        codes = curve.apply(expose(hdr, exposure_ev(scene) if ev is None else ev))
        sigma = scene.sensor.noise_sigma if scene.has("sensor") else 0.0
        if sigma > 0:
            g = torch.Generator().manual_seed((scene.seed * 1_000_003 + frame_index) & 0x7FFFFFFF)
            codes = (codes + sigma * torch.randn(codes.shape, generator=g)).clamp(0.0, 1.0)
        return curve.quantise(codes)  # what the file stores


def video_round_trip(ldr: np.ndarray, fps: float, crf: int, curve: CameraCurve) -> np.ndarray:
    """Encode [T, H, W, 3] codes as the camera's mp4 and decode them back (lossy), same shape."""
    from core.io.video import read_video  # noqa: PLC0415 — core.io.video pulls in av, cv2, OpenEXR, PIL: imported when used
    from core.sim.camera_curves import write_video  # noqa: PLC0415 — core.io.video pulls in av, cv2, OpenEXR, PIL: imported when used

    t, h, w, _ = ldr.shape
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sensor.mp4"
        write_video(path, ldr, fps, curve, crf=crf)
        decoded = read_video(path).frames
    if len(decoded) != t:
        raise RuntimeError(f"video round trip returned {len(decoded)} frames for {t}")
    return np.ascontiguousarray(decoded[:, :h, :w, :3])  # the writer pads odd sizes


def sensor_sequence(scene: SceneSpec, hdr_frames: list[torch.Tensor], cost: CostReport | None = None) -> np.ndarray:
    """The files' codes [T, H, W, 3] float32 in [0, 1] of a whole sequence (with compression if set)."""
    cost = cost if cost is not None else CostReport()
    evs = frame_evs(scene, hdr_frames)
    ldr = np.stack(
        [sensor_frame(scene, h, i, cost, ev).numpy() for i, (h, ev) in enumerate(zip(hdr_frames, evs))]
    ).astype(np.float32)
    if scene.has("sensor") and scene.sensor.video_compression:
        with cost.track("sensor"):
            ldr = video_round_trip(ldr, scene.fps, scene.sensor.crf, scene_curve(scene))
    return ldr
