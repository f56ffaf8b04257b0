"""Scene bounds: the box and time range a light field is normalised to.

A field's inputs are mapped to [-1, 1] (positions per axis, time over the capture) so that
positional encodings and grids see the same numeric range for a shoebox room and a hall.
The box comes from the unprojected depth (where probes can be placed) plus the camera
positions (probes sit between the camera and the surfaces), made robust to outliers and
to degenerate depth:

1. keep finite points; take the per-axis 1st..99th percentiles (`PERCENTILES`), so a few
   depth spikes (sky through a window, sensor noise) do not blow the box up;
2. grow each axis to at least `MIN_EXTENT_M` around its centre, so a flat wall (zero
   thickness) or a single valid point never makes the normalisation divide by zero;
3. pad each side by `MARGIN_FRACTION` of the extent, so probes placed just in front of
   the surfaces are inside.

With no finite point at all the box falls back to a `FALLBACK_HALF_EXTENT_M` cube around
the first camera (or the origin) and `fallback=True` is recorded, so the engine can warn.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

PERCENTILES = (1.0, 99.0)
MIN_EXTENT_M = 0.5  # a flat wall or a single point still gets half a metre of depth
MARGIN_FRACTION = 0.1  # per side, of the (minimum-enforced) extent
FALLBACK_HALF_EXTENT_M = 1.0  # unit box (2 m cube) around the camera without any valid depth


class BoundsError(ValueError):
    """Bounds given explicitly (e.g. read from JSON) are malformed."""


@dataclass(frozen=True)
class SceneBounds:
    """Axis-aligned box [lo, hi] (world metres) and time range [t0, t1] (seconds)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    t0: float = 0.0
    t1: float = 0.0
    fallback: bool = False  # True when no valid depth existed and the box is a guess

    def __post_init__(self):
        lo = tuple(float(v) for v in self.lo)
        hi = tuple(float(v) for v in self.hi)
        if len(lo) != 3 or len(hi) != 3:
            raise BoundsError(f"bounds lo/hi must have 3 values, got lo={self.lo}, hi={self.hi}")
        for name, vals in (("lo", lo), ("hi", hi)):
            if not all(math.isfinite(v) for v in vals):
                raise BoundsError(f"bounds.{name} must be finite, got {vals}")
        if not all(h > l for l, h in zip(lo, hi)):
            raise BoundsError(f"bounds.hi must exceed bounds.lo on every axis, got lo={lo}, hi={hi}")
        t0, t1 = float(self.t0), float(self.t1)
        if not (math.isfinite(t0) and math.isfinite(t1)) or t1 < t0:
            raise BoundsError(f"bounds time range must be finite with t1 >= t0, got t0={t0}, t1={t1}")
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)
        object.__setattr__(self, "t0", t0)
        object.__setattr__(self, "t1", t1)
        object.__setattr__(self, "fallback", bool(self.fallback))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_points(
        cls,
        points: torch.Tensor,
        times: torch.Tensor | None = None,
        camera_positions: torch.Tensor | None = None,
    ) -> "SceneBounds":
        """Bounds of unprojected depth points [..., 3] (non-finite rows ignored), the camera
        positions [C, 3] and the frame times [T] (seconds)."""
        pts = torch.as_tensor(points, dtype=torch.float64).reshape(-1, 3)
        pts = pts[torch.isfinite(pts).all(dim=-1)]
        cams = None
        if camera_positions is not None:
            cams = torch.as_tensor(camera_positions, dtype=torch.float64).reshape(-1, 3)
            cams = cams[torch.isfinite(cams).all(dim=-1)]
        t0, t1 = _time_range(times)

        if pts.shape[0] == 0:
            centre = cams[0] if cams is not None and cams.shape[0] else torch.zeros(3, dtype=torch.float64)
            half = FALLBACK_HALF_EXTENT_M
            return cls(tuple((centre - half).tolist()), tuple((centre + half).tolist()), t0, t1, fallback=True)

        q = torch.tensor([PERCENTILES[0] / 100.0, PERCENTILES[1] / 100.0], dtype=torch.float64)
        lo, hi = torch.quantile(pts, q, dim=0)  # each [3]
        if cams is not None and cams.shape[0]:
            lo = torch.minimum(lo, cams.min(dim=0).values)
            hi = torch.maximum(hi, cams.max(dim=0).values)
        centre, extent = 0.5 * (lo + hi), (hi - lo).clamp_min(MIN_EXTENT_M)
        half = 0.5 * extent + MARGIN_FRACTION * extent
        return cls(tuple((centre - half).tolist()), tuple((centre + half).tolist()), t0, t1)

    # ------------------------------------------------------------------ normalisation
    @property
    def has_duration(self) -> bool:
        return self.t1 > self.t0

    def normalize_x(self, x: torch.Tensor) -> torch.Tensor:
        """World positions [..., 3] -> [-1, 1]^3 inside the box (not clamped outside)."""
        lo = torch.tensor(self.lo, dtype=x.dtype, device=x.device)
        hi = torch.tensor(self.hi, dtype=x.dtype, device=x.device)
        return 2.0 * (x - lo) / (hi - lo) - 1.0

    def normalize_t(self, t: torch.Tensor) -> torch.Tensor:
        """Seconds [...] -> [-1, 1] over [t0, t1]; a zero duration (single frame) maps to 0."""
        if not self.has_duration:
            return torch.zeros_like(t)
        return 2.0 * (t - self.t0) / (self.t1 - self.t0) - 1.0

    def knot_times(self, knots: int) -> torch.Tensor:
        """Seconds [knots] (float64) of `knots` time knots evenly over [t0, t1]: where the field's
        learned time curves (codes, view detail, emitters, observed surfaces) put theirs."""
        return self.t0 + torch.linspace(0.0, 1.0, int(knots), dtype=torch.float64) * (self.t1 - self.t0)

    def contains(self, x: torch.Tensor) -> torch.Tensor:
        """[...] bool: position inside the (padded) box. Non-finite positions are outside."""
        lo = torch.tensor(self.lo, dtype=x.dtype, device=x.device)
        hi = torch.tensor(self.hi, dtype=x.dtype, device=x.device)
        return ((x >= lo) & (x <= hi)).all(dim=-1)

    def contains_t(self, t: torch.Tensor) -> torch.Tensor:
        """[...] bool: time inside [t0, t1] (with a relative tolerance for float round-off)."""
        tol = 1e-6 * max(1.0, abs(self.t0), abs(self.t1))
        return (t >= self.t0 - tol) & (t <= self.t1 + tol)

    # ------------------------------------------------------------------ JSON
    def to_dict(self) -> dict:
        return {"lo": list(self.lo), "hi": list(self.hi), "t0": self.t0, "t1": self.t1, "fallback": self.fallback}

    @classmethod
    def from_dict(cls, data: dict) -> "SceneBounds":
        if not isinstance(data, dict):
            raise BoundsError(f"bounds must be an object, got {type(data).__name__}")
        missing = {"lo", "hi", "t0", "t1"} - set(data)
        if missing:
            raise BoundsError(f"bounds is missing {sorted(missing)}")
        try:
            return cls(tuple(data["lo"]), tuple(data["hi"]), data["t0"], data["t1"], bool(data.get("fallback", False)))
        except (TypeError, ValueError) as exc:
            if isinstance(exc, BoundsError):
                raise
            raise BoundsError(f"bounds values are malformed: {exc}") from exc


def _time_range(times) -> tuple[float, float]:
    if times is None:
        return 0.0, 0.0
    t = torch.as_tensor(times, dtype=torch.float64).reshape(-1)
    t = t[torch.isfinite(t)]
    if t.numel() == 0:
        return 0.0, 0.0
    return float(t.min()), float(t.max())
