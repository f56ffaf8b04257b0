"""Evaluating a cached light field for the HTTP layer (blocking: run in a threadpool).

Validation of the query values lives here too, so every endpoint refuses the same things
with the same codes: x must be three finite numbers, t finite, sizes within the limits.
"""
from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from service.errors import InvalidInput, PayloadTooLarge
from service.fieldcache import CachedField

MAX_ABS_EV = 64.0
SH_ENVMAP_HEIGHT = 128  # enough to isolate a small light; SH only needs band 2


@dataclass(frozen=True)
class EvalFlags:
    x: bool
    t: bool

    def header(self) -> str:
        """X-Lightfield-Extrapolated: the axes outside the trained range, or 'none'."""
        return ",".join(a for a, on in (("x", self.x), ("t", self.t)) if on) or "none"


def parse_x(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise InvalidInput(f"x must be three finite numbers 'X,Y,Z' (metres), got {text[:80]!r}", code="invalid_x")
    return values  # type: ignore[return-value]


def check_t(t: float) -> float:
    if not math.isfinite(t):
        raise InvalidInput(f"t must be a finite number of seconds, got {t}", code="invalid_t")
    return float(t)


def check_ev(ev: float) -> float:
    if not math.isfinite(ev) or abs(ev) > MAX_ABS_EV:
        raise InvalidInput(f"ev must be finite and within +-{MAX_ABS_EV:g}, got {ev}", code="invalid_ev")
    return float(ev)


def check_size(value: int, limit: int, name: str) -> int:
    if value > limit:
        raise PayloadTooLarge(f"{name}={value} exceeds the limit of {limit}", code=f"{name}_too_large")
    return value


def _flags(raw: dict) -> EvalFlags:
    """From the engine's per-query flag dict (LightFieldArtefact and BakedField alike)."""
    return EvalFlags(bool(raw["extrapolated_x"]), bool(raw["extrapolated_t"]))


def _numpy(hdr) -> np.ndarray:
    if hasattr(hdr, "detach"):
        hdr = hdr.detach().cpu().numpy()
    return np.ascontiguousarray(hdr, dtype=np.float32)


@contextmanager
def _as_invalid_input():
    """The engine's QueryError (a query it refuses) becomes the API's 422 invalid_query."""
    from core.fields.artefact import QueryError

    try:
        yield
    except QueryError as exc:
        raise InvalidInput(str(exc), code="invalid_query") from None


def envmap(cf: CachedField, x, t: float, height: int) -> tuple[np.ndarray, EvalFlags]:
    with _as_invalid_input(), cf.lock:
        hdr, flags = cf.artefact.envmap(x, t, height)
    return _numpy(hdr), _flags(flags)


def envmap_with_quality(cf: CachedField, x, t: float, height: int, quality: str):
    """(hdr, flags, quality used): 'fast' reads the baked lattice, anything else the field."""
    if quality == "fast":
        return (*baked_envmap(cf, x, t, height), "fast")
    return (*envmap(cf, x, t, height), "exact")


def baked_envmap(cf: CachedField, x, t: float, height: int) -> tuple[np.ndarray, EvalFlags]:
    """Interpolated from the baked lattice (the worker bakes it after distillation; an
    artefact without one is baked here once and saved beside it, atomically)."""
    from core.fields.bake import load_or_bake

    with _as_invalid_input(), cf.lock:
        if cf.baked is None:
            cf.baked = load_or_bake(cf.artefact, save=True)
        hdr, flags = cf.baked.envmap(x, t, height)
    return _numpy(hdr), _flags(flags)


def envmaps(cf: CachedField, xs, ts, height: int) -> tuple[np.ndarray, list[EvalFlags]]:
    with _as_invalid_input(), cf.lock:
        hdrs, flags = cf.artefact.envmaps(xs, ts, height)
    return _numpy(hdrs), [_flags(f) for f in flags]


def spherical_harmonics(cf: CachedField, x, t: float):
    """(dominant light with ambient SH, SH of the whole map, flags): ARCore Environmental HDR split."""
    import torch

    from core.lights import extract_dominant_light
    from core.sh import project_sh

    hdr, flags = envmap(cf, x, t, SH_ENVMAP_HEIGHT)
    env = torch.from_numpy(hdr)
    light = extract_dominant_light(env)
    return light, project_sh(env.double()), flags


def envmap_sequence(cf: CachedField, x, times, height: int, quality: str = "exact"):
    """Yield (t, hdr, flags) one time at a time (the field lock is taken per frame, so other
    queries interleave with a long sequence)."""
    for t in times:
        hdr, flags, _ = envmap_with_quality(cf, x, t, height, quality)
        yield t, hdr, flags


def cubemap(cf: CachedField, x, t: float, size: int) -> tuple[np.ndarray, EvalFlags]:
    """Faces [6, size, size, 3] (+X, -X, +Y, -Y, +Z, -Z), sampled from a 2*size-high env map (one map pixel per texel at the face centres)."""
    import torch

    from core.cubemap import equirect_to_cubemap

    hdr, flags = envmap(cf, x, t, max(2 * size, 8))
    faces = equirect_to_cubemap(torch.from_numpy(hdr), size)
    return _numpy(faces), flags
