"""Light fields L(x, t, d) in three parts: components (building blocks every kind shares:
settings, normalization, encodings, lattice, emitters, surfaces), kinds (the LightField shell,
FieldConfig, the registry, and the paper's MLP, the 3x3x3 env-map grid ablation, a fast
trunk+head, registered by kind) and stored (the artefact on disk and its baked fast path).

    from core.fields import FieldConfig, SceneBounds, build_field
    field = build_field(FieldConfig(kind="mlp", uses_time=False), SceneBounds.from_points(points))
    radiance = field(x, t, d)                 # [B, 3] > 0, world metres / seconds / unit d
    maps = field.envmaps(xs, ts, height=64)   # [P, 64, 128, 3]
"""
from __future__ import annotations

from core.fields.components.normalization import BoundsError, SceneBounds
from core.fields.kinds.base import LightField, build_field
from core.fields.kinds.config import FieldConfig
from core.fields.kinds.registry import field_kinds, register_field

# the built-in kinds register on import, in this order (the order of FieldConfig's sections and
# of the API's field choices): not sorted
# isort: off
from core.fields.kinds.mlp import MLPField
from core.fields.kinds.grid import GridField
from core.fields.kinds.trunk import TrunkField
# isort: on

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
