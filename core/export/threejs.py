"""three.js hand-off (checked against three r187 in Node: tests/node/).

- `SphericalHarmonics3` / `LightProbe`: same basis, band order and frame as ours, radiance
  coefficients, no Condon-Shortley phase: `coefficients[k] = (r, g, b)` of our c_k,
  `sh.fromArray(threejs_sh(c))` reads them (27 floats, coefficient-major, RGB interleaved).
  ARCore's 27 floats (the API's default) negate k = 1, 3, 5, 7: passing those to three.js
  mirrors the lighting in x and y.
- `EXRLoader` returns rows bottom-up and a texture with `flipY = false`; set
  `texture.mapping = EquirectangularReflectionMapping`. three's equirect u is ours minus 1/4,
  so upload `equirect_for_threejs(env)` (rolled a quarter turn) or rotate the scene's
  environment by +90 degrees about y (`scene.environmentRotation.y = Math.PI / 2`).
"""
from __future__ import annotations

import numpy as np


def threejs_sh(radiance_sh) -> list[float]:
    """Our [9, 3] radiance SH -> the 27 floats `SphericalHarmonics3.fromArray` reads
    (core.export.sh_layouts 'threejs')."""
    from core.export.sh_layouts import pack  # noqa: PLC0415 — core.export.sh_layouts pulls in torch: imported when used

    return pack(radiance_sh, "threejs")


def equirect_for_threejs(env: np.ndarray) -> np.ndarray:
    """Our map re-laid out for three's EquirectangularReflectionMapping (u = ours - 1/4)."""
    a = np.asarray(env)
    return np.roll(a, -a.shape[1] // 4, axis=1)


def threejs_equirect_uv(d: np.ndarray) -> np.ndarray:
    """three's `equirectUv(dir)` (shaders/ShaderChunk/common.glsl.js): u = atan(z, x) / 2pi + 0.5,
    v = asin(y) / pi + 0.5, v measured from the bottom row (GL t)."""
    d = np.asarray(d, np.float64)
    return np.stack((np.arctan2(d[..., 2], d[..., 0]) / (2 * np.pi) + 0.5,
                     np.arcsin(np.clip(d[..., 1], -1, 1)) / np.pi + 0.5), axis=-1)
