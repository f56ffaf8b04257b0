"""The JSON every hand-off product is, as pydantic models: the API serves them (they are its OpenAPI
schema) and the CLI prints or writes the very same models, so a client can switch between the two
without renaming a field. One model per product: SH with the main light (`SphericalHarmonics`),
the Unity probe grid (`UnityProbeGrid`), the ARKit layout (`ArkitProbe`).
"""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

from core.export.sh_layouts import LAYOUT_NAMES, pack

SHLayoutName = Literal["arcore", "threejs", "babylon", "unity", "arkit"]
assert set(SHLayoutName.__args__) == set(LAYOUT_NAMES)  # the table in core.export.sh_layouts is the source

SH_BAND_ORDER = ("coefficient k = 0..8 is (l, m) = (0,0), (1,-1), (1,0), (1,1), (2,-2), (2,-1), (2,0), (2,1), "
                 "(2,2), i.e. 1, y, z, x, xy, yz, 3z^2-1, xz, x^2-y^2; each layout's signs, scale, axes and "
                 "packing: core.export.sh_layouts (docs/integrations.md)")


class AnswerGrade(BaseModel):
    """How far to trust an answer: the job's self-check (core.engine.self_check) and how much of the
    sphere was seen rather than filled (docs/api.md)."""

    grade: str = Field(description="'explained', 'partly explained', 'worse than a constant map' or 'unchecked'")
    seen_share: float | None = Field(description="share of the sphere the frames saw from their cameras "
                                     "(0 when the answer is the constant map)")
    filled_share: float | None = Field(description="the rest: filled by the prior and the field")
    residual_ratio: float | None = Field(description="the field's residual over the constant map's on the frames")
    fallback: str | None = Field(description="why the answer is the capture's constant map; null: the field's")

    @classmethod
    def of(cls, meta: dict) -> "AnswerGrade":
        """From an artefact's lightfield.json (its `quality` block; 'unchecked' without one)."""
        q = meta.get("quality") or {}
        fallback = (q.get("fallback") or {}).get("reason")
        seen = 0.0 if fallback else q.get("seen_share")
        return cls(grade=q.get("grade") or "unchecked", seen_share=seen,
                   filled_share=None if seen is None else round(1.0 - seen, 4),
                   residual_ratio=q.get("residual_ratio"), fallback=fallback)


class Flags(BaseModel):
    x: bool = Field(description="x lies outside the region the field was estimated in")
    t: bool = Field(description="t lies outside the capture's time range")


class DominantLight(BaseModel):
    direction: tuple[float, float, float] = Field(description="unit vector the light arrives from (world); "
                                                  "the best guess even when found is false")
    intensity: tuple[float, float, float] = Field(
        description="RGB intensity of a directional light (radiance x sr, "
        "relative units): ambient SH + this light reproduce the map's irradiance"
    )
    solid_angle: float = Field(description="effective steradians of the light's lobe")
    found: bool = Field(description="confidence >= the threshold: the light is real; when false, use the ambient SH "
                        "alone (coefficients_with_light) or the light at your own risk")
    confidence: float = Field(
        description="0..1: share of the irradiance facing the light that it gives x (1 - 1/contrast)"
    )
    reason: str = Field(description="why it was or was not found, in words")
    sharpness: float = Field(0.0, description="von Mises-Fisher kappa of the lobe (large = compact)")
    contrast: float = Field(1.0, description="mean radiance of the light's cap over its surroundings")
    irradiance_error: float = Field(0.0, description="worst |E(ambient + light) - E(map)| over normals / max E(map)")

    @classmethod
    def of(cls, light) -> "DominantLight":
        """From a core.lights.DominantLight."""
        return cls(
            direction=tuple(float(v) for v in light.direction),
            intensity=tuple(float(v) for v in light.intensity_rgb),
            solid_angle=float(light.solid_angle),
            found=bool(light.found),
            confidence=float(light.confidence),
            reason=light.reason,
            sharpness=float(light.sharpness),
            contrast=float(light.contrast) if light.contrast != float("inf") else 1e30,
            irradiance_error=float(light.irradiance_error),
        )


