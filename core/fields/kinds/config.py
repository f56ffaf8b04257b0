"""Field configuration (pydantic, JSON round-trip).

One `FieldConfig` names the field kind and carries a settings section per registered kind
(each kind's `Config`, core.fields.kinds.registry); only the section of the chosen kind is used.
Keeping every section (with defaults) makes configs trivially editable (`with_kind("grid")`),
lets a preset carry settings for every kind a job may pick, and keeps the artefact JSON
self-describing. JSON layout: {"kind", "uses_time", "log_radiance_min", "log_radiance_max",
"view_detail_heights", "view_detail_radius", "view_anchors", "view_detail_time_rank",
"view_detail_time_knots", "emitter_count", "emitter_knots", "emitter_gate_resolution",
"emitter_sigma_floor", "room_lattice", "room_lattice_height", "surface_points", "surface_knots",
"surface_height", "time_gain_knots", "time_gain_channels", "<kind>": {section}, ...}.
"""
from __future__ import annotations

import math
from typing import Any, Literal, Mapping

from pydantic import (
    BaseModel,
    Field,
    SerializeAsAny,
    ValidationError,
    field_validator,
    model_serializer,
    model_validator,
)

from core.fields.components.settings import FieldSettings
from core.fields.kinds.registry import FIELDS, field_class

# Output range of every field: radiance = exp(lo + (hi - lo) * sigmoid(z)). 12 decades cover a
# dim corner (1e-6) up to a bare bulb seen at ev 0 (1e6) in relative units; outputs can never
# be 0, negative, inf or NaN, and the gradient w.r.t. z is bounded by (hi - lo)/4 * L.
DEFAULT_LOG_RADIANCE_MIN = math.log(1e-6)
DEFAULT_LOG_RADIANCE_MAX = math.log(1e6)
# Observed surfaces: points x time knots at most (x 3 colours x 4 bytes: 12 MB of an artefact),
# so no config, the engine's or a hand-edited artefact's, asks for more memory than that.
MAX_SURFACE_VALUES = 1 << 20


