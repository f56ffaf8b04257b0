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

The stage is built with Pixar's usd-core (UsdLux.DomeLight, UsdGeom) and packaged by
`UsdUtils.CreateNewARKitUsdzPackage` (one flattened layer, 64-byte aligned stored zip: the
USDZ rules), so no USD text or zip layout is written by hand here. usd-core is the `usd` extra
(~160 MB installed); without it these functions raise `USDUnavailable`, which names the extra.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from core.export.metadata import envmap_attributes

OPENEXR_LAYOUT = ("OpenEXR latlong: row 0 up (+y), column 0 at longitude +pi, image centre looks along +z "
                  "(our map rolled by W/2; docs/integrations.md)")
INSTALL_HINT = "pip install 'lightfield[usd]' (or: pip install usd-core)"


class USDUnavailable(ValueError):
    """usd-core is not installed: USD export cannot run."""


def _pxr():
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdUtils  # noqa: PLC0415 — optional: an ImportError is handled here
    except ImportError as exc:
        raise USDUnavailable(f"USD export needs Pixar's usd-core, which is not installed: {INSTALL_HINT}") from exc
    return Gf, Sdf, Usd, UsdGeom, UsdLux, UsdUtils


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
    import OpenEXR  # noqa: PLC0415 — OpenEXR is heavy: imported when used

    from core.io.exr import encode_exr  # noqa: PLC0415 — core.io.exr pulls in av, cv2, OpenEXR, PIL: imported when used

    attrs = envmap_attributes(x, t, artefact, layout=OPENEXR_LAYOUT)
    attrs["envmap"] = OpenEXR.ENVMAP_LATLONG
    return encode_exr(to_openexr_latlong(np.asarray(env, np.float32)), attributes=attrs)


def dome_light_stage(path, texture: str, x, t: float | None, artefact: str | None = None, intensity: float = 1.0,
                     grade: dict | None = None):
    """A new USD stage at `path` (.usda/.usdc): /Probe (an Xform at x, our metadata in customData)
    holding /Probe/EnvLight, a DomeLight textured by `texture` (a path relative to the stage);
    `grade` (core.export.schema.AnswerGrade as a dict) in the layer's customLayerData."""
    Gf, Sdf, Usd, UsdGeom, UsdLux, _ = _pxr()
    if "@" in texture or "\n" in texture:
        raise ValueError(f"texture path {texture!r} cannot be written as a USD asset path")
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    px, py, pz = (float(v) for v in x)
    stage.GetRootLayer().documentation = (f"lightfield: env map at x = ({px:g}, {py:g}, {pz:g}) m"
                                          + ("" if t is None else f", t = {t:g} s"))
    probe = UsdGeom.Xform.Define(stage, "/Probe")
    probe.AddTranslateOp().Set(Gf.Vec3d(px, py, pz))
    stage.SetDefaultPrim(probe.GetPrim())
    if grade:  # nulls have no USD value: left out
        stage.GetRootLayer().customLayerData = {f"lightfield:{k}": v for k, v in grade.items() if v is not None}
    custom = {"t": None if t is None else float(t), "artefactId": artefact or "", "units": "relative linear radiance"}
    for key, value in custom.items():
        if value is not None:
            probe.GetPrim().SetCustomDataByKey(f"lightfield:{key}", value)
    dome = UsdLux.DomeLight.Define(stage, "/Probe/EnvLight")
    dome.CreateIntensityAttr().Set(float(intensity))
    dome.CreateTextureFileAttr().Set(Sdf.AssetPath(texture))
    dome.CreateTextureFormatAttr().Set(UsdLux.Tokens.latlong)
    return stage


def dome_light_usda(texture: str, x, t: float | None, artefact: str | None = None, intensity: float = 1.0,
                    grade: dict | None = None) -> str:
    """The stage as usda text, referencing `texture` (a relative path inside the package or folder)."""
    with tempfile.TemporaryDirectory() as tmp:
        stage = dome_light_stage(Path(tmp) / "probe.usda", texture, x, t, artefact, intensity, grade)
        return stage.GetRootLayer().ExportToString()


def usdz(env: np.ndarray, x, t: float | None, artefact: str | None = None, grade: dict | None = None) -> bytes:
    """One .usdz packaged by usd-core's UsdUtils.CreateNewARKitUsdzPackage: the stage (flattened to
    one layer) and its texture `envmap.exr` (OpenEXR latlong)."""
    *_, UsdUtils = _pxr()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        (root / "envmap.exr").write_bytes(dome_texture_exr(env, x, t, artefact))
        dome_light_stage(root / "probe.usda", "envmap.exr", x, t, artefact, grade=grade).Save()
        if not UsdUtils.CreateNewARKitUsdzPackage(str(root / "probe.usda"), str(root / "probe.usdz")):
            raise RuntimeError("usd-core could not package the stage as a .usdz")
        return (root / "probe.usdz").read_bytes()


__all__ = ["to_openexr_latlong", "openexr_latlong_direction", "dome_texture_exr", "dome_light_stage",
           "dome_light_usda", "usdz", "USDUnavailable", "INSTALL_HINT"]
