"""Simulator speed: one 192x144 frame + 9 ground-truth env maps at 64x128 (direct light).

Target (issue 3): under 2 s on a 2-core CPU. Prints one JSON line with the wall time of
the best of `--repeats` runs and the per-effect cost report of that run.

    python bench/sim_speed.py [--suite spatial] [--repeats 3] [--threads 2]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import torch  # noqa: E402

from core.sim.cost import CostReport  # noqa: E402
from core.sim.render import render_envmap, render_frame  # noqa: E402
from core.sim.suites import suite  # noqa: E402

TARGET_SECONDS = 2.0


def probe_grid(scene, count: int = 9) -> list[tuple[float, float, float]]:
    """`count` probe points spread through the first room box (free space only)."""
    from core.sim.render import geometry

    geom = geometry(scene)
    box = scene.room.boxes[0]
    pts = []
    for i in range(64):
        fx, fz = ((i * 0.618034) % 1.0), ((i * 0.381966 + 0.2) % 1.0)
        p = (
            box.lo[0] + 0.2 + fx * (box.hi[0] - box.lo[0] - 0.4),
            1.0 + 0.5 * (i % 3) / 2,
            box.lo[2] + 0.2 + fz * (box.hi[2] - box.lo[2] - 0.4),
        )
        t = torch.tensor([p])
        if bool(geom.inside_room(t)) and not bool(geom.inside_furniture(t)):
            pts.append(p)
        if len(pts) == count:
            break
    return pts


def run_once(scene, probes, height: int) -> tuple[float, float, CostReport]:
    """(wall seconds, process CPU seconds, cost). CPU time shows contention on a busy machine."""
    start, cpu = time.perf_counter(), time.process_time()
    frame = render_frame(scene, 0)
    cost = frame.cost
    for p in probes:
        render_envmap(scene, p, 0.0, height, cost)
    return time.perf_counter() - start, time.process_time() - cpu, cost


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="spatial", help="a direct-light suite (default: spatial)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--height", type=int, default=64)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    scene = suite(args.suite)
    probes = probe_grid(scene)
    run_once(scene.model_copy(update={"resolution": (16, 12)}), probes[:1], 8)  # warm-up
    runs = [run_once(scene, probes, args.height) for _ in range(args.repeats)]
    best, best_cpu, cost = min(runs, key=lambda r: r[0])
    print(json.dumps({
        "bench": "sim_speed",
        "suite": args.suite,
        "effects": sorted(scene.effects),
        "resolution": list(scene.resolution),
        "envmaps": len(probes),
        "envmap_size": [args.height, 2 * args.height],
        "threads": args.threads,
        "seconds_best": round(best, 3),
        "seconds_all": [round(r[0], 3) for r in runs],
        "cpu_seconds_best": round(best_cpu, 3),
        "target_seconds": TARGET_SECONDS,
        "within_target": best < TARGET_SECONDS,
        "cost": cost.as_dict(),
        "load_average": os.getloadavg()[0],
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
