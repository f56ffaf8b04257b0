"""One env map -> each downloadable product (the service's routes and the CLI call these).

Every function takes our equirect map (torch or numpy [H, 2H, 3]) and the query it answers
(x metres, t seconds, the artefact id), and returns file bytes. Cube products need the map
at least 2 x size rows high (`cube_source_height`).
"""
from __future__ import annotations

import numpy as np
import torch

from core.conventions import CONVENTIONS_SUMMARY
from core.envmap import mirror_envmap
from core.export.ktx2 import encode_ktx2_cubemap
from core.export.metadata import envmap_attributes
from core.export.prefilter import prefiltered_cubemap
from core.export.sh_layouts import pack
from core.export.usd import usdz
from core.lights import extract_dominant_light
from core.sh import project_sh


def cube_source_height(size: int) -> int:
    """Env map height that gives about one map pixel per cube texel at the face centres."""
    return max(2 * int(size), 8)


def _tensor(env) -> torch.Tensor:
    return env if isinstance(env, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(env, np.float32))


def prefiltered(env, size: int, levels: int | None = None) -> list[np.ndarray]:
    return [m.numpy() for m in prefiltered_cubemap(_tensor(env), size, levels)]


CUBE_LAYOUTS = ("gl", "threejs")


def cube_for(env, layout: str = "gl"):
    """The map whose GL-table cube faces a consumer samples as our radiance: 'gl' (OpenGL/Vulkan/Metal
    cube tables, Babylon, Filament, ARCore) is ours; 'threejs' is mirrored in x, because three.js
    samples a CubeTexture it did not render at (-x, y, z) (`flipEnvMap = -1`)."""
    if layout not in CUBE_LAYOUTS:
        raise ValueError(f"cube layout must be one of {', '.join(CUBE_LAYOUTS)}, got {layout!r}")
    e = _tensor(env)
    return mirror_envmap(e, "x") if layout == "threejs" else e


def cube_ktx2(env, size: int, levels: int | None = None, layout: str = "gl") -> bytes:
    """KTX2 cube map, RGBA16F, GGX roughness mips (levels=1: the mirror cube only), in `layout`."""
    return encode_ktx2_cubemap(prefiltered(cube_for(env, layout), size, levels))


def probe_glb(env, x, t, size: int = 64, levels: int | None = None, artefact: str = "",
              main_light: bool = True, grade: dict | None = None) -> bytes:
    """glTF binary with EXT_lights_image_based (irradiance SH + prefiltered specular mips) and, with
    `main_light` and a light found, a KHR_lights_punctual directional light (core.export.gltf);
    `grade` (core.export.schema.AnswerGrade as a dict) in the probe node's extras."""
    from core.export.gltf import build_glb  # noqa: PLC0415 — core.export.gltf pulls in av, cv2, OpenEXR, PIL: imported when used

    e = _tensor(env)
    light = extract_dominant_light(e) if main_light else None
    return build_glb(prefiltered(e, size, levels), project_sh(e.double()).numpy(), x, t,
                     extras={"artefact": artefact, "conventions": CONVENTIONS_SUMMARY,
                             **({"grade": grade} if grade else {})}, main_light=light)


def probe_usdz(env, x, t, artefact: str = "", grade: dict | None = None) -> bytes:
    return usdz(np.asarray(_tensor(env).detach().cpu(), np.float32), x, t, artefact, grade)


def envmap_exr_attributes(x, t, artefact: str = "", extrapolated: str | None = None) -> dict:
    return envmap_attributes(x, t, artefact or None, extrapolated=extrapolated)


def sh_in_layout(radiance_sh, layout: str) -> list[float]:
    """27 floats of our radiance SH in a consumer's layout (core.export.sh_layouts)."""
    return pack(radiance_sh, layout)
