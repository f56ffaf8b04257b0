"""ARKit / RealityKit / SceneKit hand-off (Apple platforms are not available here; tested
numerically against the documented Metal cube layout).

- Metal cube textures (`MTLTextureType.typeCube`) have slices +X, -X, +Y, -Y, +Z, -Z and select
  faces with the same table as OpenGL, row 0 first in memory: our faces copy slice by slice.
  `metal_cube_slices` gives each slice's bytes for `replace(region:mipmapLevel:slice:withBytes:
  bytesPerRow:bytesPerImage:)`: `.rgba16Float` (HDR, for RealityKit `EnvironmentResource` /
  SceneKit `lightingEnvironment`) or `.rgba8Unorm_srgb` (what `AREnvironmentProbeAnchor
  .environmentTexture` holds: tone-mapped first, sRGB-encoded).
- ARKit's world frame is ours (right-handed, +y up, camera -z): directions need no change. A
  texture sampled in an anchor's frame needs `rotate_envmap(env, R_anchor.T)` first.
- `ARDirectionalLightEstimate.sphericalHarmonicsCoefficients`: 27 floats in three planes of 9
  (R, G, B), `arkit_sh_planes`. Apple does not document the basis signs; this is the layout only.
"""
from __future__ import annotations

import base64

import numpy as np


def _srgb_encode(linear: np.ndarray) -> np.ndarray:
    a = np.clip(np.asarray(linear, np.float64), 0.0, 1.0)
    return np.where(a <= 0.0031308, 12.92 * a, 1.055 * a ** (1 / 2.4) - 0.055)


def metal_cube_slices(faces: np.ndarray, pixel_format: str = "rgba16Float", exposure_ev: float = 0.0) -> list[bytes]:
    """Per-slice bytes of cube faces [6, S, S, 3] (ours) for a Metal cube texture.

    `rgba16Float`: linear radiance clipped to the half range (+-65504), alpha 1 (bytesPerRow = 8 S). `rgba8Unorm_srgb`:
    2^ev scaled,
    clipped to [0, 1], sRGB-encoded, alpha 255 (bytesPerRow = 4 S)."""
    f = np.asarray(faces, np.float32)
    if f.ndim != 4 or f.shape[0] != 6 or f.shape[1] != f.shape[2] or f.shape[3] != 3:
        raise ValueError(f"faces must be [6, S, S, 3], got {f.shape}")
    alpha = np.ones(f.shape[:3] + (1,), np.float32)
    if pixel_format == "rgba16Float":
        rgba = np.clip(np.concatenate((f, alpha), -1), -65504.0, 65504.0)  # the half range: no inf for a bright lamp
        return [s.tobytes() for s in rgba.astype("<f2")]
    if pixel_format == "rgba8Unorm_srgb":
        ldr = np.round(_srgb_encode(f * 2.0 ** exposure_ev) * 255).astype(np.uint8)
        return [s.tobytes() for s in np.concatenate((ldr, (alpha * 255).astype(np.uint8)), -1)]
    raise ValueError(f"pixel_format must be 'rgba16Float' or 'rgba8Unorm_srgb', got {pixel_format!r}")


def arkit_sh_planes(radiance_sh) -> list[float]:
    """Our [9, 3] SH -> 27 floats as three planes of 9 (all R, then G, then B): core.export.sh_layouts 'arkit'."""
    from core.export.sh_layouts import pack  # noqa: PLC0415 — core.export.sh_layouts pulls in torch: imported when used

    return pack(radiance_sh, "arkit")


def arkit_probe(env, x, t, flags, size: int = 64, pixel_format: str = "rgba16Float", exposure_ev: float = 0.0):
    """The ARKit product (core.export.schema.ArkitProbe) of one env map of ours [H, 2H, 3]: Metal cube
    slices, the ambient SH planes and the main light. `flags`: core.export.schema.Flags."""
    import torch  # noqa: PLC0415 — torch is heavy: imported when used

    from core.cubemap import equirect_to_cubemap  # noqa: PLC0415 — core.cubemap pulls in torch: imported when used
    from core.export.schema import ArkitProbe, DominantLight  # noqa: PLC0415 — core.export.schema pulls in pydantic, torch: imported when used
    from core.lights import extract_dominant_light  # noqa: PLC0415 — core.lights pulls in torch: imported when used

    e = torch.as_tensor(np.asarray(env, np.float32))
    faces = equirect_to_cubemap(e, size).numpy()
    slices = metal_cube_slices(faces, pixel_format, exposure_ev)
    light = extract_dominant_light(e.double())
    texel = 8 if pixel_format == "rgba16Float" else 4
    return ArkitProbe(x=tuple(float(v) for v in x), t=None if t is None else float(t), extrapolated=flags,
                      pixel_format=pixel_format, size=size, bytes_per_row=texel * size,
                      bytes_per_image=texel * size * size, slices_base64=[base64.b64encode(s).decode() for s in slices],
                      sh_planes=arkit_sh_planes(light.ambient_sh), dominant_light=DominantLight.of(light))
