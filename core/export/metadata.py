"""EXR header attributes our env maps carry, so a file says what it is once it leaves us.

Standard attributes: `chromaticities` (Rec. 709 / sRGB primaries, D65 white: the colour space
the frames are assumed to be in; radiance is linear). Custom attributes (prefix
`lightfield:`): probe position (world metres, our frame), time (seconds from the first
frame), units, layout, conventions and the artefact id. `envmap` (OpenEXR's latlong tag) is set
only on maps re-laid out in OpenEXR's own latlong convention (`core.export.usd`): ours is
rotated 180 degrees about +y from it, and a reader honouring the tag would turn it round.
"""
from __future__ import annotations

import numpy as np

from core.conventions import CONVENTIONS_SUMMARY

REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)  # red, green, blue, white (x, y)
UNITS = "relative linear radiance (uncalibrated: one unknown scale per artefact)"
LAYOUT = ("equirect H x 2H, row 0 up (+y), image centre looks along -z, +x right of centre, "
          "d = direction light arrives from (docs/conventions.md)")
PREFIX = "lightfield:"


def envmap_attributes(x=None, t: float | None = None, artefact_id: str | None = None,
                      layout: str = LAYOUT, extrapolated: str | None = None, **extra: str | float) -> dict:
    """EXR header attributes for one env map at probe `x` (metres) and time `t` (seconds)."""
    attrs: dict = {
        "chromaticities": REC709_CHROMATICITIES,
        PREFIX + "units": UNITS,
        PREFIX + "layout": layout,
        PREFIX + "conventions": CONVENTIONS_SUMMARY,
    }
    if x is not None:
        attrs[PREFIX + "probePosition"] = np.asarray(x, dtype=np.float32).reshape(3)
    if t is not None:
        attrs[PREFIX + "time"] = float(t)
    if artefact_id:
        attrs[PREFIX + "artefactId"] = str(artefact_id)
    if extrapolated:
        attrs[PREFIX + "extrapolated"] = extrapolated
    for key, value in extra.items():
        attrs[PREFIX + key] = value
    return attrs


def artefact_id(meta: dict, fallback: str = "") -> str:
    """A stable id for an artefact: `fallback` (the service's job id) when given, else the
    SHA-256 of its weights (what the CLI has)."""
    return str(fallback or (meta.get("weights") or {}).get("sha256") or "")
