"""EXR header attributes our env maps carry, so a file says what it is once it leaves us.

Standard attributes: `chromaticities` (Rec. 709 / sRGB primaries, D65 white: the colour space
the frames are assumed to be in; radiance is linear; with `colour="acescg"` the pixels are
converted to ACEScg (AP1 primaries, ACES white ~D60, Bradford adaptation) and the attribute
says AP1), and on sequence frames `timeCode` / `framesPerSecond` (`sequence_attributes`). Custom attributes (prefix
`lightfield:`): probe position (world metres, our frame), time (seconds from the first
frame), units, layout, conventions and the artefact id. `envmap` (OpenEXR's latlong tag) is set
only on maps re-laid out in OpenEXR's own latlong convention (`core.export.usd`): ours is
rotated 180 degrees about +y from it, and a reader honouring the tag would turn it round.
"""
from __future__ import annotations

import fractions

import numpy as np

from core.conventions import CONVENTIONS_SUMMARY

REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)  # red, green, blue, white (x, y)
# ACES AP1 primaries with the ACES white point (SMPTE ST 2065-1 / S-2014-004)
ACESCG_CHROMATICITIES = (0.713, 0.293, 0.165, 0.830, 0.128, 0.044, 0.32168, 0.33767)
COLOURS = {"rec709": REC709_CHROMATICITIES, "acescg": ACESCG_CHROMATICITIES}
_BRADFORD = np.array([[0.8951, 0.2664, -0.1614], [-0.7502, 1.7135, 0.0367], [0.0389, -0.0685, 1.0296]])
UNITS = "relative linear radiance (uncalibrated: one unknown scale per artefact)"
LAYOUT = ("equirect H x 2H, row 0 up (+y), image centre looks along -z, +x right of centre, "
          "d = direction light arrives from (docs/conventions.md)")
PREFIX = "lightfield:"


def _rgb_to_xyz(chromaticities) -> np.ndarray:
    """RGB -> XYZ matrix of a colour space given by its (x, y) primaries and white (the usual derivation)."""
    c = np.asarray(chromaticities, np.float64).reshape(4, 2)
    xyz = np.stack([c[:, 0] / c[:, 1], np.ones(4), (1 - c[:, 0] - c[:, 1]) / c[:, 1]], axis=1)  # Y = 1 each
    primaries, white = xyz[:3].T, xyz[3]
    return primaries * np.linalg.solve(primaries, white)[None, :]


def rec709_to(colour: str) -> np.ndarray:
    """3x3 matrix taking linear Rec. 709 (D65) RGB to `colour` ('rec709' or 'acescg', white adapted by Bradford)."""
    if colour not in COLOURS:
        raise ValueError(f"colour must be one of {', '.join(COLOURS)}, got {colour!r}")
    src, dst = _rgb_to_xyz(REC709_CHROMATICITIES), _rgb_to_xyz(COLOURS[colour])
    w_src, w_dst = _BRADFORD @ src.sum(axis=1), _BRADFORD @ dst.sum(axis=1)
    cat = np.linalg.inv(_BRADFORD) @ np.diag(w_dst / w_src) @ _BRADFORD
    return np.linalg.inv(dst) @ cat @ src


def in_colour(env: np.ndarray, colour: str = "rec709") -> np.ndarray:
    """Our (linear Rec. 709) map [..., 3] in `colour`, float32."""
    a = np.asarray(env, np.float32)
    return a if colour == "rec709" else (a.astype(np.float64) @ rec709_to(colour).T).astype(np.float32)


def sequence_attributes(t: float, fps: float | None) -> dict:
    """`framesPerSecond` (a rational close to `fps`) and the SMPTE `timeCode` of time t (seconds,
    counted at the nearest whole frame rate), the standard attributes compositors read on sequences."""
    import OpenEXR  # noqa: PLC0415 — OpenEXR is heavy: imported when used

    if not fps or fps <= 0 or t < 0:
        return {}
    rate = fractions.Fraction(fps).limit_denominator(1001)
    whole = max(1, round(fps))
    frames = int(round(t * fps))
    seconds, frame = divmod(frames, whole)
    minutes, seconds = divmod(seconds, 60)
    hours, minutes = divmod(minutes, 60)
    code = OpenEXR.TimeCode()
    code.hours, code.minutes, code.seconds, code.frame = hours % 24, minutes, seconds, frame
    return {"framesPerSecond": rate, "timeCode": code}


def envmap_attributes(x=None, t: float | None = None, artefact_id: str | None = None,
                      layout: str = LAYOUT, extrapolated: str | None = None, colour: str = "rec709",
                      **extra: str | float) -> dict:
    """EXR header attributes for one env map at probe `x` (metres) and time `t` (seconds)."""
    if colour not in COLOURS:
        raise ValueError(f"colour must be one of {', '.join(COLOURS)}, got {colour!r}")
    attrs: dict = {
        "chromaticities": COLOURS[colour],
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