class SphericalHarmonics(BaseModel):
    x: tuple[float, float, float]
    t: float | None = Field(description="seconds from the first frame; null when not given for a static field")
    extrapolated: Flags
    layout: SHLayoutName = Field(description="layout of `coefficients` and `coefficients_with_light`")
    coefficients: list[float] = Field(description="ambient SH (the map without the main light), 27 floats in `layout`")
    coefficients_with_light: list[float] = Field(description="SH of the whole map (for clients without a "
                                                 "directional light), 27 floats in `layout`")
    arcore_27: list[float] = Field(description="ambient SH in ARCore's 27-float layout (9 coefficients x RGB "
                                   "interleaved, Condon-Shortley signs), whatever the layout")
    band_order: str = SH_BAND_ORDER
    dominant_light: DominantLight
    grade: AnswerGrade | None = None

    @classmethod
    def of(cls, x, t, flags: Flags, layout: str, light, full_sh) -> "SphericalHarmonics":
        """From a core.lights.DominantLight (its ambient SH) and the whole map's SH [9, 3]."""
        return cls(x=tuple(float(v) for v in x), t=None if t is None else float(t), extrapolated=flags, layout=layout,
                   coefficients=pack(light.ambient_sh, layout), coefficients_with_light=pack(full_sh, layout),
                   arcore_27=pack(light.ambient_sh, "arcore"), dominant_light=DominantLight.of(light))


class Region(BaseModel):
    lo: tuple[float, float, float] = Field(description="corner, world metres (ours)")
    hi: tuple[float, float, float] = Field(description="opposite corner, world metres (ours)")
    source: str = Field(description="how the region was found")


class UnityProbe(BaseModel):
    position: tuple[float, float, float] = Field(description="world metres, our frame")
    position_unity: tuple[float, float, float] = Field(description="Unity coordinates (z flipped)")
    sh: list[list[float]] = Field(description="SphericalHarmonicsL2 [channel][k]: Unity's convention (irradiance "
                                  "x basis constant / pi, on Unity's axes)")
    extrapolated: Flags = Field(description="per probe: outside the region the captures cover / the time range")


class UnityProbeGrid(BaseModel):
    about: str = ("Unity light probes: probes[i].position_unity are Unity coordinates (z flipped from ours); sh is "
                  "SphericalHarmonicsL2 [channel][k] in Unity's convention (docs/integrations.md)")
    t: float | None
    grid: tuple[int, int, int]
    covered: Region = Field(description="the region the captures cover: the default grid lies inside it")
    extrapolated_probes: int = Field(description="how many probes lie outside `covered` or the time range")
    probes: list[UnityProbe]
    artefact: str
    grade: AnswerGrade | None = None


class ArkitProbe(BaseModel):
    x: tuple[float, float, float]
    t: float | None
    extrapolated: Flags
    pixel_format: Literal["rgba16Float", "rgba8Unorm_srgb"]
    size: int = Field(description="cube face edge in texels")
    bytes_per_row: int
    bytes_per_image: int
    slices_base64: list[str] = Field(description="6 Metal cube slices +X, -X, +Y, -Y, +Z, -Z, each for "
                                     "replace(region:mipmapLevel:slice:withBytes:bytesPerRow:bytesPerImage:)")
    sh_planes: list[float] = Field(description="ambient SH as three planes of 9 (R, G, B), layout 'arkit' "
                                   "(Apple does not document the basis signs)")
    dominant_light: DominantLight
    grade: AnswerGrade | None = None


__all__ = ["AnswerGrade", "Flags", "DominantLight", "SphericalHarmonics", "Region", "UnityProbe", "UnityProbeGrid",
           "ArkitProbe", "SHLayoutName", "SH_BAND_ORDER"]
