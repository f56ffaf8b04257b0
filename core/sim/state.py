"""Time-dependent scene state: emitter schedules and the camera path, resolved at a frame.

Frames may be fractional (t * fps) so ground truth exists between frames. `on` is a step
that switches exactly at its keyframe; intensity, colour and position are held (`step`) or
interpolated linearly (`linear`) between keyframes. Without the `schedules` effect every
emitter keeps its base state; without `camera_motion` the camera stays at its start pose.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from core.camera import Camera, Intrinsics
from core.sim.spec import AreaEmitter, CameraSpec, SceneSpec, Schedule

# A frame index computed as t * fps may land a hair below an integer; switching must not.
FRAME_EPS = 1e-6
AXIS = {"x": 0, "y": 1, "z": 2}
EMITTER_OFFSET = 1e-3  # metres an area emitter sits in front of its wall, so it wins the depth test


@dataclass(frozen=True)
class EmitterValue:
    on: bool
    scale: tuple[float, float, float]  # intensity * colour
    center: tuple[float, float, float]


def _lerp(a, b, w):
    return tuple(x + (y - x) * w for x, y in zip(a, b))


def schedule_value(schedule: Schedule, frame: float, base_center) -> EmitterValue:
    """Emitter state at (possibly fractional) `frame`; before the first keyframe: on, scale 1."""
    keys = schedule.keyframes
    f = frame + FRAME_EPS
    before = [k for k in keys if k.frame <= f]
    if not before:
        return EmitterValue(True, (1.0, 1.0, 1.0), tuple(base_center))
    k0 = before[-1]
    scale0 = tuple(k0.intensity * c for c in k0.color)
    center0 = tuple(k0.position) if k0.position is not None else tuple(base_center)
    after = [k for k in keys if k.frame > f]
    if schedule.interpolation == "linear" and after:
        k1 = after[0]
        w = (frame - k0.frame) / (k1.frame - k0.frame)
        w = min(max(w, 0.0), 1.0)
        scale1 = tuple(k1.intensity * c for c in k1.color)
        center1 = tuple(k1.position) if k1.position is not None else tuple(base_center)
        return EmitterValue(k0.on, _lerp(scale0, scale1, w), _lerp(center0, center1, w))
    return EmitterValue(k0.on, scale0, center0)


@dataclass(frozen=True)
class LightState:
    """All emitters at one instant, as tensors (float32)."""

    rect_center: torch.Tensor  # [E, 3] (already offset in front of the wall)
    rect_axis: torch.Tensor  # [E] long, normal axis
    rect_sign: torch.Tensor  # [E] +1/-1: emits towards +axis or -axis
    rect_half: torch.Tensor  # [E, 3] half extents (0 along the normal axis)
    rect_radiance: torch.Tensor  # [E, 3]
    lamp_center: torch.Tensor  # [L, 3]
    lamp_radius: torch.Tensor  # [L]
    lamp_radiance: torch.Tensor  # [L, 3]

    @property
    def rect_normal(self) -> torch.Tensor:
        n = torch.zeros_like(self.rect_center)
        if len(n):
            n[torch.arange(len(n)), self.rect_axis] = self.rect_sign
        return n


def light_state(spec: SceneSpec, frame: float) -> LightState:
    use_schedules = spec.has("schedules")
    rects, lamps = [], []
    for e in spec.emitters:
        v = (
            schedule_value(e.schedule, frame, e.center)
            if use_schedules
            else EmitterValue(True, (1.0, 1.0, 1.0), tuple(e.center))
        )
        rad = [r * s * (1.0 if v.on else 0.0) for r, s in zip(e.radiance, v.scale)]
        (rects if isinstance(e, AreaEmitter) else lamps).append((e, v.center, rad))
    rc, ra, rs, rh, rr = [], [], [], [], []
    for e, c, rad in rects:
        axis, sign = AXIS[e.facing[1]], (1.0 if e.facing[0] == "+" else -1.0)
        c = list(c)
        c[axis] += sign * EMITTER_OFFSET
        half = [0.0, 0.0, 0.0]
        others = [a for a in range(3) if a != axis]
        half[others[0]], half[others[1]] = e.size[0] / 2.0, e.size[1] / 2.0
        rc.append(c), ra.append(axis), rs.append(sign), rh.append(half), rr.append(rad)
    f32 = torch.float32
    return LightState(
        rect_center=torch.tensor(rc, dtype=f32).reshape(-1, 3),
        rect_axis=torch.tensor(ra, dtype=torch.long),
        rect_sign=torch.tensor(rs, dtype=f32),
        rect_half=torch.tensor(rh, dtype=f32).reshape(-1, 3),
        rect_radiance=torch.tensor(rr, dtype=f32).reshape(-1, 3),
        lamp_center=torch.tensor([list(c) for _, c, _ in lamps], dtype=f32).reshape(-1, 3),
        lamp_radius=torch.tensor([e.radius for e, _, _ in lamps], dtype=f32),
        lamp_radiance=torch.tensor([r for _, _, r in lamps], dtype=f32).reshape(-1, 3),
    )


def intrinsics_of(cam: CameraSpec, resolution: tuple[int, int]) -> Intrinsics:
    w, h = resolution
    if cam.fx is not None:
        return Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy, w, h)
    return Intrinsics.from_hfov(w, h, cam.hfov_deg)


def pose_from_yaw_pitch(position, yaw_deg: float, pitch_deg: float) -> torch.Tensor:
    """c2w for a camera at `position` turned by yaw about +y, then pitched about its x axis."""
    y, p = math.radians(yaw_deg), math.radians(pitch_deg)
    ry = torch.tensor([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]], dtype=torch.float64)
    rx = torch.tensor([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]], dtype=torch.float64)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = ry @ rx
    c2w[:3, 3] = torch.tensor(position, dtype=torch.float64)
    return c2w


def camera_at(spec: SceneSpec, frame: float) -> Camera:
    cam = spec.camera
    w = 0.0 if spec.frames <= 1 or not spec.has("camera_motion") else min(max(frame / (spec.frames - 1), 0.0), 1.0)
    yaw, pos = cam.yaw_deg, cam.position
    if cam.path.kind == "pan":
        yaw = cam.yaw_deg + (cam.path.yaw_end_deg - cam.yaw_deg) * w
    elif cam.path.kind == "dolly":
        pos = _lerp(cam.position, cam.path.position_end, w)
    return Camera(intrinsics_of(cam, spec.resolution), pose_from_yaw_pitch(pos, yaw, cam.pitch_deg))


def frame_of_time(spec: SceneSpec, t: float) -> float:
    return float(t) * spec.fps
