"""Field configuration (pydantic, JSON round-trip) and presets.

One `FieldConfig` names the field kind and carries a settings section per kind; only the
section of the chosen kind is used. Keeping every section (with defaults) makes configs
trivially editable (`FieldConfig(kind="grid")`) and the artefact JSON self-describing.
"""
from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

FieldKind = Literal["mlp", "grid", "trunk"]

# Output range of every field: radiance = exp(lo + (hi - lo) * sigmoid(z)). 12 decades cover a
# dim corner (1e-6) up to a bare bulb seen at ev 0 (1e6) in relative units; outputs can never
# be 0, negative, inf or NaN, and the gradient w.r.t. z is bounded by (hi - lo)/4 * L.
DEFAULT_LOG_RADIANCE_MIN = math.log(1e-6)
DEFAULT_LOG_RADIANCE_MAX = math.log(1e6)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class EncodingSettings(_Strict):
    """Positional-encoding frequencies of the network kinds: PE(x) 6, PE(t) 4, PE(d) 4."""

    x_freqs: int = Field(6, ge=0, le=16)
    t_freqs: int = Field(4, ge=0, le=16)
    d_freqs: int = Field(4, ge=0, le=16)


class MLPSettings(EncodingSettings):
    """The paper's MLP: PE(x) 6 freqs, PE(t) 4, PE(d) 4; 6 x 256 ReLU, skip into layer 3."""

    width: int = Field(256, ge=1)
    layers: int = Field(6, ge=1)
    skip_layer: int | None = Field(3, ge=1, description="1-based hidden layer that also receives the input encoding")

    @model_validator(mode="after")
    def _skip_in_range(self):
        if self.skip_layer is not None and self.skip_layer > self.layers:
            raise ValueError(f"mlp.skip_layer={self.skip_layer} exceeds mlp.layers={self.layers}")
        return self


class GridSettings(_Strict):
    """The paper's ablation: a resolution[0] x [1] x [2] lattice of learnable equirect maps."""

    resolution: tuple[int, int, int] = (3, 3, 3)
    env_height: int = Field(16, ge=2, le=256)  # each map is env_height x 2*env_height
    time_keyframes: int = Field(4, ge=2, le=256)  # linear interpolation between keys (uses_time only)

    @model_validator(mode="after")
    def _resolution_positive(self):
        if min(self.resolution) < 2:
            raise ValueError(f"grid.resolution must be >= 2 per axis, got {self.resolution}")
        return self


class TrunkSettings(EncodingSettings):
    """Faster field: trunk over (x, t) -> feature; head over (feature, PE(d)) -> radiance."""

    trunk_width: int = Field(128, ge=1)
    trunk_layers: int = Field(3, ge=1)
    feature_dim: int = Field(64, ge=1)
    head_width: int = Field(64, ge=1)
    head_layers: int = Field(2, ge=1)
    # Optional learnable dense feature grid over the box, concatenated to PE(x): local
    # capacity near lights without widening the trunk. None = PE only.
    x_grid: tuple[int, int, int] | None = None
    x_grid_features: int = Field(8, ge=1, le=64)

    @model_validator(mode="after")
    def _grid_positive(self):
        if self.x_grid is not None and min(self.x_grid) < 2:
            raise ValueError(f"trunk.x_grid must be >= 2 per axis, got {self.x_grid}")
        return self


class FieldConfig(_Strict):
    kind: FieldKind = "mlp"
    uses_time: bool = True  # False: single image, or lighting the engine decided is static
    log_radiance_min: float = DEFAULT_LOG_RADIANCE_MIN
    log_radiance_max: float = DEFAULT_LOG_RADIANCE_MAX
    mlp: MLPSettings = MLPSettings()
    grid: GridSettings = GridSettings()
    trunk: TrunkSettings = TrunkSettings()

    @model_validator(mode="after")
    def _range_ordered(self):
        lo, hi = self.log_radiance_min, self.log_radiance_max
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise ValueError(f"need finite log_radiance_min < log_radiance_max, got {lo}, {hi}")
        if max(abs(lo), abs(hi)) > 80.0:  # exp(88) overflows float32
            raise ValueError(f"log-radiance range must stay within +-80 (float32), got {lo}, {hi}")
        return self

    def with_time(self, uses_time: bool) -> "FieldConfig":
        return self.model_copy(update={"uses_time": bool(uses_time)})


FIELD_PRESETS: dict[str, FieldConfig] = {
    "mlp": FieldConfig(kind="mlp"),  # the paper's
    "grid": FieldConfig(kind="grid"),  # the paper's ablation
    "trunk": FieldConfig(kind="trunk"),
}


def field_preset(kind: str, uses_time: bool = True) -> FieldConfig:
    if kind not in FIELD_PRESETS:
        raise ValueError(f"unknown field kind {kind!r}; choose one of {sorted(FIELD_PRESETS)}")
    return FIELD_PRESETS[kind].with_time(uses_time)
