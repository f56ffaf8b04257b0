"""Evaluating a cached light field for the HTTP layer.

Validation of the query values lives here too, so every endpoint refuses the same things
with the same codes: x must be three finite numbers within +-MAX_ABS_X_M, t finite within
+-MAX_ABS_T_S, sizes within the limits. Evaluation goes through the field's FieldBatcher
(service.evaluator): `envmap_answer` queues one map and awaits it.

Quality (docs/api.md, "Query speed", gives the cost and the error of each):
* `exact` evaluates the field at every pixel of the requested map;
* `fast` (the default) evaluates the field exactly at the query's (x, t), at a quarter of the
  requested rows (at least FAST_MIN_ROWS), and upsamples bilinearly: 1/16 of the pixels, the
  angular detail of a 4x smaller map, no error in position or time;
* `baked` interpolates the lattice of env maps the worker baked (core.fields.stored.bake) in x and t:
  the cheapest, but between lattice nodes it is wrong wherever the light changes quickly
  with position (near lamps), so it is never the default.
"""
from __future__ import annotations

import math
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from core.cubemap import equirect_to_cubemap
from core.envmap import upsample_envmaps
from core.lights import extract_dominant_light
from core.sh import project_sh
from service.errors import InvalidInput, PayloadTooLarge
from service.evaluator import EnvmapAnswer, EnvmapRequest, FieldBatcher, group_requests
from service.fieldcache import CachedField
from service.query_rules import MAX_ABS_EV, MAX_ABS_T_S, MAX_ABS_X_M

DEFAULT_QUALITY = "fast"
FAST_MIN_ROWS, FAST_DIVISOR = 16, 4


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
    if len(values) != 3 or not all(math.isfinite(v) and abs(v) <= MAX_ABS_X_M for v in values):
        raise InvalidInput(f"x must be three finite numbers 'X,Y,Z' in metres within +-{MAX_ABS_X_M:g}, "
                           f"got {text[:80]!r}", code="invalid_x")
    return values  # type: ignore[return-value]


def check_t(t: float) -> float:
    if not (math.isfinite(t) and abs(t) <= MAX_ABS_T_S):
        raise InvalidInput(f"t must be a finite number of seconds within +-{MAX_ABS_T_S:g}, got {t}", code="invalid_t")
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
    from core.fields.stored.artefact import QueryError  # noqa: PLC0415 — core.fields.stored.artefact pulls in safetensors: imported when used

    try:
        yield
    except QueryError as exc:
        raise InvalidInput(str(exc), code="invalid_query") from None


