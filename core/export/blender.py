"""Blender hand-off (not installable here: the conversion is tested numerically against
Cycles' `direction_to_equirectangular`, intern/cycles/kernel/geom/... , as documented below).

Blender's world is right-handed and **Z-up**; importers of Y-up formats (glTF) map
(x, y, z)_ours -> (x, -z, y)_blender. Its Environment Texture node (equirectangular) reads
u = 0.5 - atan2(y, x) / 2pi, v = 0.5 + asin(z) / pi (v from the bottom row): the image centre
looks along +X there, not along our forward (-z -> +Y in Blender). So for a world shader,
either load `equirect_for_blender(env)` (our map rolled a quarter turn), or load ours and set
the Mapping node's Z rotation to -90 degrees.
"""
from __future__ import annotations

import numpy as np

BLENDER_FROM_OURS = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # d_blender = M d_ours


def to_blender(v: np.ndarray) -> np.ndarray:
    """Directions or positions [..., 3] from our frame to Blender's."""
    return np.asarray(v, np.float64) @ BLENDER_FROM_OURS.T


def blender_equirect_uv(d_blender: np.ndarray) -> np.ndarray:
    """Cycles' equirectangular (u, v) of Blender-frame directions; v = 0 at the bottom row."""
    d = np.asarray(d_blender, np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return np.stack((0.5 - np.arctan2(d[..., 1], d[..., 0]) / (2 * np.pi),
                     0.5 + np.arcsin(np.clip(d[..., 2], -1, 1)) / np.pi), axis=-1)


def equirect_for_blender(env: np.ndarray) -> np.ndarray:
    """Our map laid out for Blender's Environment Texture with no Mapping rotation."""
    a = np.asarray(env)
    return np.roll(a, -a.shape[1] // 4, axis=1)
