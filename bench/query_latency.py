"""Env-map query latency per field kind (exact and baked) and the accuracy cost of baking.

Each field kind (paper MLP, 3x3x3 env-map grid, trunk+head) is first fitted by plain
regression (log space, Adam) to an analytic room lighting (a small bright ceiling lamp,
a window lobe, a sky/floor gradient that darkens towards the back wall), so the fields
have realistic structure: a sharp light whose direction changes with position. The fitted
field is saved and loaded as an artefact, then:

* exact: p50 / p99 latency of `LightFieldArtefact.envmap` at 64x128 and 128x256;
* baked: time and size of `bake(...)`, p50 / p99 latency of `BakedField.envmap`;
* baking accuracy: baked vs exact env maps at random in-box probes and times, at the
  baked height: median and p99 per-texel relative error, relative si-RMSE (si-RMSE /
  RMS of the exact map), and relative error of the total incident power (integral of L dw);
* fit quality (for context): log-radiance RMSE of the fitted field vs the analytic one.

Prints one JSON document.

    python bench/query_latency.py [--quick] [--threads 2] [--fit-steps 400]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import torch  # noqa: E402

from core.envmap import integrate  # noqa: E402
from core.fields import FieldConfig, SceneBounds, build_field  # noqa: E402
from core.fields.stored.artefact import LightFieldArtefact, save_artefact  # noqa: E402
from core.fields.stored.bake import bake  # noqa: E402
from core.metrics import si_rmse  # noqa: E402

ROOM = SceneBounds((-2.0, 0.0, -4.0), (2.0, 2.5, 0.0), t0=0.0, t1=4.0)
LAMP = torch.tensor([0.5, 2.3, -2.0])
LAMP_RADIUS = 0.12
LAMP_RADIANCE = 2000.0
WINDOW_DIR = torch.nn.functional.normalize(torch.tensor([1.0, 0.3, 0.2]), dim=0)
HEIGHTS = (64, 128)


def analytic_radiance(x: torch.Tensor, t: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """[B,3] radiance of the analytic room; the lamp dims to 30 % over the 4 s capture."""
    to_lamp = LAMP - x
    dist = to_lamp.norm(dim=-1).clamp_min(LAMP_RADIUS * 1.5)
    cos_lamp = (d * to_lamp).sum(-1) / dist
    cos_edge = torch.cos(torch.atan(LAMP_RADIUS / dist))
    sharp = 400.0  # soft edge of the lamp disc
    lamp = torch.sigmoid(sharp * (cos_lamp - cos_edge)) * LAMP_RADIANCE * (1.0 - 0.7 * t / 4.0)
    window = 30.0 * torch.exp(12.0 * ((d * WINDOW_DIR).sum(-1) - 1.0)) * (0.5 + 0.5 * (x[:, 0] + 2.0) / 4.0)
    ambient = 0.4 + 0.3 * d[:, 1] + 0.15 * (x[:, 2] + 4.0) / 4.0
    grey = lamp + window + ambient.clamp_min(0.02)
    return grey[:, None] * torch.tensor([1.0, 0.9, 0.75])


def random_queries(n: int, g: torch.Generator):
    lo, hi = torch.tensor(ROOM.lo), torch.tensor(ROOM.hi)
    x = lo + (hi - lo) * torch.rand(n, 3, generator=g)
    t = torch.rand(n, generator=g) * ROOM.t1
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return x, t, d


def fit(kind: str, steps: int, batch: int, seed: int = 0):
    """Log-space regression of a fresh field onto the analytic room; returns (field, stats)."""
    torch.manual_seed(seed)
    g = torch.Generator().manual_seed(seed)
    field = build_field(FieldConfig(kind=kind, uses_time=True), ROOM)
    lr = 0.05 if kind == "grid" else 2e-3
    opt = torch.optim.Adam(field.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    t0 = time.perf_counter()
    for _ in range(steps):
        x, t, d = random_queries(batch, g)
        loss = (field(x, t, d).log() - analytic_radiance(x, t, d).log()).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    fit_s = time.perf_counter() - t0
    x, t, d = random_queries(20000, torch.Generator().manual_seed(1234))
    with torch.no_grad():
        rmse = (field(x, t, d).log() - analytic_radiance(x, t, d).log()).pow(2).mean().sqrt().item()
    return field, {"fit_steps": steps, "fit_seconds": round(fit_s, 2), "log_rmse_vs_analytic": round(rmse, 4)}


def percentiles(samples_s: list[float]) -> dict:
    ms = sorted(1000.0 * s for s in samples_s)
    p99 = ms[min(len(ms) - 1, math.ceil(0.99 * len(ms)) - 1)]
    return {"p50_ms": round(statistics.median(ms), 2), "p99_ms": round(p99, 2), "n": len(ms)}


def time_queries(query, probes: list, reps: int) -> dict:
    query(*probes[0])  # warm-up (allocator, lazy init)
    samples = []
    for i in range(reps):
        t0 = time.perf_counter()
        query(*probes[i % len(probes)])
        samples.append(time.perf_counter() - t0)
    return percentiles(samples)


def baking_accuracy(art: LightFieldArtefact, baked, height: int, n: int) -> dict:
    g = torch.Generator().manual_seed(7)
    xs, ts, _ = random_queries(n, g)
    exact, _ = art.envmaps(xs, ts, height)
    fast, _ = baked.envmaps(xs, ts, height)
    rel = ((fast - exact).abs() / exact).flatten()
    si = [si_rmse(f, e) / e.pow(2).sum(-1).mean().sqrt().item() for f, e in zip(fast, exact)]
    power = [((integrate(f) - integrate(e)).abs() / integrate(e)).mean().item() for f, e in zip(fast, exact)]
    return {
        "height": height,
        "probes": n,
        "rel_error_median": round(rel.median().item(), 4),
        "rel_error_p99": round(rel.quantile(0.99).item(), 4),
        "si_rmse_relative_mean": round(statistics.mean(si), 4),
        "power_rel_error_mean": round(statistics.mean(power), 4),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer fit steps and repetitions")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--fit-steps", type=int, default=None)
    ap.add_argument("--kinds", default="mlp,grid,trunk")
    ap.add_argument("--bake-grid", default="5,5,5")
    ap.add_argument("--bake-times", type=int, default=4)
    ap.add_argument("--bake-height", type=int, default=64)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    steps = args.fit_steps or (100 if args.quick else 400)
    reps = {64: 10 if args.quick else 40, 128: 5 if args.quick else 20}
    grid = tuple(int(v) for v in args.bake_grid.split(","))
    g = torch.Generator().manual_seed(99)
    probes = [(x.tolist(), float(t)) for x, t in zip(*random_queries(16, g)[:2])]

    report = {"threads": args.threads, "torch": torch.__version__, "room": ROOM.to_dict(), "kinds": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for kind in args.kinds.split(","):
            field, stats = fit(kind, steps, batch=2048)
            art = save_artefact(Path(tmp) / kind, field, {})
            entry = {**stats, "parameters": sum(p.numel() for p in field.parameters()), "exact": {}, "baked": {}}
            for h in HEIGHTS:
                entry["exact"][f"{h}x{2 * h}"] = time_queries(lambda x, t, h=h: art.envmap(x, t, h), probes, reps[h])
            t0 = time.perf_counter()
            baked = bake(art, grid=grid, times=args.bake_times, height=args.bake_height)
            entry["baked"]["spec"] = {"grid": list(grid), "times": args.bake_times, "height": args.bake_height}
            entry["baked"]["bake_seconds"] = round(time.perf_counter() - t0, 2)
            entry["baked"]["bytes"] = baked.maps.numel() * 4
            for h in HEIGHTS:
                entry["baked"][f"{h}x{2 * h}"] = time_queries(lambda x, t, h=h: baked.envmap(x, t, h), probes, reps[h])
            entry["baked"]["accuracy_vs_exact"] = baking_accuracy(art, baked, args.bake_height, 8 if args.quick else 24)
            report["kinds"][kind] = entry
            print(f"{kind}: done", file=sys.stderr)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
