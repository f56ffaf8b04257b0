"""USD hand-off: a stage with a UsdLux DomeLight textured by our env map (.usda + EXR, or one .usdz).

UsdLux's DomeLight (with the stage's up axis +Y) follows OpenEXR's latitude-longitude
convention: pixel (min x, min y) has latitude +pi/2 and longitude +pi, latitude 0 /
longitude 0 points along +z, longitude +pi/2 along +x. Ours puts -z at the image centre:
OpenEXR's direction at column j is ours rotated 180 degrees about +y, so the texture we ship
is our map rolled by half a turn (`to_openexr_latlong`), carrying OpenEXR's `envmap = latlong`
tag. The stage: `upAxis = "Y"`, `metersPerUnit = 1`, a `/Probe` Xform at the query position
(a dome is at infinity; the position documents where the light was measured) holding
`/Probe/EnvLight` (DomeLight, `inputs:texture:format = "latlong"`), with our metadata in
`customData`.

A .usdz is an uncompressed zip whose first file is the stage and whose file data starts on
64-byte boundaries (USDZ specification); `usdz_package` writes one without needing usd-core.
"""
from __future__ import annotations

import io
import json
import zipfile

import numpy as np

from core.export.metadata import envmap_attributes

OPENEXR_LAYOUT = ("OpenEXR latlong: row 0 up (+y), column 0 at longitude +pi, image centre looks along +z "
                  "(our map rolled by W/2; docs/integrations.md)")


def to_openexr_latlong(env: np.ndarray) -> np.ndarray:
    """Our equirect map -> OpenEXR's latlong layout (a half-turn roll about +y)."""
    a = np.asarray(env)
    return np.roll(a, -a.shape[1] // 2, axis=1)


def openexr_latlong_direction(row: np.ndarray, col: np.ndarray, height: int) -> np.ndarray:
    """Unit direction of pixel centres in OpenEXR's latlong convention (as documented by OpenEXR)."""
    width = 2 * height
    lat = np.pi / 2 - np.pi * (np.asarray(row) + 0.5) / height
    lon = np.pi - 2 * np.pi * (np.asarray(col) + 0.5) / width
    return np.stack((np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)), axis=-1)


def dome_texture_exr(env: np.ndarray, x=None, t: float | None = None, artefact: str | None = None) -> bytes:
    """The DomeLight's texture: OpenEXR-latlong float32 EXR with our metadata attributes."""
    import OpenEXR

    from core.io.exr import encode_exr

    attrs = envmap_attributes(x, t, artefact, layout=OPENEXR_LAYOUT)
    attrs["envmap"] = OpenEXR.ENVMAP_LATLONG
    return encode_exr(to_openexr_latlong(np.asarray(env, np.float32)), attributes=attrs)


def _usd_string(text: str) -> str:
    return json.dumps(text)  # a JSON string literal is a valid usda string literal (quotes, escapes)


def dome_light_usda(texture: str, x, t: float | None, artefact: str | None = None, intensity: float = 1.0) -> str:
    """The stage text (usda) referencing `texture` (a relative path inside the package or folder)."""
    if "@" in texture or "\n" in texture:
        raise ValueError(f"texture path {texture!r} cannot be written as a USD asset path")
    px, py, pz = (float(v) for v in x)
    custom = {"lightfield:t": t, "lightfield:artefactId": artefact or "", "lightfield:units": "relative linear radiance"}
    custom_text = "\n".join(
        f"            {'double' if isinstance(v, float) else 'string'} {k.replace(':', '_')} = "
        f"{repr(float(v)) if isinstance(v, float) else _usd_string(str(v))}"
        for k, v in custom.items() if v is not None)
    return f'''#usda 1.0
(
    defaultPrim = "Probe"
    doc = "lightfield: env map at x = ({px:g}, {py:g}, {pz:g}) m{"" if t is None else f", t = {t:g} s"}"
    metersPerUnit = 1
    upAxis = "Y"
)

def Xform "Probe" (
    customData = {{
        dictionary lightfield = {{
{custom_text}
        }}
    }}
)
{{
    double3 xformOp:translate = ({px!r}, {py!r}, {pz!r})
    uniform token[] xformOpOrder = ["xformOp:translate"]

    def DomeLight "EnvLight"
    {{
        float inputs:intensity = {float(intensity)!r}
        asset inputs:texture:file = @{texture}@
        token inputs:texture:format = "latlong"
    }}
}}
'''


def usdz_package(files: dict[str, bytes]) -> bytes:
    """Uncompressed zip with every file's data 64-byte aligned; the first entry is the stage."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as z:
        for name, data in files.items():
            info = zipfile.ZipInfo(name, date_time=(2020, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_STORED
            header_end = buf.tell() + 30 + len(name.encode())  # local file header + name
            pad = -(header_end + 4) % 64  # an extra field (id 0x1986, length) padded to the boundary
            info.extra = (b"\x86\x19" + pad.to_bytes(2, "little") + bytes(pad))
            z.writestr(info, data)
    return buf.getvalue()


def usdz(env: np.ndarray, x, t: float | None, artefact: str | None = None) -> bytes:
    """One .usdz: `probe.usda` + `envmap.exr` (OpenEXR latlong)."""
    stage = dome_light_usda("envmap.exr", x, t, artefact).encode()
    return usdz_package({"probe.usda": stage, "envmap.exr": dome_texture_exr(env, x, t, artefact)})


__all__ = ["to_openexr_latlong", "openexr_latlong_direction", "dome_texture_exr", "dome_light_usda",
           "usdz_package", "usdz"]
