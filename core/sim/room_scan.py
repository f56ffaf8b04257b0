"""Room scans: a phone turned about one spot the way photo-sphere apps guide a user.

A scan is a ring at the horizon, a ring looking up and a ring looking down, with tilts between,
filmed with the phone's auto-exposure on and nothing else recorded (no poses, no exposures):
what a user of an AR app or a 360 capture app produces when asked to "look around the room".
This module makes such clips from a panorama, as test captures with known answers: the camera
sits at the panorama's centre, so every frame is an exact perspective crop of it.

* Path (`scan_poses`): SCAN_FRAMES frames at SCAN_FPS; RINGS (pitch, frames) joined by TILTS
  (the frames that move between two rings while the yaw keeps turning); the yaw advances by
  360 deg / frames over each ring and by the ring's step during a tilt; every frame gets a
  small hand jitter (yaw, pitch and roll, HAND_JITTER_DEG, seeded).
* Exposure (`lagging_auto_exposure`): each frame's meter is the mean linear luminance of the
  view with pixels capped at METER_CAP x the scan's median (a lamp pulls the exposure down,
  not to black), metered to MID_GREY; the exposure moves AE_SPEED of the way towards that goal
  each frame (the lag a real auto-exposure has). Nothing is stretched: the span is what the
  room makes it, 2-7 stops over the rooms here (floor in shadow to ceiling with its lamps);
  `span_stops` rescales the course of goals in log for a test that wants a given span.
* Sensor: a camera curve (core.sim.camera_curves) at each frame's exposure, quantised to its
  bit depth, H.264 declaring the curve (the caller writes the video: `write_scan`); without a
  curve, 8-bit frames in the engine's convention (a capture built in memory).
"""
from __future__ import annotations

import math
import random
from dataclasses import dataclass
from pathlib import Path

import torch

from core.camera import Camera, Intrinsics
from core.conventions import equirect_width, expose, inverse_tonemap, tonemap
from core.envmap import resize_envmap, rotate_envmap, sample_envmap
from core.exposure import luminance
from core.sim.camera_curves import CameraCurve, get_curve, write_video
from core.sim.panorama_room import load_panorama

SCAN_FPS = 10.0
SCAN_SIZE = (192, 144)  # width, height
SCAN_HFOV_DEG = 60.0
# (pitch in degrees, frames) per ring, and the pitches of the tilts between consecutive rings
RINGS = ((10.0, 16), (55.0, 12), (-40.0, 13))
TILTS = ((25.0, 40.0), (30.0, 5.0, -20.0))
SCAN_FRAMES = sum(n for _, n in RINGS) + sum(len(t) for t in TILTS)  # 46
PAN_FRAMES, PAN_STEP_DEG = 20, 9.0  # a pan: a half-turn at the horizon
HAND_JITTER_DEG = 1.5
AE_SPEED = 0.5  # of the way to the metered goal per frame
METER_CAP = 64.0  # metered pixels are capped at this many times the scan's median luminance
MID_GREY = 0.18


@dataclass(frozen=True)
class ScanClip:
    ldr: torch.Tensor  # [T, H, W, 3] the camera curve's codes (or the convention's 8-bit LDR) at each frame's exposure
    hdr: torch.Tensor  # [T, H, W, 3] linear radiance (the truth the sensor saw)
    evs: list[float]  # each frame's exposure in stops (unknown to the product)
    poses: list[torch.Tensor]  # [4, 4] c2w, world = the panorama's frame
    intrinsics: Intrinsics
    span_stops: float  # the exposure's range over the clip
    curve: CameraCurve | None = None  # the camera's curve (None: frames in the engine's convention)

    def linear(self) -> torch.Tensor:
        """The frames [T, H, W, 3] linearised with the curve they were encoded with."""
        return inverse_tonemap(self.ldr) if self.curve is None else self.curve.decode(self.ldr)


def _rotation(yaw_deg: float, pitch_deg: float, roll_deg: float) -> torch.Tensor:
    """c2w rotation: roll about the camera's z, then pitch about x, then yaw about +y."""
    y, p, r = (math.radians(v) for v in (yaw_deg, pitch_deg, roll_deg))
    ry = torch.tensor([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]], dtype=torch.float64)
    rx = torch.tensor([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]], dtype=torch.float64)
    rz = torch.tensor([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]], dtype=torch.float64)
    return ry @ rx @ rz


def scan_angles(yaw0: float = 0.0, path: str = "scan") -> list[tuple[float, float]]:
    """(yaw, pitch) in degrees of each frame of the path, without the hand's jitter: "scan" (the
    three rings and their tilts) or "pan" (PAN_FRAMES frames at the horizon, PAN_STEP_DEG apart:
    the half-turn a user makes when asked to pan)."""
    if path == "pan":
        return [(yaw0 + PAN_STEP_DEG * n, 0.0) for n in range(PAN_FRAMES)]
    out: list[tuple[float, float]] = []
    yaw = yaw0
    for k, (pitch, frames) in enumerate(RINGS):
        step = 360.0 / frames
        for _ in range(frames):
            out.append((yaw, pitch))
            yaw += step
        for tilt_pitch in TILTS[k] if k < len(TILTS) else ():
            out.append((yaw, tilt_pitch))
            yaw += step
    return out


