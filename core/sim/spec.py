"""Scene specification: a validated, JSON-round-trippable description of one simulated scene.

Every field is plain data (pydantic v2, `extra='forbid'`) so a spec written to `scene.json`
reloads bit-identically. Geometry is axis-aligned (boxes, rectangles, spheres) because the
scenes are small and the ray caster intersects every primitive at once.
"""
from __future__ import annotations

from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, field_serializer, field_validator, model_validator

Vec3 = tuple[float, float, float]
RGB = tuple[float, float, float]

EFFECTS = ("emission", "direct", "shadows", "indirect", "schedules", "camera_motion", "sensor")
Effect = Literal["emission", "direct", "shadows", "indirect", "schedules", "camera_motion", "sensor"]
# A face of an axis-aligned box, and the direction an area emitter faces (emits towards).
Facing = Literal["+x", "-x", "+y", "-y", "+z", "-z"]


class SceneSpecError(ValueError):
    """A scene spec is inconsistent (bad box, emitter outside the room, unknown suite, ...)."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Box(_Model):
    """Axis-aligned box [lo, hi] in world metres."""

    lo: Vec3
    hi: Vec3

    @model_validator(mode="after")
    def _ordered(self):
        if any(h <= l for l, h in zip(self.lo, self.hi)):
            raise ValueError(f"box needs lo < hi on every axis, got lo={self.lo} hi={self.hi}")
        return self


class RoomAlbedo(_Model):
    floor: RGB = (0.5, 0.45, 0.4)
    ceiling: RGB = (0.8, 0.8, 0.8)
    walls: RGB = (0.6, 0.6, 0.6)


class Room(_Model):
    """The room's interior: the union of overlapping boxes (one box, or two for an L shape).

    Surfaces may self-emit (`surface_emission`, used by the furnace test): that light reaches
    other surfaces only through the `indirect` effect, see docs/simulator.md.
    """

    boxes: list[Box] = Field(min_length=1, max_length=4)
    albedo: RoomAlbedo = RoomAlbedo()
    surface_emission: RGB = (0.0, 0.0, 0.0)


class Furniture(_Model):
    """A solid Lambertian box (a slab, a table leg, a cabinet)."""

    name: str = "box"
    box: Box
    albedo: RGB = (0.5, 0.5, 0.5)


class Keyframe(_Model):
    """Emitter state from `frame` on. `on` always switches exactly at `frame` (step);
    intensity, colour and position follow the schedule's interpolation."""

    frame: int = Field(ge=0)
    on: bool = True
    intensity: float = Field(default=1.0, ge=0.0)
    color: RGB = (1.0, 1.0, 1.0)
    position: Vec3 | None = None  # new centre (movement); None keeps the emitter's own


class Schedule(_Model):
    keyframes: list[Keyframe] = Field(default_factory=list)
    interpolation: Literal["step", "linear"] = "step"

    @field_validator("keyframes")
    @classmethod
    def _sorted(cls, v):
        frames = [k.frame for k in v]
        if frames != sorted(set(frames)):
            raise ValueError(f"schedule keyframes must have strictly increasing frames, got {frames}")
        return v


class AreaEmitter(_Model):
    """A one-sided rectangle emitting uniform radiance towards `facing` (ceiling panel or
    window). `size` is its extent along the two other axes in x, y, z order."""

    kind: Literal["ceiling_panel", "window"]
    name: str = ""
    center: Vec3
    facing: Facing
    size: tuple[float, float] = Field(description="extent along the two non-normal axes, in x,y,z order")
    radiance: RGB
    schedule: Schedule = Schedule()

    @model_validator(mode="after")
    def _check(self):
        if min(self.size) <= 0:
            raise ValueError(f"area emitter size must be > 0, got {self.size}")
        if min(self.radiance) < 0:
            raise ValueError(f"emitter radiance must be >= 0, got {self.radiance}")
        return self


class Lamp(_Model):
    """A small uniformly emitting sphere."""

    kind: Literal["lamp"] = "lamp"
    name: str = ""
    center: Vec3
    radius: float = Field(gt=0.0)
    radiance: RGB
    schedule: Schedule = Schedule()

    @model_validator(mode="after")
    def _check(self):
        if min(self.radiance) < 0:
            raise ValueError(f"lamp radiance must be >= 0, got {self.radiance}")
        return self


Emitter = Annotated[Union[AreaEmitter, Lamp], Field(discriminator="kind")]


class StaticPath(_Model):
    kind: Literal["static"] = "static"


class PanPath(_Model):
    """Yaw sweep about the camera position, linear in frame index from `yaw_deg` to `yaw_end_deg`."""

    kind: Literal["pan"] = "pan"
    yaw_end_deg: float


class DollyPath(_Model):
    """Translation, linear in frame index from `position` to `position_end`."""

    kind: Literal["dolly"] = "dolly"
    position_end: Vec3


CameraPath = Annotated[Union[StaticPath, PanPath, DollyPath], Field(discriminator="kind")]


class CameraSpec(_Model):
    """Pinhole camera at `position`, yaw about +y (positive turns left), pitch about camera x
    (positive looks up). Intrinsics come from `hfov_deg` unless fx, fy, cx, cy are all given."""

    position: Vec3
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    hfov_deg: float = Field(default=60.0, gt=0.0, lt=180.0)
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    path: CameraPath = StaticPath()

    @model_validator(mode="after")
    def _all_or_none(self):
        given = [v is not None for v in (self.fx, self.fy, self.cx, self.cy)]
        if any(given) and not all(given):
            raise ValueError("camera: give all of fx, fy, cx, cy or none of them (then hfov_deg is used)")
        return self


