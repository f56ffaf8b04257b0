"""Frame by frame, how the draft field follows `temporal`'s lighting between its switches (issue 12's
static-stretch target), beside its prior.

    python -m bench.temporal_stretches [--seed 0] [--variant NAME:key=value,key=value ...] [-o stretches.json]

The accuracy probe reports per stretch only the largest deviation of pred/truth brightness from
its mean. This prints the whole course: per stretch position and frame, the field's and the
prior's brightness over the truth's (each divided by its mean over the stretch, so 1.0 on every
frame is a perfect follower whatever the scale), for the shipped draft and for each `--variant`
(draft preset overrides, dotted keys, JSON values), distilled with the same seed. The variants
share the seed's draws (frames and probes in the same order), so a shape common to all of them
may come from those draws: compare seeds (`--seed`) before reading it as structure.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

import torch


def stretch_courses(suite, series_preds: list[torch.Tensor]) -> list[dict]:
    """Per stretch of the suite's series: the prediction's relative course, frame by frame."""
    from bench.suite.evaluation import envmap_brightness, relative_course

    out = []
    for s, pred in zip(suite.series, series_preds):
        if s.kind != "stretch":
            continue
        course = [round(float(v), 4) for v in relative_course(envmap_brightness(pred), envmap_brightness(s.gt))]
        out.append({"x": list(s.x), "frames": len(s.times), "course": course,
                    "max_dev": round(max(abs(v - 1.0) for v in course), 4)})
    return out


def parse_variant(text: str) -> tuple[str, dict]:
    from bench.overrides import parse_set

    name, _, sets = text.partition(":")
    return name, parse_set([kv for kv in sets.split(",") if kv])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--variant", action="append", default=[], help="NAME:key=value,key=value (draft overrides)")
    p.add_argument("-o", "--output", default=None)
    args = p.parse_args(argv)
    torch.set_num_threads(1)

    from bench.accuracy_probe import distill_with_seed, probe_method
    from bench.methods import Method, MethodRun, query_field, run_per_probe
    from bench.run import default_cache_dir
    from bench.suite.simulated import load_suite
    from core.engine.presets import preset

    suite = load_suite("temporal", default_cache_dir(), None, 64)
    prior_run = run_per_probe(Method("prior", "per-probe", "baseline", "prior"), suite, preset("draft"))
    report = {"suite": "temporal", "seed": args.seed, "prior (shortcut)": stretch_courses(suite, prior_run.series),
              "variants": {}}
    for name, overrides in [("draft", {})] + [parse_variant(v) for v in args.variant]:
        base = preset("draft").with_overrides(overrides) if overrides else preset("draft")
        with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            method = probe_method("field", base)
            path = distill_with_seed(method, suite, base, Path(tmp) / name, args.seed)
            run = MethodRun(method)
            query_field(run, path, suite)
        report["variants"][name] = {"overrides": overrides, "stretches": stretch_courses(suite, run.series)}
        for s in report["variants"][name]["stretches"]:
            print(f"{name:>16} x={s['x']} max dev {s['max_dev']:.3f}: " + " ".join(f"{v:.3f}" for v in s["course"]),
                  file=sys.stderr, flush=True)
    for s in report["prior (shortcut)"]:
        print(f"{'prior (shortcut)':>16} x={s['x']} max dev {s['max_dev']:.3f}: " + " ".join(f"{v:.3f}" for v in s["course"]),
              file=sys.stderr)
    if args.output:
        Path(args.output).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
