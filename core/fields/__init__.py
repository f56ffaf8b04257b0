"""Light fields L(x, t, d): the paper's MLP, the 3x3x3 env-map grid ablation, a fast trunk+head.

    from core.fields import FieldConfig, SceneBounds, build_field, field_preset
    field = build_field(field_preset("mlp", uses_time=False), SceneBounds.from_points(points))
    radiance = field(x, t, d)                 # [B, 3] > 0, world metres / seconds / unit d
    maps = field.envmaps(xs, ts, height=64)   # [P, 64, 128, 3]
"""
from __future__ import annotations

from core.fields.base import LightField
from core.fields.config import FIELD_PRESETS, FieldConfig, field_preset
from core.fields.grid import GridField
from core.fields.mlp import MLPField
from core.fields.normalization import BoundsError, SceneBounds
from core.fields.trunk import TrunkField

FIELD_CLASSES: dict[str, type[LightField]] = {"mlp": MLPField, "grid": GridField, "trunk": TrunkField}


def build_field(config: FieldConfig, bounds: SceneBounds) -> LightField:
    """A freshly initialised field of `config.kind` normalised to `bounds` (float32, CPU)."""
    return FIELD_CLASSES[config.kind](config, bounds)


__all__ = [
    "FIELD_CLASSES",
    "FIELD_PRESETS",
    "BoundsError",
    "FieldConfig",
    "GridField",
    "LightField",
    "MLPField",
    "SceneBounds",
    "TrunkField",
    "build_field",
    "field_preset",
]
