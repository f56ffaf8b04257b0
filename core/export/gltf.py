"""glTF 2.0 binary (.glb) carrying one image-based light (EXT_lights_image_based) and, when the
map has one, its main light as a KHR_lights_punctual directional light.

The container (JSON + binary chunk, buffer views, padding) is written and read by pygltflib;
this module only decides what goes in it.

What EXT_lights_image_based specifies (KhronosGroup/glTF, extensions/2.0/Vendor/EXT_lights_image_based),
and how its reference loader (Babylon.js, @babylonjs/loaders) reads it:
- `irradianceCoefficients`: 9 x [r, g, b] SH of the *irradiance*, read by Babylon's
  `SphericalHarmonics.FromArray`, whose basis carries the Condon-Shortley phase: our radiance SH
  convolved with the clamped cosine, odd-m entries negated (core.export.sh_layouts 'babylon';
  checked with @babylonjs/core in tests/test_export_node.py). glTF's frame is ours (right-handed,
  +y up), so no axis change.
- `specularImages`: N mips x 6 faces (+X, -X, +Y, -Y, +Z, -Z) of a GGX-prefiltered cube map,
  mips evenly spaced in roughness 0..1 (core.export.prefilter), power-of-two faces.
- HDR images are 4-channel PNGs packed as RGBD: stored rgb = (value * D)^(1/2.2), alpha = D,
  value = stored_linear / D; D = floor(min(255 / max(rgb), 255)) / 255 (Babylon.js's packing).
  RGBD holds values up to 255. A brighter map is divided, images, SH and main light alike, by
  the scale N that brings its maximum to 255, with `intensity` left at 1 and N recorded in the
  probe node's `extras.radianceScale` (multiply by it for the field's units). Not `intensity = N`:
  Babylon multiplies the SH by `intensity` in its loader *and* by the texture level (= intensity)
  in its PBR shader, so its diffuse light would come out N times too bright.
- "each saved image must be flipped about its vertical axis": every face is mirrored left-right
  before encoding.

Main light (`main_light`, found by core.lights): a node `main light` whose -Z axis points along
the direction the light travels (KHR_lights_punctual), `color` = its RGB normalised to a maximum
of 1 and `intensity` = that maximum: the irradiance it gives a surface facing it, in the map's
relative units. The irradiance SH are then the *ambient* SH (the map without the light), so
SH + light add up to the map's irradiance; the specular images keep the whole map (reflections
show the lamp). Without a light (or `main_light=None`) the SH are the whole map's.
The scene holds a node `probe` at the query position x (metres), with `extras` giving the query
(x, t), the conventions and the artefact id.
"""
from __future__ import annotations

import json

import numpy as np

from core.export.sh_layouts import to_layout
from core.io.images import UNTAGGED, encode_png

EXTENSION = "EXT_lights_image_based"
PUNCTUAL = "KHR_lights_punctual"
RGBD_MAX = 255.0


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
    """Our radiance SH [9, 3] -> the extension's irradiance SH, 9 x [r, g, b] (Babylon's basis)."""
    return to_layout(np.asarray(radiance_sh, np.float64).reshape(9, 3), "babylon").tolist()


def light_rotation(direction) -> list[float]:
    """Quaternion [x, y, z, w] turning a node's +Z onto `direction` (the light arrives from it), so
    its -Z (KHR_lights_punctual's direction of travel) points from the light into the scene."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    if d[2] < -1.0 + 1e-9:  # opposite +Z: half a turn about x
        return [1.0, 0.0, 0.0, 0.0]
    q = np.array([-d[1], d[0], 0.0, 1.0 + d[2]])
    return (q / np.linalg.norm(q)).tolist()


def build_glb(mips: list[np.ndarray], radiance_sh: np.ndarray, x, t: float | None,
              extras: dict | None = None, name: str = "lightfield probe", main_light=None) -> bytes:
    """A .glb with one EXT_lights_image_based light: `mips[i]` float [6, S >> i, S >> i, 3]
    (prefiltered, roughness i / (N - 1)), `radiance_sh` our [9, 3] SH of the same map.
    `main_light`: a core.lights.DominantLight; when given and found, a KHR_lights_punctual
    directional light and the ambient SH (see the module doc)."""
    import pygltflib as g  # noqa: PLC0415 — pygltflib is heavy: imported when used

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
            png = encode_png(rgbd_encode(face[:, ::-1] / scale), UNTAGGED)  # mirrored left-right (see module doc)
            views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(png)))
            blob += png + bytes(-len(png) % 4)
            images.append(g.Image(bufferView=len(views) - 1, mimeType="image/png"))
            faces.append(len(images) - 1)
        specular.append(faces)
    light_found = main_light is not None and bool(main_light.found)
    sh = np.asarray(main_light.ambient_sh.detach().cpu().double() if light_found else radiance_sh, np.float64)
    ibl = {"name": name, "intensity": 1.0, "rotation": [0.0, 0.0, 0.0, 1.0],
           "irradianceCoefficients": irradiance_coefficients(sh / scale),
           "specularImageSize": size, "specularImages": specular}
    nodes = [g.Node(name="probe", translation=[float(v) for v in x],
                    extras={"t": t, "irradiance": "ambient (main light separate)" if light_found else "whole map",
                            "radianceScale": float(scale), **(extras or {})})]
    used, root_ext = [EXTENSION], {EXTENSION: {"lights": [ibl]}}
    if light_found:
        rgb = np.asarray(main_light.intensity_rgb.detach().cpu().double(), np.float64) / scale
        strength = float(rgb.max())
        color = (rgb / strength).tolist() if strength > 0 else [1.0, 1.0, 1.0]
        used.append(PUNCTUAL)
        root_ext[PUNCTUAL] = {"lights": [{"type": "directional", "name": "main light", "color": color,
                                          "intensity": strength}]}
        nodes.append(g.Node(name="main light", rotation=light_rotation(main_light.direction.detach().cpu().double()),
                            extensions={PUNCTUAL: {"light": 0}},
                            extras={"confidence": float(main_light.confidence), "reason": main_light.reason}))
    doc = g.GLTF2(
        asset=g.Asset(version="2.0", generator="lightfield (core/export/gltf.py, pygltflib)"),
        extensionsUsed=used, extensions=root_ext, scene=0,
        scenes=[g.Scene(name=name, nodes=list(range(len(nodes))), extensions={EXTENSION: {"light": 0}})],
        nodes=nodes, buffers=[g.Buffer(byteLength=len(blob))], bufferViews=views, images=images)
    doc.set_binary_blob(bytes(blob))
    return b"".join(doc.save_to_bytes())


def read_glb(data: bytes) -> tuple[dict, bytes]:
    """(JSON document, binary chunk) of a .glb, read by pygltflib (for tests and round trips)."""
    import pygltflib as g  # noqa: PLC0415 — pygltflib is heavy: imported when used

    doc = g.GLTF2.load_from_bytes(bytes(data))
    if doc is None or doc.asset is None or doc.asset.version != "2.0":
        raise ValueError("not a glTF 2.0 binary file")
    return json.loads(doc.to_json()), bytes(doc.binary_blob() or b"")


__all__ = ["build_glb", "read_glb", "rgbd_encode", "rgbd_decode", "irradiance_coefficients", "light_rotation",
           "EXTENSION", "PUNCTUAL"]