class FieldConfig(FieldSettings):
    kind: str = "mlp"
    uses_time: bool = True  # False: single image, or lighting the engine decided is static
    log_radiance_min: float = DEFAULT_LOG_RADIANCE_MIN
    log_radiance_max: float = DEFAULT_LOG_RADIANCE_MAX
    # View detail (core.fields.kinds.base, docs/engine.md): learnable equirect log-radiance residuals,
    # one per height, added to every kind's output with a weight exp(-r^2 / 2 radius^2), r the
    # distance to the nearest anchor (the engine sets the capture's camera centres). () = off.
    view_detail_heights: tuple[int, ...] = Field((), max_length=6)
    view_detail_radius: float = Field(
        0.3, gt=0, le=100, description="metres over which the detail fades away from an anchor"
    )
    view_anchors: tuple[tuple[float, float, float], ...] = Field((), max_length=256)
    # With a time input the detail also has `view_detail_time_rank` maps whose weights follow
    # learned per-knot coefficients (`view_detail_time_knots`, the engine sets one per frame):
    # a rank-R factorisation of how the photographed region changes over time. 0: no detail
    # for a field with a time input.
    view_detail_time_rank: int = Field(4, ge=0, le=16)
    view_detail_time_knots: int = Field(2, ge=2, le=4096)
    # Emitters (core.fields.components.emitters, docs/engine.md): small bright sources as explicit spheres
    # whose positions and per-knot intensities the engine measures in the frames (in the saved
    # weights: positions and radii as buffers, intensities and visibility gates as parameters the
    # distillation refines). 0: none, the field as before.
    emitter_count: int = Field(0, ge=0, le=16)
    emitter_knots: int = Field(1, ge=1, le=4096)
    emitter_gate_resolution: int = Field(8, ge=1, le=32, description="cells per side of each emitter's visibility grid")
    emitter_sigma_floor: float = Field(0.05, gt=0, le=1.0, description=(
        "radians: narrowest lobe of `forward` / `probe_radiance` (the engine sets 0.6 pixel of the prior's maps); "
        "`envmaps` uses 0.6 pixel of the map asked for"))
    # Room lattice (core.fields.components.lattice, docs/engine.md): a (nx, ny, nz) lattice of learnable
    # `room_lattice_height`-row log-radiance maps over the box, added to every kind's output; it
    # fits the slowly varying colour and brightness across the room fast. () = off.
    room_lattice: tuple[int, ...] = Field((), max_length=3)
    room_lattice_height: int = Field(8, ge=2, le=64)
    # Observed surfaces (core.fields.components.surfaces, docs/engine.md): up to `surface_points` points of
    # the frames with their radiance at `surface_knots` times, splatted at `surface_height` rows
    # and answering, away from the cameras, the directions they cover (the engine fills them
    # after the distillation). 0: none.
    surface_points: int = Field(0, ge=0, le=1 << 16)
    surface_knots: int = Field(1, ge=1, le=256)
    surface_height: int = Field(24, ge=4, le=128)
    # Time gain (core.fields.components.encodings.TimeGain, docs/engine.md "Time gain"): a learned log gain
    # per knot (the engine sets one knot per frame) and colour channel (or one for all three),
    # multiplying the network's radiance (not the emitters' or the observed surfaces', which have
    # their own time curves): a light that dims the whole room is one number per frame instead
    # of a direction the time codes must find. 0 knots: none (a field without a time input has none).
    time_gain_knots: int = Field(0, ge=0, le=4096)
    time_gain_channels: Literal[1, 3] = 3
    # kind -> its settings; given (and serialised) as one top-level key per kind
    sections: Mapping[str, SerializeAsAny[BaseModel]] = Field(default_factory=dict, repr=False)

    @model_validator(mode="before")
    @classmethod
    def _sections_by_kind(cls, data: Any) -> Any:
        """Top-level `<kind>` keys -> validated sections, with defaults for the kinds not given."""
        if not isinstance(data, Mapping):
            return data
        data = dict(data)
        given = dict(data.pop("sections", None) or {})
        for kind in FIELDS:
            if kind in data:
                given[kind] = data.pop(kind)
        sections = {}
        for kind, field_cls in FIELDS.items():
            raw = given.pop(kind, None)
            try:
                sections[kind] = (
                    raw if isinstance(raw, field_cls.Config) else field_cls.Config.model_validate(raw or {})
                )
            except ValidationError as exc:  # name the section: "mlp.width: ..."
                raise ValueError(
                    "; ".join(f"{kind}.{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
                ) from None
        if given:
            raise ValueError(f"settings for unknown field kinds {sorted(given)}; registered: {', '.join(FIELDS)}")
        data["sections"] = sections
        return data

    @field_validator("kind")
    @classmethod
    def _registered_kind(cls, kind: str) -> str:
        field_class(kind)  # raises, naming the registered kinds
        return kind

    @field_validator("view_detail_heights")
    @classmethod
    def _detail_heights(cls, heights: tuple[int, ...]) -> tuple[int, ...]:
        if any(h < 2 or h > 512 for h in heights):
            raise ValueError(f"view_detail_heights must each be in [2, 512], got {heights}")
        return heights

    @field_validator("room_lattice")
    @classmethod
    def _lattice_shape(cls, resolution: tuple[int, ...]) -> tuple[int, ...]:
        if resolution and (len(resolution) != 3 or any(r < 2 or r > 32 for r in resolution)):
            raise ValueError(f"room_lattice must be () or three node counts in [2, 32], got {resolution}")
        return resolution

    @field_validator("view_anchors")
    @classmethod
    def _finite_anchors(cls, anchors):
        if not all(math.isfinite(v) for a in anchors for v in a):
            raise ValueError("view_anchors must be finite")
        return anchors

    @model_validator(mode="after")
    def _range_ordered(self):
        lo, hi = self.log_radiance_min, self.log_radiance_max
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise ValueError(f"need finite log_radiance_min < log_radiance_max, got {lo}, {hi}")
        if max(abs(lo), abs(hi)) > 80.0:  # exp(88) overflows float32
            raise ValueError(f"log-radiance range must stay within +-80 (float32), got {lo}, {hi}")
        return self

    @model_validator(mode="after")
    def _surfaces_bounded(self):
        if self.surface_points * self.surface_knots > MAX_SURFACE_VALUES:
            raise ValueError(f"surface_points x surface_knots must be at most {MAX_SURFACE_VALUES}, got "
                             f"{self.surface_points} x {self.surface_knots}")
        return self

    @model_serializer(mode="wrap")
    def _sections_as_keys(self, handler) -> dict:
        out = handler(self)
        out.update(out.pop("sections", {}))
        return out

    def section(self, kind: str | None = None) -> BaseModel:
        """The settings of `kind` (default: this config's own kind)."""
        return self.sections[kind or self.kind]

    def with_section(self, kind: str | None = None, **changes) -> "FieldConfig":
        """A copy with `changes` applied to the settings of `kind` (default: its own), validated."""
        kind = kind or self.kind
        section = self.section(kind).model_dump()
        return FieldConfig.model_validate({**self.model_dump(), kind: {**section, **changes}})

    def with_kind(self, kind: str) -> "FieldConfig":
        return FieldConfig.model_validate({**self.model_dump(), "kind": kind})

    def with_view_anchors(self, anchors) -> "FieldConfig":
        return self.model_copy(update={"view_anchors": tuple(tuple(float(v) for v in a) for a in anchors)})

    def with_time(self, uses_time: bool) -> "FieldConfig":
        return self.model_copy(update={"uses_time": bool(uses_time)})
