"""How much the prior's answer at a held-out probe depends on which frame it is asked from.

    python -m bench.prior_frames [--suites hard,moving-camera] [--extra-probes 8] [--probe-seed 0]
        [--field-json bench/results/accuracy_probe.json] [-o frames.json]

bench/accuracy_probe.py compares the field with the prior queried directly at each probe's
time, i.e. from the one frame nearest to it. With static lighting the field is one answer for
the whole clip, distilled from every frame's prior, so on a moving camera it is compared with
the prior's answer from one viewpoint, which may be its best or its worst. For each suite this
asks the job's prior (bench.methods._bound_prior, the per-probe baseline of the accuracy probe)
at every probe from every frame and reports, per probe and as means over the probes, the
three-sphere metrics of
* `own_frame`   the frame nearest the probe's time (what the accuracy probe's `prior` row scores);
* `best_frame` / `worst_frame`  per metric, the frame with the lowest / highest error;
* `mean_of_frames`  the mean of the env maps over all frames (a static clip's average answer,
  what a time-invariant field fitted to the prior tends towards);
and, with `--field-json` (an accuracy probe report with the same probes), the field's scores.
A SHORTCUT measurement: it explains the field/prior ratio, it is not what users get.
"""
from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import torch

MATERIALS = ("diffuse", "matte", "mirror")
METRICS = ("si_rmse", "angular_deg")


def frame_scores(prior, suite, probe_index: int, sphere_size: int) -> dict:
    """Per-probe scores of the prior from each frame, its own frame and the mean map."""
    from core.metrics import three_sphere_metrics

    capture = prior._capture
    probe = suite.probes[probe_index]
    x = torch.tensor([probe.x], dtype=torch.float32)
    maps = torch.stack([prior.envmaps(x, float(t), suite.eval_height)[0] for t in capture.times])
    gt = suite.gt[probe_index]
    per_frame = [three_sphere_metrics(m, gt, sphere_size) for m in maps]
    own = prior.frame_at(float(probe.t))
    out = {"x": list(probe.x), "t": probe.t, "own_frame": per_frame[own],
           "mean_of_frames": three_sphere_metrics(maps.mean(0), gt, sphere_size), "best_frame": {}, "worst_frame": {},
           "per_frame": {f"{mat}.{m}": [round(s[mat][m], 4) for s in per_frame] for mat in MATERIALS for m in METRICS}}
    for mat in MATERIALS:
        out["best_frame"][mat] = {m: min(s[mat][m] for s in per_frame) for m in METRICS}
        out["worst_frame"][mat] = {m: max(s[mat][m] for s in per_frame) for m in METRICS}
    return out


def field_from_report(field_report: dict | None, suite_name: str, probe_xs: list, source: str,
                      metrics: tuple[str, ...] = METRICS) -> dict | None:
    """The field's mean scores on `suite_name` from an accuracy probe report (None when the report
    lacks the suite); exits when its probes are not these (other --extra-probes / --probe-seed)."""
    fs = (field_report or {}).get("suites", {}).get(suite_name)
    if fs is None:
        return None
    if [list(q["x"]) for q in fs["probes"]] != [list(x) for x in probe_xs]:
        raise SystemExit(
            f"{source}: the probes of {suite_name} differ from these (same --extra-probes / --probe-seed?)"
        )
    return {mat: {m: fs["scores"]["field"][mat][m] for m in metrics} for mat in MATERIALS}


def write_report(report: dict, output: str | None) -> None:
    if output:
        Path(output).write_text(json.dumps(report, indent=1))


def mean_over(probes: list[dict], key: str) -> dict:
    return {mat: {m: sum(p[key][mat][m] for p in probes) / len(probes) for m in METRICS} for mat in MATERIALS}


def main(argv: list[str] | None = None) -> int:
    from core.sim.camera_curves import add_curve_argument

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suites", default="hard,moving-camera")
    p.add_argument("--extra-probes", type=int, default=8, help="as the accuracy probe's (same draws for the same seed)")
    p.add_argument("--probe-seed", type=int, default=0)
    p.add_argument("--gt-height", type=int, default=64)
    p.add_argument("--sphere-size", type=int, default=64)
    p.add_argument("--field-json", default=None, help="an accuracy probe report to set the field's scores beside")
    p.add_argument("--bind-changing", action="store_true",
                   help="bind the prior as for changing lighting whatever the job decides (no merged views, no "
                        "exposure evidence across frames): the accuracy probe's prior row before 2026-12-02")
    p.add_argument("--cache-dir", default=None)
    p.add_argument("-o", "--output", default=None)
    add_curve_argument(p, allow_all=False)  # the suites' camera curve: drawn per scene, or forced
    args = p.parse_args(argv)

    from bench.methods import _bound_prior
    from bench.run import default_cache_dir
    from bench.suite.simulated import load_suite, with_extra_probes
    from core.engine.presets import preset

    field_report = json.loads(Path(args.field_json).read_text()) if args.field_json else None
    cache = Path(args.cache_dir) if args.cache_dir else default_cache_dir()
    cfg = preset("draft")
    report: dict = {
        "extra_probes": args.extra_probes,
        "probe_seed": args.probe_seed,
        "bind_changing": args.bind_changing,
        "curve": args.curve,
        "suites": {},
    }
    for name in args.suites.split(","):
        suite = with_extra_probes(load_suite(name, cache, None, args.gt_height, args.curve), args.extra_probes,
                                  args.probe_seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            prior = _bound_prior(suite, cfg)
            if args.bind_changing:
                prior.bind(prior._capture, lighting_changes=True)
            probes = [frame_scores(prior, suite, i, args.sphere_size) for i in range(len(suite.probes))]
        entry = {key: mean_over(probes, key) for key in ("own_frame", "best_frame", "worst_frame", "mean_of_frames")}
        field = field_from_report(field_report, name, [q["x"] for q in probes], args.field_json)
        if field is not None:
            entry["field"] = field
        entry["probes"] = probes
        report["suites"][name] = entry
        print(f"{name} ({len(probes)} probes): mean over probes")
        for mat in MATERIALS:
            for m in METRICS:
                row = "  ".join(
                    f"{k} {entry[k][mat][m]:.3f}"
                    for k in ("own_frame", "best_frame", "worst_frame", "mean_of_frames", "field")
                    if k in entry
                )
                print(f"  {mat}.{m}: {row}")
    write_report(report, args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