def fast_rows(height: int) -> int:
    """Rows at which quality=fast evaluates the field for a `height`-row answer."""
    return min(height, max(FAST_MIN_ROWS, height // FAST_DIVISOR))


def _evaluate(cf: CachedField, quality: str, xs, ts, height: int):
    """(maps [P, height, 2 height, 3], flags) in the given quality. Call with cf.lock held."""
    if quality == "baked":
        return _baked(cf).envmaps(xs, ts, height)
    if quality == "fast":
        low, flags = cf.artefact.envmaps(xs, ts, fast_rows(height))
        return upsample_envmaps(low, height), flags
    return cf.artefact.envmaps(xs, ts, height)


def _baked(cf: CachedField):
    """The worker's bake (verified; a missing, stale or corrupt one is baked again here once
    and saved beside the artefact, atomically). Call with cf.lock held."""
    from core.fields.stored.bake import load_or_bake  # noqa: PLC0415 — core.fields.stored.bake pulls in safetensors: imported when used

    if cf.baked is None:
        cf.baked = load_or_bake(cf.artefact, save=True)
    return cf.baked


def evaluate_requests(cf: CachedField, requests: list[EnvmapRequest]) -> list[EnvmapAnswer]:
    """One field call per (quality, height) group, then each request's `finish` (blocking)."""
    answers: list[EnvmapAnswer | None] = [None] * len(requests)
    for (quality, height), indices in group_requests(requests).items():
        xs = [requests[i].x for i in indices]
        ts = [requests[i].t for i in indices]
        with _as_invalid_input(), cf.lock:
            hdrs, flags = _evaluate(cf, quality, xs, ts, height)
        hdrs = _numpy(hdrs)
        for k, i in enumerate(indices):
            finish, flag = requests[i].finish, _flags(flags[k])
            answers[i] = EnvmapAnswer(finish(hdrs[k], flag) if finish else hdrs[k], flag, quality)
    return answers  # type: ignore[return-value]


def batcher(cf: CachedField, max_pending_pixels: int, on_batch=None) -> FieldBatcher:
    """The field's batcher (created on first use, on the event loop)."""
    if cf.batcher is None:
        cf.batcher = FieldBatcher(lambda requests: evaluate_requests(cf, requests), max_pending_pixels, on_batch)
    return cf.batcher


async def envmap_answer(ctx, cf: CachedField, x, t: float, height: int, quality: str,
                        finish: Callable[[np.ndarray, EvalFlags], Any] | None = None) -> EnvmapAnswer:
    """Queue one env map on the field's batcher and await it (value = finish(hdr, flags) or hdr).
    `ctx` (service.context.AppContext) gives the queue bound and the metrics."""
    request = EnvmapRequest(tuple(float(v) for v in x), float(t), int(height), quality, finish)
    on_batch = ctx.metrics.observe_batch if ctx.metrics is not None else None
    return await batcher(cf, ctx.settings.limits.max_pending_pixels, on_batch).submit(request)


def sh_from_envmap(hdr: np.ndarray):
    """(dominant light with ambient SH, SH of the whole map) of an env map: ARCore Environmental HDR split."""
    env = torch.from_numpy(hdr)
    return extract_dominant_light(env), project_sh(env.double())


# -- one map at a time, in the caller's thread (exports: ktx2, glTF, USD, EXR sequences, large maps) --
# A query costing more than this many field evaluations (an exact map above 362 rows) is an
# export: evaluated on the exports' copy of the field, cancellable, never through the batcher.
LARGE_COST = 1 << 17


def is_large(height: int, quality: str) -> bool:
    return EnvmapRequest((0.0, 0.0, 0.0), 0.0, int(height), quality).cost > LARGE_COST


def envmap(cf: CachedField, x, t: float, height: int) -> tuple[np.ndarray, EvalFlags]:
    hdr, flags, _ = envmap_with_quality(cf, x, t, height, "exact")
    return hdr, flags


def envmap_with_quality(cf: CachedField, x, t: float, height: int, quality: str, on_map=None):
    """(hdr, flags, quality used) of one map, on the exports' copy of the field (service.exports:
    the small queries' batches never wait for it). t=None: a field that does not vary in time."""
    times = None if t is None else [t]
    if quality == "baked":  # interpolation of the shared bake: cheap, under the batcher's lock
        with _as_invalid_input(), cf.lock:
            hdrs, flags = _evaluate(cf, quality, [list(x)], times, height)
    else:
        with _as_invalid_input(), cf.export_lock:
            artefact = cf.export_artefact()
            if quality == "fast":
                low, flags = artefact.envmaps([list(x)], times, fast_rows(height))
                hdrs = upsample_envmaps(low, height)
            else:
                hdrs, flags = artefact.envmaps([list(x)], times, height)
    if on_map is not None:
        on_map(quality)
    return _numpy(hdrs[0]), _flags(flags[0]), quality


def envmap_sequence(cf: CachedField, x, times, height: int, quality: str = "exact", cancellation=None, on_map=None):
    """Yield (t, hdr, flags) one time at a time, each frame inside `cancellation.running()`
    (service.exports) when given."""
    for t in times:
        with cancellation.running() if cancellation is not None else nullcontext():
            hdr, flags, _ = envmap_with_quality(cf, x, t, height, quality, on_map)
        yield t, hdr, flags


def cube_faces(hdr: np.ndarray, size: int) -> np.ndarray:
    """Faces [6, size, size, 3] (+X, -X, +Y, -Y, +Z, -Z) sampled from an env map of 2*size rows
    (one map pixel per texel at the face centres)."""
    return _numpy(equirect_to_cubemap(torch.from_numpy(hdr), size))


def cubemap_height(size: int) -> int:
    return max(2 * size, 8)
