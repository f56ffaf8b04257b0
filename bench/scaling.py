"""How cost grows with the input: distillation time and peak memory vs frames T, frame
resolution and probes per step N (log-log fitted exponents), and query latency vs env-map
height (exact field vs baked lattice).

Each distillation point runs in a FRESH subprocess so its peak memory is clean: the child
reports its own times and its peak RSS (VmHWM of its own address space; ru_maxrss would
include the forking parent's pages), and the parent subtracts the peak of a baseline child
that only imports. The capture is synthetic (smooth seeded colours, the engine's assumed
box-room depth): cost does not depend on what the pixels show.

    python -m bench.scaling --point '{"frames": 4, "height": 72, "probes": 9, "iterations": 10}'
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CENTRE = {"frames": 4, "height": 72, "probes": 4}
QUICK_SWEEPS = {"frames": [1, 8, 64], "height": [36, 72, 144], "probes": [1, 4, 16]}
FULL_SWEEPS = {"frames": [1, 8, 64, 256], "height": [36, 72, 144, 288], "probes": [1, 4, 9, 16, 32]}
UNITS = {"frames": "frames T", "height": "frame rows (ball = 1/4)", "probes": "probes per step N"}
QUERY_HEIGHTS = {"quick": [16, 32, 64, 128], "full": [16, 32, 64, 128, 256, 512]}


def synthetic_capture(frames: int, height: int):
    import torch

    from core.capture.load import capture_from_arrays

    width = height * 4 // 3
    g = torch.Generator().manual_seed(frames * 1000 + height)
    coarse = torch.rand(frames, 3, 6, 8, generator=g)
    images = torch.nn.functional.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)
    return capture_from_arrays(images.permute(0, 2, 3, 1).contiguous(), None, fps=8.0)


def run_point(point: dict) -> dict:
    """Child side: build a synthetic capture and distil on it (iterations == 0: imports only,
    the baseline whose peak RSS is subtracted, so memory includes the capture itself)."""
    import torch

    from core.engine.distill import distill
    from core.engine.presets import preset
    from core.engine.scene import scene_bounds
    from core.priors.registry import build_prior

    if point["iterations"] == 0:
        return {"seconds": 0.0, "cpu_seconds": 0.0}
    capture = synthetic_capture(point["frames"], point["height"])
    cfg = preset("draft").with_overrides({"distill": dict(iterations=point["iterations"], n_probes=point["probes"],
                                                          work_height=point["height"], checkpoint_every=10**6)})
    t0, c0 = time.perf_counter(), time.process_time()
    prior = build_prior("reprojection", cfg.prior_settings("reprojection"))
    prior.bind(capture)
    result = distill(capture, prior, cfg, uses_time=point["frames"] > 1, bounds=scene_bounds(capture))
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    ok = all(math.isfinite(v) for v in result.losses)
    del torch
    return {"seconds": seconds, "cpu_seconds": cpu, "finite_losses": ok}


def peak_rss_mb() -> float | None:
    """This process's peak RSS since exec (VmHWM), None where /proc is unavailable."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0  # kB
    except (OSError, ValueError, IndexError):
        pass
    return None