def scan_poses(
    yaw0: float = 0.0, seed: int = 0, jitter_deg: float = HAND_JITTER_DEG, path: str = "scan"
) -> list[torch.Tensor]:
    """c2w poses [4, 4] float64 at the origin along the path (scan_angles), with a seeded hand jitter."""
    rng = random.Random(f"scan:{seed}")
    poses = []
    for yaw, pitch in scan_angles(yaw0, path):
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = _rotation(
            yaw + rng.gauss(0, jitter_deg), pitch + rng.gauss(0, jitter_deg), rng.gauss(0, jitter_deg)
        )
        poses.append(c2w)
    return poses


def lagging_auto_exposure(hdr: torch.Tensor, span_stops: float | None = None, speed: float = AE_SPEED) -> list[float]:
    """Each frame's exposure (stops) for HDR frames [T, H, W, 3]: a metered goal per frame (mean
    luminance, pixels capped at METER_CAP x the clip's median, to MID_GREY), followed with a lag
    (`speed` of the way per frame); with `span_stops`, the goals' course rescaled in log to span it."""
    y = luminance(hdr.to(torch.float64)).clamp_min(0.0)
    cap = METER_CAP * float(y.median().clamp_min(1e-12))
    goals = [math.log2(MID_GREY / max(float(f.clamp(max=cap).mean()), 1e-12)) for f in y]
    if span_stops is not None:
        lo, hi = min(goals), max(goals)
        mid = 0.5 * (lo + hi)
        stretch = span_stops / (hi - lo) if hi - lo > 1e-9 else 0.0
        goals = [mid + (g - mid) * stretch for g in goals]
    evs, ev = [], goals[0]
    for g in goals:
        ev += speed * (g - ev)
        evs.append(ev)
    return evs


def render_scan(panorama: torch.Tensor, yaw0: float = 0.0, seed: int = 0, span_stops: float | None = None,
                size: tuple[int, int] = SCAN_SIZE, hfov_deg: float = SCAN_HFOV_DEG, supersample: int = 2,
                path: str = "scan", curve: CameraCurve | None = None) -> ScanClip:
    """A room scan (or, path "pan", a pan: scan_angles) of `panorama` [h, 2h, 3] (linear HDR, the
    camera at its centre), encoded with the camera `curve` (None: 8-bit frames in the engine's
    convention, for captures built in memory)."""
    intr = Intrinsics.from_hfov(size[0], size[1], hfov_deg)
    big = intr.scaled(size[0] * supersample, size[1] * supersample)
    poses = scan_poses(yaw0, seed, path=path)
    pano = panorama.to(torch.float64)
    frames = []
    for c2w in poses:
        _, d = Camera(big, c2w).pixel_rays(dtype=torch.float64)
        rgb = sample_envmap(pano, d).permute(2, 0, 1)[None]
        frames.append(torch.nn.functional.avg_pool2d(rgb, supersample)[0].permute(1, 2, 0))
    hdr = torch.stack(frames).float()
    evs = lagging_auto_exposure(hdr, span_stops)
    if curve is None:
        ldr = torch.stack([torch.round(tonemap(h, ev) * 255.0) / 255.0 for h, ev in zip(hdr, evs)])
    else:
        ldr = torch.stack([curve.encode(expose(h, ev)) for h, ev in zip(hdr, evs)])
    return ScanClip(ldr, hdr, evs, poses, intr, max(evs) - min(evs), curve)


def scan_truth(panorama: torch.Tensor, clip: ScanClip, height: int, first: int = 0) -> torch.Tensor:
    """The panorama [h, 2h, 3] in the axes of the scan's camera `first` (a tracked scan's world is
    its first kept camera's): truth(d) = panorama(R_first d), `height` rows."""
    return rotate_envmap(resize_envmap(panorama, height), clip.poses[first][:3, :3].T)


def scan_constant_map(clip: ScanClip, height: int) -> torch.Tensor:
    """The baseline to beat: a constant map of the clip's mean colour, linearised with the
    curve the clip was encoded with (`ScanClip.linear`)."""
    mean = clip.linear().reshape(-1, 3).mean(0)
    return mean.expand(height, equirect_width(height), 3).clone()


def write_scan(path, clip: ScanClip) -> Path:
    """The clip as the phone's MP4: its codes at the curve's bit depth, the stream declaring the
    curve's transfer. A clip without a curve holds the engine's convention, which no camera
    writes: it is refused (render the scan with a curve)."""
    if clip.curve is None:
        raise ValueError("a scan without a camera curve is in the engine's convention, not a camera's file: "
                         "render it with render_scan(..., curve=...)")
    return write_video(path, clip.ldr, SCAN_FPS, clip.curve)


SAMPLE_PANORAMA = Path(__file__).resolve().parents[2] / "assets" / "sample_panorama.hdr"  # bundled (CC0)
SAMPLE_SEED = 7
# The sample's camera: a phone's SDR video (BT.709, 8-bit, declared), which every browser plays
# (the web page shows it; 10-bit HLG H.264 plays in few).
SAMPLE_CURVE = "rec709"


def write_sample_scan(out_dir, curve: str = SAMPLE_CURVE) -> tuple[Path, ScanClip, torch.Tensor]:
    """(MP4 path, ScanClip, panorama) of the bundled panorama's room scan, written as a phone
    would upload it (by default 8-bit BT.709 H.264 declaring its transfer; `curve="hlg10"`: a
    10-bit HLG clip as iPhones record; no poses): the demo's and the web page's sample."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    pano = load_panorama(SAMPLE_PANORAMA, 256)
    clip = render_scan(pano, yaw0=0.0, seed=SAMPLE_SEED, curve=get_curve(curve))
    return write_scan(out_dir / "room_scan.mp4", clip), clip, pano
