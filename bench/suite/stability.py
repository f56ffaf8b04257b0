"""Numerically hard inputs run end to end (`run_job` -> artefact -> queries).

A case FAILS if the job raises, or any queried radiance is non-finite or negative, or (long
video) the peak RSS increase exceeds LONG_VIDEO_MEMORY_LIMIT_MB. Queries include points
outside the box and times outside the clip, which the artefact must answer (flagged).
"""
from __future__ import annotations

import sys
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from bench.suite.measure import measured

QUERY_HEIGHT = 16
LONG_VIDEO_MEMORY_LIMIT_MB = 2048.0
SIZE = (96, 72)  # width, height of the synthetic inputs


@dataclass(frozen=True)
class Case:
    name: str
    description: str
    make: Callable[[Path, bool], tuple[Path, Path | None]]  # (dir, quick) -> (input, depth or None)
    memory_limit_mb: float | None = None


def _gradient(frames: int = 1) -> np.ndarray:
    w, h = SIZE
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    base = np.stack([x / w, y / h, 0.5 * np.ones_like(x)], -1)
    return np.repeat(base[None], frames, 0)


def _extreme_range(d: Path, quick: bool):
    """HDR scene spanning 1e-6..1e6 tone mapped at ev 0: near-black walls, clipped bulb."""
    import torch

    from core.conventions import tonemap
    from core.io.images import write_png

    w, h = SIZE
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    hdr = 10.0 ** (-6.0 + 12.0 * (x / (w - 1)))[..., None] * np.ones(3, np.float32)
    hdr[h // 3 : h // 3 + 3, w // 2 : w // 2 + 3] = 1e6
    write_png(d / "extreme.png", tonemap(torch.from_numpy(hdr)).numpy())
    return d / "extreme.png", None


def _dark(d: Path, quick: bool):
    from core.io.images import write_png

    write_png(d / "dark.png", np.zeros((SIZE[1], SIZE[0], 3), np.float32))
    return d / "dark.png", None


def _saturated(d: Path, quick: bool):
    from core.io.images import write_png

    write_png(d / "white.png", np.ones((SIZE[1], SIZE[0], 3), np.float32))
    return d / "white.png", None


def _single_frame(d: Path, quick: bool):
    from core.io.images import write_png

    write_png(d / "single.png", _gradient()[0])
    return d / "single.png", None


def _bad_depth(d: Path, quick: bool):
    """One frame with a depth map full of NaN, inf, zeros and negatives (a third valid)."""
    from core.io.images import write_png

    write_png(d / "frame.png", _gradient()[0])
    depth = np.full((SIZE[1], SIZE[0]), np.nan, np.float32)
    depth[:, : SIZE[0] // 3] = 2.5
    depth[::2, SIZE[0] // 3 :] = np.inf
    depth[1::4, SIZE[0] // 3 :] = 0.0
    depth[3::4, SIZE[0] // 3 :] = -1.0
    np.save(d / "depth.npy", depth)
    return d / "frame.png", d / "depth.npy"


def _switch_video(d: Path, quick: bool):
    """Short video whose light switches off half way (time input, big temporal step)."""
    from core.io.video import write_video

    frames = _gradient(12)
    frames[6:] *= 0.05
    write_video(d / "switch.mp4", frames, 8.0)
    return d / "switch.mp4", None


def _long_video(d: Path, quick: bool):
    """A long video (more frames than the default decode limit): memory must stay bounded."""
    from core.io.video import write_video

    n = 400 if quick else 1200
    t = np.linspace(0, 1, n, dtype=np.float32)[:, None, None, None]
    frames = np.clip(_gradient(n) * (0.6 + 0.4 * np.sin(6.28 * t)), 0, 1)
    write_video(d / "long.mp4", frames, 30.0)
    return d / "long.mp4", None


CASES = [
    Case("extreme-dynamic-range", "radiance 1e-6..1e6 at ev 0: black walls, clipped bulb", _extreme_range),
    Case("darkness", "an all-black frame", _dark),
    Case("saturation", "an all-white (clipped) frame", _saturated),
    Case("bad-depth", "depth with NaN, inf, zero and negative values", _bad_depth),
    Case("single-frame", "one ordinary image: no time axis, default intrinsics and assumed depth", _single_frame),
    Case("light-switch-video", "12-frame video, light drops 20x half way", _switch_video),
    Case("long-video", "video longer than the decode limit", _long_video, memory_limit_mb=LONG_VIDEO_MEMORY_LIMIT_MB),
]


def _queries(art) -> tuple[list, list]:
    b = art.bounds
    centre = [(lo + hi) / 2 for lo, hi in zip(b.lo, b.hi)]
    outside = [hi + 10.0 for hi in b.hi]
    xs = [centre, list(b.lo), outside]
    ts = [b.t0, b.t1, b.t1 + 100.0]
    return xs, ts


def run_case(case: Case, workdir: Path, iterations: int) -> dict:
    import torch

    from core.engine import run_job
    from core.engine.params import JobParams
    from core.engine.presets import preset

    d = workdir / f"stability-{case.name}"
    d.mkdir(parents=True, exist_ok=True)
    out = {"name": case.name, "description": case.description, "passed": False}
    try:
        inp, depth = case.make(d, quick=iterations < 50)
        with measured() as m, warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            art = run_job(inp, depth, JobParams(preset="draft"), d / "artefact",
                          config=preset("draft").with_overrides({"distill.iterations": iterations})).artefact
            xs, ts = _queries(art)
            hdr, flags = art.envmaps(
                torch.tensor(xs, dtype=torch.float32), torch.tensor(ts, dtype=torch.float32), QUERY_HEIGHT
            )
        out.update(
            {
                "seconds": round(m.seconds, 2),
                "cpu_seconds": round(m.cpu_seconds, 2),
                "peak_rss_delta_mb": round(m.peak_rss_delta_mb, 1),
            }
        )
        finite = bool(torch.isfinite(hdr).all())
        nonneg = bool((hdr >= 0).all()) if finite else False
        lo, hi = (float(hdr.min()), float(hdr.max())) if finite else (None, None)
        out["output_range"] = "non-finite" if not finite else f"{lo:.2e}..{hi:.2e}"
        out["uses_time"] = art.uses_time
        out["warnings"] = sorted({str(w.message)[:200] for w in caught})
        out["frames_used"] = art.meta.get("capture", {}).get("frames")
        out["extrapolation_flags"] = flags
        problems = []
        if not finite:
            problems.append("non-finite radiance")
        elif not nonneg:
            problems.append("negative radiance")
        if case.memory_limit_mb is not None and m.peak_rss_delta_mb > case.memory_limit_mb:
            problems.append(f"peak RSS +{m.peak_rss_delta_mb:.0f} MB > {case.memory_limit_mb:.0f} MB")
        if not flags[2]["extrapolated_x"]:
            problems.append("a query 10 m outside the box was not flagged")
        out["passed"] = not problems
        out["detail"] = "; ".join(problems) or f"{out['frames_used']} frames used, uses_time={art.uses_time}"
    except Exception as exc:  # noqa: BLE001 - a crash is a failed case, reported with its message
        out["detail"] = f"{type(exc).__name__}: {exc}"[:300]
        out["traceback"] = traceback.format_exc()[-2000:]
    print(
        f"[bench] stability {case.name}: {'PASS' if out['passed'] else 'FAIL'} {out.get('detail', '')}",
        file=sys.stderr,
        flush=True,
    )
    return out


def run_stability(quick: bool = False, workdir: Path | None = None) -> dict:
    import tempfile

    iterations = 10 if quick else 100
    workdir = Path(workdir or tempfile.mkdtemp(prefix="lightfield-stability-"))
    cases = [run_case(c, workdir, iterations) for c in CASES]
    return {
        "note": (
            f"run_job (draft preset, {iterations} steps, reprojection prior) -> artefact -> env maps at the box "
            "centre, "
            f"a corner and 10 m outside, at t0, t1 and t1 + 100 s. FAIL = exception, non-finite or negative radiance, "
            f"unflagged extrapolation, or (long video) peak RSS increase > {LONG_VIDEO_MEMORY_LIMIT_MB:.0f} MB. "
            "The simulated `hard` suite (dark room, 1e4x lamp, saturated windows, compressed noisy video) runs end to "
            "end "
            "in the simulated section; non-finite predictions there are counted per method."
        ),
        "cases": cases,
        "failures": sum(not c["passed"] for c in cases),
    }
