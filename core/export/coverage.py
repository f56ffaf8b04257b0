"""Where a field knows the light: the region its captures cover, for flagging probes and for
default probe grids.

A field's box (`SceneBounds`) is the 1st..99th percentile box of the captures' depth points and
camera positions, grown to a minimum extent and then padded by `MARGIN_FRACTION` per side
(core.fields.components.normalization), so that a probe just in front of a wall still evaluates. The
padding is outside the room: walls, floor and ceiling sit at the unpadded box's faces, and the
field is only constrained inside it. `covered_region` undoes the padding; a probe outside it is
extrapolated even where the field's own flag (the padded box) says it is not. A box built without
any depth (`fallback`) is a guess around the camera: the region says so.
"""
from __future__ import annotations

import numpy as np

from core.fields.components.normalization import MARGIN_FRACTION


def covered_region(bounds) -> tuple[np.ndarray, np.ndarray, str]:
    """(lo [3], hi [3], how it was found) of the region the captures cover."""
    lo, hi = np.asarray(bounds.lo, np.float64), np.asarray(bounds.hi, np.float64)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 / (1.0 + 2.0 * MARGIN_FRACTION)
    source = ("the captures' depth and camera box (the field's box without its "
              f"{MARGIN_FRACTION:.0%} margin)")
    if getattr(bounds, "fallback", False):
        source = "a guess: the capture had no valid depth, so the box is a fixed cube around the camera"
    return centre - half, centre + half, source


def inside(lo, hi, xs, tolerance: float = 1e-9) -> np.ndarray:
    """[N] bool: positions [N, 3] inside the box [lo, hi]."""
    x = np.atleast_2d(np.asarray(xs, np.float64))
    return np.all((x >= np.asarray(lo) - tolerance) & (x <= np.asarray(hi) + tolerance), axis=-1)


def cell_centre_grid(lo, hi, counts) -> np.ndarray:
    """[N, 3] positions at the centres of a counts[0] x counts[1] x counts[2] split of [lo, hi]: every
    probe strictly inside the box, none on a wall, the floor or the ceiling."""
    axes = [a + (np.arange(int(n)) + 0.5) * (b - a) / int(n) for a, b, n in zip(lo, hi, counts)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