def measure_point(point: dict) -> dict:
    """Parent side: run one point in a subprocess and read its JSON line."""
    proc = subprocess.run([sys.executable, "-m", "bench.scaling", "--point", json.dumps(point)], cwd=REPO,
                          capture_output=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    if proc.returncode != 0:
        return {"error": proc.stderr.decode(errors="replace")[-400:]}
    return json.loads(proc.stdout.decode().strip().splitlines()[-1])


def loglog_exponent(xs: list[float], ys: list[float]) -> float | None:
    """Least-squares slope of log y vs log x over the positive pairs (None with < 2 pairs)."""
    pairs = [(math.log(x), math.log(y)) for x, y in zip(xs, ys) if x and y and x > 0 and y > 0]
    if len(pairs) < 2:
        return None
    mx = sum(p[0] for p in pairs) / len(pairs)
    my = sum(p[1] for p in pairs) / len(pairs)
    sxx = sum((p[0] - mx) ** 2 for p in pairs)
    return sum((p[0] - mx) * (p[1] - my) for p in pairs) / sxx if sxx > 0 else None


def query_latency(heights: list[int], repeats: int = 3) -> dict:
    """CPU ms of one env-map query: exact (the draft MLP, untrained: same cost) vs baked."""
    import statistics
    import tempfile

    import torch

    from core.engine.presets import preset
    from core.fields import SceneBounds, build_field
    from core.fields.stored.artefact import save_artefact
    from core.fields.stored.bake import bake

    bounds = SceneBounds(lo=(-2.5, -1.5, -4.0), hi=(2.5, 1.5, 0.0), t0=0.0, t1=2.0)
    field = build_field(preset("draft").field.with_kind("mlp"), bounds)
    with tempfile.TemporaryDirectory() as tmp:
        art = save_artefact(Path(tmp) / "a", field, {})
        t0 = time.perf_counter()
        baked = bake(art)
        bake_s = time.perf_counter() - t0
        out = {"heights": heights, "exact_ms": [], "baked_ms": [], "bake_seconds": bake_s, "baked_height": baked.height}
        x, t = torch.tensor([[0.1, 0.2, -1.0]]), [0.5]
        for h in heights:
            for key, fn in (("exact_ms", lambda: art.envmaps(x, t, h)), ("baked_ms", lambda: baked.envmaps(x, t, h))):
                fn()  # warm-up
                times = []
                for _ in range(repeats):
                    s = time.process_time()  # CPU time: robust to other load on a shared machine
                    fn()
                    times.append(1000.0 * (time.process_time() - s))
                out[key].append(statistics.median(times))
    out["exact_exponent"] = loglog_exponent(heights, out["exact_ms"])
    out["baked_exponent"] = loglog_exponent(heights, out["baked_ms"])
    return out


def run_scaling(quick: bool = False, workdir: Path | None = None) -> dict:
    iterations = 10 if quick else 50
    sweeps = QUICK_SWEEPS if quick else FULL_SWEEPS
    baseline = measure_point({**CENTRE, "iterations": 0})
    base_rss = baseline.get("peak_rss_mb") or 0.0
    cache: dict = {}
    out: dict = {
        "note": (
            f"Each point: {iterations} distillation steps of the draft MLP on a synthetic capture, reprojection prior, "
            f"one thread, in a fresh subprocess; other axes held at {CENTRE}. Seconds are CPU seconds (wall in the "
            "JSON) and include "
            "per-job costs (prior set-up, bounds) besides the steps. Memory = child's peak RSS minus a child that "
            "only imports "
            f"({base_rss:.0f} MB), so it includes the capture. Exponent = log-log least-squares slope."
        ),
        "iterations": iterations,
        "centre": CENTRE,
        "baseline_peak_rss_mb": base_rss,
        "sweeps": {},
    }
    for axis, values in sweeps.items():
        secs, cpus, mems, errors = [], [], [], []
        for v in values:
            point = {**CENTRE, axis: v, "iterations": iterations}
            key = json.dumps(point, sort_keys=True)
            if key not in cache:
                print(f"[bench] scaling {axis}={v}", file=sys.stderr, flush=True)
                cache[key] = measure_point(point)
            r = cache[key]
            errors.append(r.get("error"))
            secs.append(r.get("seconds"))
            cpus.append(r.get("cpu_seconds"))
            mems.append(None if r.get("peak_rss_mb") is None else max(0.0, r["peak_rss_mb"] - base_rss))
        out["sweeps"][axis] = {
            "unit": UNITS[axis],
            "values": values,
            "seconds": cpus,
            "wall_seconds": secs,
            "peak_rss_delta_mb": mems,
            "time_exponent": loglog_exponent(values, cpus),
            "wall_time_exponent": loglog_exponent(values, secs),
            "memory_exponent": loglog_exponent(values, mems),
            "errors": [e for e in errors if e],
        }
    q = query_latency(QUERY_HEIGHTS["quick" if quick else "full"])
    out["query_latency"] = q
    out["sweeps"]["query height (exact)"] = {
        "unit": "env map rows",
        "values": q["heights"],
        "seconds": [v / 1000 for v in q["exact_ms"]],
        "peak_rss_delta_mb": [],
        "time_exponent": q["exact_exponent"],
        "memory_exponent": None,
    }
    out["sweeps"]["query height (baked)"] = {
        "unit": "env map rows",
        "values": q["heights"],
        "seconds": [v / 1000 for v in q["baked_ms"]],
        "peak_rss_delta_mb": [],
        "time_exponent": q["baked_exponent"],
        "memory_exponent": None,
    }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--point", required=True, help="JSON: frames, height, probes, iterations")
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    result = run_point(json.loads(args.point))
    result["peak_rss_mb"] = peak_rss_mb()
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
