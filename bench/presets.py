"""Wall time of the CPU presets on simulator captures of the sizes the presets promise.

    python -m bench.presets [--presets draft,standard] [--unique-frames 5] [--temporal auto|on|off]
        [--set field.view_detail_time_rank=0 ...] [-o results.json]

draft: a 20-frame 192x144 clip; standard: a 100-frame 320x240 clip (the `temporal` suite,
so the time input is on). Rendering 100 distinct simulator frames costs more than the
estimate itself, so the clip holds `--unique-frames` rendered frames, each repeated
(a held shot): distillation cost depends on the frame SIZE and the step count, not on how
many distinct frames exist (each step uses one frame), while loading and temporal detection
still see the full T frames. The JSON records this. `--temporal on` forces the time input (the
cost of a job whose lighting changes; the draft clip's dimming lamp is read as static under
`auto`) and `--set` overrides the preset (dotted keys, JSON values). No timing assertions live
in tests.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

from bench.overrides import knobs_of, parse_set

SIZES = {"draft": (20, 192, 144), "standard": (100, 320, 240)}


def make_clip(out: Path, frames: int, width: int, height: int, unique: int) -> dict:
    """Simulate the first `unique` frames of the temporal suite (its lamp dims over them) and
    repeat each to make `frames` frames at the suite's fps."""
    import numpy as np

    from core.io.depth import write_depth_npz
    from core.sim.capture import write_capture
    from core.sim.suites import temporal

    unique = max(1, min(unique, frames))
    spec = temporal().model_copy(update={"frames": unique, "resolution": (width, height), "probes": []})
    t0 = time.perf_counter()
    doc = write_capture(spec, out, envmap_height=16, video=False)
    sim_s = time.perf_counter() - t0
    rep = [i * unique // frames for i in range(frames)]
    depth = np.load(out / doc["depth"])["depth"]
    write_depth_npz(out / doc["depth"], depth[rep])
    doc.update(frames=[doc["frames"][i] for i in rep], poses=[doc["poses"][i] for i in rep], frame_count=frames,
               hdr_frames=[doc["hdr_frames"][i] for i in rep], video=None)
    doc.pop("cost", None)
    (out / "capture.json").write_text(json.dumps(doc))
    return {"simulate_s": round(sim_s, 2), "unique_frames": unique}


def bench_preset(name: str, unique: int, workdir: Path, temporal: str = "auto", overrides: dict | None = None) -> dict:
    from core.engine import run_job
    from core.engine.params import JobParams
    from core.engine.presets import preset

    frames, w, h = SIZES[name]
    clip = workdir / f"{name}-clip"
    info = make_clip(clip, frames, w, h, unique)
    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        config = preset(name).with_overrides(overrides) if overrides else preset(name)
        with knobs_of(config):
            result = run_job(clip, None, JobParams(preset=name, temporal=temporal), workdir / f"{name}-out",
                             config=config)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    meta = result.artefact.meta
    tr = meta["training"]
    return {
        "preset": name,
        "frames": frames,
        "width": w,
        "height": h,
        **info,
        "temporal": temporal,
        "overrides": overrides or {},
        # cpu_s ~ wall time on an idle machine: distillation runs one intra-op thread
        "wall_s": round(wall, 2),
        "cpu_s": round(cpu, 2),
        "iterations": tr["iterations"],
        "ms_per_step": round(
            1000 * tr["stage_timings"]["optimisation"]["seconds"] / tr["iterations"]
            + 1000
            * sum(tr["stage_timings"][k]["seconds"] for k in ("prior", "field_render", "probe_geometry"))
            / tr["iterations"],
            1,
        ),
        "uses_time": meta["temporal"]["uses_time"],
        "final_loss": tr["final_loss"],
        "stage_timings": tr["stage_timings"],
        "cpu_count": os.cpu_count(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--presets", default="draft,standard")
    p.add_argument("--unique-frames", type=int, default=5)
    p.add_argument("--temporal", choices=("auto", "on", "off"), default="auto", help="the job's temporal parameter")
    p.add_argument("--set", action="append", default=[], help="preset override key=value (JSON value)")
    p.add_argument("-o", "--output", default=None, help="also write the JSON here")
    args = p.parse_args(argv)
    overrides = parse_set(args.set)
    results = []
    with tempfile.TemporaryDirectory(prefix="lf-bench-") as tmp:
        for name in [s.strip() for s in args.presets.split(",") if s.strip()]:
            if name not in SIZES:
                print(f"error: no benchmark size for preset {name!r} (have {sorted(SIZES)})", file=sys.stderr)
                return 2
            results.append(bench_preset(name, args.unique_frames, Path(tmp), args.temporal, overrides))
            print(json.dumps(results[-1]), file=sys.stderr)
    from bench.suite.measure import machine_info

    text = json.dumps({"presets": results, "machine": machine_info()}, indent=2)  # seconds are the host's too
    if args.output:
        Path(args.output).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
