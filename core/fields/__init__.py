"""Light fields L(x, t, d): the paper's MLP, the 3x3x3 env-map grid ablation, a fast trunk+head,
registered by kind (core.fields.registry); the stored artefact (artefact) and its baked
fast path (bake) are submodules.

    from core.fields import FieldConfig, SceneBounds, build_field
    field = build_field(FieldConfig(kind="mlp", uses_time=False), SceneBounds.from_points(points))
    radiance = field(x, t, d)                 # [B, 3] > 0, world metres / seconds / unit d
    maps = field.envmaps(xs, ts, height=64)   # [P, 64, 128, 3]
"""
from __future__ import annotations

from core.fields.base import LightField
from core.fields.config import FieldConfig
from core.fields.normalization import BoundsError, SceneBounds
from core.fields.registry import build_field, field_kinds, register_field

# the built-in kinds register on import, in this order (the order of FieldConfig's sections)
from core.fields.mlp import MLPField
from core.fields.grid import GridField
from core.fields.trunk import TrunkField

__all__ = [
    "BoundsError",
    "FieldConfig",
    "GridField",
    "LightField",
    "MLPField",
    "SceneBounds",
    "TrunkField",
    "build_field",
    "field_kinds",
    "register_field",
]
