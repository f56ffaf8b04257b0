"""glTF 2.0 binary (.glb) carrying one image-based light: EXT_lights_image_based.

What the extension specifies (KhronosGroup/glTF, extensions/2.0/Vendor/EXT_lights_image_based):
- `irradianceCoefficients`: 9 x 3 SH coefficients of the *irradiance* up to l = 2
  (Ramamoorthi & Hanrahan). We write E_k = A_l c_k: our radiance SH (core.sh: real,
  orthonormal, no Condon-Shortley phase, band order 1, y, z, x, xy, yz, 3z^2-1, xz, x^2-y^2)
  convolved with the clamped cosine. glTF's frame is ours (right-handed, +y up), so no axis
  change.
- `specularImages`: N mips x 6 faces (+X, -X, +Y, -Y, +Z, -Z) of a GGX-prefiltered cube map,
  mips evenly spaced in roughness 0..1 (core.export.prefilter), power-of-two faces.
- HDR images are 4-channel PNGs packed as RGBD: stored rgb = (value * D)^(1/2.2), alpha = D,
  value = stored_linear / D; D = floor(min(255 / max(rgb), 255)) / 255 (Babylon.js's packing,
  the reference implementation). RGBD holds values up to 255, so the map is divided by a scale
  that brings its maximum to 255 and `intensity` carries that scale back.
- "each saved image must be flipped about its vertical axis": every face is mirrored left-right
  before encoding.
The scene holds one node, `probe`, at the query position x (metres), and `extras` with the
query (x, t), the conventions and the artefact id.
"""
from __future__ import annotations

import json
import struct

import numpy as np

from core.io.images import encode_png

EXTENSION = "EXT_lights_image_based"
RGBD_MAX = 255.0
GLB_MAGIC, GLB_VERSION, CHUNK_JSON, CHUNK_BIN = 0x46546C67, 2, 0x4E4F534A, 0x004E4942


def rgbd_encode(rgb: np.ndarray) -> np.ndarray:
    """Linear HDR [..., 3] (0..255) -> uint8 RGBD [..., 4] (Babylon.js's toRGBD)."""
    a = np.clip(np.asarray(rgb, np.float64), 0.0, RGBD_MAX)
    peak = np.maximum(a.max(axis=-1, keepdims=True), 1e-12)
    d = np.clip(np.floor(np.minimum(RGBD_MAX / peak, RGBD_MAX)) / 255.0, 1.0 / 255.0, 1.0)
    stored = np.clip((a * d) ** (1.0 / 2.2), 0.0, 1.0)
    return np.round(np.concatenate((stored, d), axis=-1) * 255.0).astype(np.uint8)


def rgbd_decode(rgbd: np.ndarray) -> np.ndarray:
    """uint8 RGBD [..., 4] -> linear [..., 3] (Babylon.js's fromRGBD)."""
    a = np.asarray(rgbd, np.float64) / 255.0
    return (a[..., :3] ** 2.2) / np.maximum(a[..., 3:], 1.0 / 255.0)


def irradiance_coefficients(radiance_sh: np.ndarray) -> list[list[float]]:
    """Our radiance SH [9, 3] -> the extension's irradiance SH, 9 x [r, g, b]."""
    from core.sh import COSINE_LOBE_BY_BAND, SH_BANDS

    c = np.asarray(radiance_sh, np.float64).reshape(9, 3)
    lobe = np.array([COSINE_LOBE_BY_BAND[l] for l in SH_BANDS])[:, None]
    return (c * lobe).tolist()


def _pad(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 4)


def build_glb(mips: list[np.ndarray], radiance_sh: np.ndarray, x, t: float | None,
              extras: dict | None = None, name: str = "lightfield probe") -> bytes:
    """A .glb with one EXT_lights_image_based light: `mips[i]` float [6, S >> i, S >> i, 3]
    (prefiltered, roughness i / (N - 1)), `radiance_sh` our [9, 3] SH of the same map."""
    if not mips:
        raise ValueError("at least one specular mip is needed")
    size = int(mips[0].shape[1])
    if size & (size - 1):
        raise ValueError(f"specular image size must be a power of two, got {size}")
    peak = max(float(np.max(m)) for m in mips)
    scale = max(peak / RGBD_MAX, 1e-30) if peak > RGBD_MAX else 1.0
    blob = bytearray()
    views, images, specular = [], [], []
    for level in mips:
        faces = []
        for face in np.asarray(level, np.float32):
            png = encode_png(rgbd_encode(face[:, ::-1] / scale))  # mirrored left-right (see module doc)
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(png)})
            blob += _pad(png, b"\0")
            images.append({"bufferView": len(views) - 1, "mimeType": "image/png"})
            faces.append(len(images) - 1)
        specular.append(faces)
    light = {"name": name, "intensity": float(scale), "rotation": [0.0, 0.0, 0.0, 1.0],
             "irradianceCoefficients": irradiance_coefficients(np.asarray(radiance_sh) / scale),
             "specularImageSize": size, "specularImages": specular}
    doc = {
        "asset": {"version": "2.0", "generator": "lightfield (core/export/gltf.py)"},
        "extensionsUsed": [EXTENSION],
        "extensions": {EXTENSION: {"lights": [light]}},
        "scene": 0,
        "scenes": [{"name": name, "nodes": [0], "extensions": {EXTENSION: {"light": 0}}}],
        "nodes": [{"name": "probe", "translation": [float(v) for v in x],
                   "extras": {"t": t, **(extras or {})}}],
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": views,
        "images": images,
    }
    json_chunk = _pad(json.dumps(doc, separators=(",", ":")).encode(), b" ")
    bin_chunk = bytes(blob)
    total = 12 + 8 + len(json_chunk) + 8 + len(bin_chunk)
    return (struct.pack("<III", GLB_MAGIC, GLB_VERSION, total) + struct.pack("<II", len(json_chunk), CHUNK_JSON)
            + json_chunk + struct.pack("<II", len(bin_chunk), CHUNK_BIN) + bin_chunk)


def read_glb(data: bytes) -> tuple[dict, bytes]:
    """(JSON document, binary chunk) of a .glb (for tests and round trips)."""
    magic, version, total = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC or version != 2 or total != len(data):
        raise ValueError("not a glTF 2.0 binary file")
    jlen, jtype = struct.unpack_from("<II", data, 12)
    doc = json.loads(data[20:20 + jlen])
    blen, _ = struct.unpack_from("<II", data, 20 + jlen)
    return doc, data[28 + jlen:28 + jlen + blen]


__all__ = ["build_glb", "read_glb", "rgbd_encode", "rgbd_decode", "irradiance_coefficients", "EXTENSION"]