# The camera curves a scene can name (core.sim.camera_curves.NAMES), or "drawn": one of the
# realistic curves a capture directory's 8-bit PNG frames can hold, drawn by the scene's name.
CameraCurveName = Literal["drawn", "srgb", "rec709", "filmic", "hlg10", "gamma2.4"]


class SensorSpec(_Model):
    """Used only when the scene declares the `sensor` effect (otherwise the ideal sensor: ev 0,
    no noise, no compression), except `curve`: every camera writes its file through a curve."""

    ev: float = Field(default=0.0, ge=-20.0, le=20.0, description="exposure (with auto_exposure: its compensation)")
    auto_exposure: bool = Field(default=False, description="a phone's auto-exposure: each frame's ev moves toward "
                                "the one that meters it at mid-grey (core.sim.sensor.frame_evs), on top of `ev`")
    auto_exposure_speed: float = Field(default=0.5, gt=0.0, le=1.0,
                                       description="share of the way to the metered ev each frame moves (1: at once)")
    record_exposure: bool = Field(default=True, description="with auto_exposure: capture.json states each frame's ev "
                                  "as `frame_ev` (capture apps record it); false: the frames alone, as a plain video")
    noise_sigma: float = Field(default=0.0, ge=0.0, le=1.0, description="Gaussian noise std in LDR units, before 8-bit")
    video_compression: bool = False
    crf: int = Field(default=23, ge=0, le=51)
    curve: CameraCurveName = Field(
        default="drawn", description="the camera curve (core.sim.camera_curves) the frames are encoded with and "
        "their files declare, with or without the `sensor` effect: 'drawn' (one of srgb, rec709, filmic, drawn by "
        "the scene's name), or a name ('hlg10' is video only: a capture directory's PNG frames take srgb; "
        "'gamma2.4' is the reference, the curve the product used to assume)")


class RenderQuality(_Model):
    """Sample counts. Fixed, stratified and seeded, so renders are deterministic."""

    area_samples: int = Field(
        default=16, ge=1, le=256, description="points per area emitter (rounded down to a square)"
    )
    indirect_samples: int = Field(default=16, ge=1, le=256, description="cosine-weighted gather rays per shading point")
    indirect_area_samples: int = Field(
        default=4, ge=1, le=256, description="points per area emitter when shading gather hits"
    )
    chunk_rays: int = Field(default=65536, ge=1024, description="rays per vectorised batch (memory bound)")


class ProbePoint(_Model):
    """A held-out evaluation point: position (world metres) and time (seconds)."""

    x: Vec3
    t: float = Field(ge=0.0)


class SceneSpec(_Model):
    name: str = "scene"
    seed: int = 0
    room: Room
    furniture: list[Furniture] = Field(default_factory=list)
    emitters: list[Emitter] = Field(default_factory=list)
    camera: CameraSpec
    frames: int = Field(default=1, ge=1, le=10000)
    fps: float = Field(default=10.0, gt=0.0, le=1000.0)
    resolution: tuple[int, int] = Field(default=(192, 144), description="(width, height) in pixels")
    effects: frozenset[Effect] = frozenset({"emission", "direct", "shadows"})
    sensor: SensorSpec = SensorSpec()
    quality: RenderQuality = RenderQuality()
    probes: list[ProbePoint] = Field(default_factory=list, description="held-out evaluation points")

    @field_serializer("effects")
    def _sorted_effects(self, v):  # deterministic scene.json
        return sorted(v)

    @field_validator("resolution")
    @classmethod
    def _res(cls, v):
        w, h = v
        if not (1 <= w <= 8192 and 1 <= h <= 8192):
            raise ValueError(f"resolution must be within 1..8192 per side, got {v}")
        return v

    @model_validator(mode="after")
    def _consistent(self):
        """Catch placements that would silently render nonsense (a light inside a wall...)."""
        for i, p in enumerate(self.probes):
            if p.t > self.duration + 1e-9:
                raise ValueError(f"probes[{i}].t={p.t} is after the last frame ({self.duration} s)")
        if not self._in_free_space(self.camera.position):
            raise ValueError(f"camera.position {self.camera.position} is outside the room or inside furniture")
        if isinstance(self.camera.path, DollyPath) and not self._in_free_space(self.camera.path.position_end):
            raise ValueError(
                f"camera.path.position_end {self.camera.path.position_end} is outside the room or inside furniture"
            )
        for i, e in enumerate(self.emitters):
            where = f"emitters[{i}] ({e.name or e.kind})"
            if isinstance(e, Lamp):
                if not self._in_free_space(e.center):
                    raise ValueError(f"{where}: centre {e.center} is outside the room or inside furniture")
            else:
                axis, sign = "xyz".index(e.facing[1]), (1.0 if e.facing[0] == "+" else -1.0)
                front = list(e.center)
                front[axis] += sign * 0.01
                if not self._in_room(front):
                    raise ValueError(
                        f"{where}: centre {e.center} facing {e.facing} does not face into the room (put it on a wall "
                        "or ceiling)"
                    )
        return self

    def _in_room(self, p) -> bool:
        return any(all(lo < x < hi for lo, x, hi in zip(b.lo, p, b.hi)) for b in self.room.boxes)

    def _in_free_space(self, p) -> bool:
        inside_furniture = any(all(f.box.lo[a] <= p[a] <= f.box.hi[a] for a in range(3)) for f in self.furniture)
        return self._in_room(p) and not inside_furniture

    @property
    def duration(self) -> float:
        return (self.frames - 1) / self.fps

    def has(self, effect: str) -> bool:
        return effect in self.effects

    def with_effects(self, effects) -> "SceneSpec":
        return self.model_copy(update={"effects": frozenset(effects)})
