"""Frame by frame, how the draft field follows `temporal`'s lighting between its switches (issue 12's
static-stretch target), beside its prior.

    python -m bench.temporal_stretches [--seed 0] [--variant NAME:key=value,key=value ...] [--room-positions 12]
                                       [-o stretches.json]

The accuracy probe reports per stretch only the largest deviation of pred/truth brightness from
its mean. This prints the whole course: per stretch position and frame, the field's and the
prior's brightness over the truth's (each divided by its mean over the stretch, so 1.0 on every
frame is a perfect follower whatever the scale), for the shipped draft and for each `--variant`
(draft preset overrides, dotted keys, JSON values), distilled with the same seed. The variants
share the seed's draws (frames and probes in the same order), so a shape common to all of them
may come from those draws: compare seeds (`--seed`) before reading it as structure.

Over the room: at `--room-positions` points drawn in the room's free space, each stretch's
brightness at its last time over its first, for the truth, the prior and each variant, and each
one's ratio to the prior's change at the same point (mean and spread over the points): does the
field change over the whole room as its prior does, or only at the two series positions?
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


def room_positions(scene, n: int, seed: int) -> list[tuple[float, float, float]]:
    """n points uniform in the room's free space (the extra held-out probes' box,
    bench.suite.simulated.free_space_box; furniture redrawn)."""
    from bench.suite.simulated import EXTRA_PROBE_TRIES, free_space_box
    from core.sim.render import ProbeError, check_probe

    lo, hi = free_space_box(scene)
    gen = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(n * EXTRA_PROBE_TRIES):
        if len(out) == n:
            break
        x = tuple(round(float(v), 3) for v in lo + (hi - lo) * torch.rand(3, generator=gen, dtype=torch.float64))
        try:
            check_probe(scene, x)
        except ProbeError:
            continue
        out.append(x)
    return out


ROOM_HEIGHT = 32  # rows of the maps whose brightness the room-wide change compares


def stretch_changes(suite, positions, envmaps) -> list[dict]:
    """Per time span of the suite's stretches (series at several positions share spans): at each
    position, the brightness at the span's last time over its first, from `envmaps(x, t) -> [h, 2h, 3]`."""
    from bench.suite.evaluation import envmap_brightness

    spans = sorted({(float(s.times[0]), float(s.times[-1])) for s in suite.series if s.kind == "stretch"})
    out = []
    for t0, t1 in spans:
        ratios = [
            float(
                envmap_brightness(envmaps(x, t1)[None])[0] / envmap_brightness(envmaps(x, t0)[None])[0].clamp_min(1e-30)
            )
            for x in positions
        ]
        out.append({"t": [round(t0, 4), round(t1, 4)], "ratios": [round(r, 4) for r in ratios]})
    return out


def room_summary(changes: list[dict], prior_changes: list[dict]) -> list[dict]:
    """Per stretch: the mean change over the positions and the mean and spread of its ratio to
    the prior's at the same positions (1.0: the estimate changes over the room as its prior)."""
    out = []
    for c, p in zip(changes, prior_changes):
        r = torch.tensor(c["ratios"], dtype=torch.float64)
        rel = r / torch.tensor(p["ratios"], dtype=torch.float64)
        out.append({"t": c["t"], "mean_change": round(float(r.mean()), 4),
                    "over_prior_mean": round(float(rel.mean()), 4), "over_prior_sd": round(float(rel.std()), 4)})
    return out


def parse_variant(text: str) -> tuple[str, dict]:
    from bench.overrides import parse_set

    name, _, sets = text.partition(":")
    return name, parse_set([kv for kv in sets.split(",") if kv])


def main(argv=None) -> int:
    from core.sim.camera_curves import add_curve_argument

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--variant", action="append", default=[], help="NAME:key=value,key=value (draft overrides)")
    p.add_argument(
        "--room-positions",
        type=int,
        default=12,
        help="also compare each stretch's end-to-start brightness change at this many room positions (0: off)",
    )
    p.add_argument("-o", "--output", default=None)
    add_curve_argument(p, allow_all=False)  # the suite's camera curve: drawn by its name, or forced
    args = p.parse_args(argv)
    torch.set_num_threads(1)

    from bench.accuracy_probe import distill_with_seed, probe_method
    from bench.methods import Method, MethodRun, query_field, run_per_probe
    from bench.run import default_cache_dir
    from bench.suite.simulated import load_suite
    from core.engine.presets import preset

    suite = load_suite("temporal", default_cache_dir(), None, 64, args.curve)
    prior_run = run_per_probe(Method("prior", "per-probe", "baseline", "prior"), suite, preset("draft"))
    report = {"suite": "temporal", "curve": suite.describe()["camera_curve"], "seed": args.seed,
              "prior (shortcut)": stretch_courses(suite, prior_run.series), "variants": {}}
    positions = room_positions(suite.scene, args.room_positions, seed=5)
    if positions:
        from bench.methods import _bound_prior
        from core.sim.render import render_envmap

        prior = _bound_prior(suite, preset("draft"))
        truth_changes = stretch_changes(
            suite, positions, lambda x, t: render_envmap(suite.scene, x, t, ROOM_HEIGHT).float()
        )
        prior_changes = stretch_changes(
            suite, positions, lambda x, t: prior.envmaps(torch.tensor([x]), t, ROOM_HEIGHT)[0]
        )
        report["room"] = {"positions": positions, "truth": room_summary(truth_changes, prior_changes),
                          "prior (shortcut)": room_summary(prior_changes, prior_changes)}
    for name, overrides in [("draft", {})] + [parse_variant(v) for v in args.variant]:
        base = preset("draft").with_overrides(overrides) if overrides else preset("draft")
        with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            method = probe_method("field", base)
            path = distill_with_seed(method, suite, base, Path(tmp) / name, args.seed)
            run = MethodRun(method)
            query_field(run, path, suite)
            room = None
            if positions:
                from core.fields.stored.artefact import LightFieldArtefact

                art = LightFieldArtefact.load(path)
                changes = stretch_changes(
                    suite, positions, lambda x, t: art.envmaps(torch.tensor([x]), [t], ROOM_HEIGHT)[0][0]
                )
                room = room_summary(changes, prior_changes)
        report["variants"][name] = {
            "overrides": overrides,
            "stretches": stretch_courses(suite, run.series),
            "room": room,
        }
        for s in room or []:
            print(f"{name:>16} t={s['t']} over the room: change {s['mean_change']:.3f}, over the prior's "
                  f"{s['over_prior_mean']:.3f} +- {s['over_prior_sd']:.3f}", file=sys.stderr, flush=True)
        for s in report["variants"][name]["stretches"]:
            print(f"{name:>16} x={s['x']} max dev {s['max_dev']:.3f}: " + " ".join(f"{v:.3f}" for v in s["course"]),
                  file=sys.stderr, flush=True)
    for s in report.get("room", {}).get("truth", []):
        print(f"{'truth':>16} t={s['t']} over the room: change {s['mean_change']:.3f}, over the prior's "
              f"{s['over_prior_mean']:.3f} +- {s['over_prior_sd']:.3f}", file=sys.stderr)
    for s in report["prior (shortcut)"]:
        print(
            f"{'prior (shortcut)':>16} x={s['x']} max dev {s['max_dev']:.3f}: "
            + " ".join(f"{v:.3f}" for v in s["course"]),
            file=sys.stderr,
        )
    if args.output:
        Path(args.output).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
