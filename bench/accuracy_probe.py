"""Accuracy probe of the distilled field against its prior and a constant map (issue 12).

    python -m bench.accuracy_probe [--suites spatial,temporal,moving-camera,hard]
        [--methods field,field-balls] [--set distill.iterations=400 ...] [--seed 0]
        [--extra-probes 8] [-o probe.json]

For each simulator suite (bench/suite: held-out probes and times, ground truth; plus
`--extra-probes` drawn uniformly in the room's free space and time, bench.suite.simulated.
with_extra_probes, because 3-4 probes leave a per-suite ratio with about +-0.1 of noise) it
scores, on the three-sphere metrics (diffuse, matte, mirror):
* prior     the reprojection prior queried directly at each held-out probe (a SHORTCUT: what
            the field is distilled from, not what users get);
* constant  one constant map of the mean linearised colour of the frame nearest the probe time;
* field     the draft preset end to end (`run_job`, then the artefact's exact env map);
* field-balls  the same with the paper's ball-render loop (`distill.supervision=balls`);
* field-oracle the draft preset distilled from the simulator's oracle prior (upper bound);
* <method>+observed  with `--observed-hybrid`, each method's maps with the prior's splat where
            the prior saw from the probe (a SHORTCUT: what a field carrying the observed surfaces'
            radiance could at best answer with this prior; not built).
Ratios field/prior (target <= 1.05 on every metric) and field/constant (target <= 0.85 on
diffuse and matte si-RMSE) are printed; on suites with a time series, the brightness
after/before each switch (pred vs truth, target |diff| <= 0.1) and, per stretch between
switches, the largest deviation of pred/truth brightness from its mean (on a static stretch the
field's own flatness; target <= 3 %). Per probe it also records the brightest direction's
luminance and its angle to the truth's (`peak_direction_deg`: where a lamp is seen from there).
Each ratio of means comes with a 90 % bootstrap interval over the probes (`interval_90`): a
target is missed for sure only when the whole interval is past it. `--set` overrides the draft
preset (dotted keys).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from bench.overrides import knobs_of, parse_set
from bench.suite.evaluation import ratio_interval

if TYPE_CHECKING:
    from bench.methods import Method

METRICS = ("si_rmse", "angular_deg", "nrmse")
MATERIALS = ("diffuse", "matte", "mirror")


def probe_method(name: str, base) -> "Method":
    """The bench Method of one `--methods` entry, training the field kind of `base` (the draft's
    unless `--set field.kind=...` changed it)."""
    from bench.methods import Method

    supervision = {"field": (), "field-balls": (("distill.supervision", "balls"),), "field-oracle": ()}[name]
    return Method(name, "field", "paper", name, field=base.field.kind, overrides=supervision,
                  prior="oracle" if name == "field-oracle" else "reprojection")


def constant_maps(suite, height: int) -> torch.Tensor:
    from bench.suite.simulated import capture_linear
    from core.capture.prepare import load_prepared_capture
    from core.conventions import equirect_width
    from core.engine.params import JobParams

    cap = load_prepared_capture(suite.capture_dir, params=JobParams(**suite.params))
    # linearised with the capture's own camera curve (not the engine's reading of its file, which
    # keeps a filmic tone curve in), a stated per-frame exposure removed, as the job does
    linear = capture_linear(suite.capture_dir, cap)
    out = []
    for p in suite.probes:
        i = int(torch.argmin((cap.times.double() - float(p.t)).abs()))
        mean = linear[i].reshape(-1, 3).mean(0)
        out.append(mean.expand(height, equirect_width(height), 3).clone())
    return torch.stack(out)


METHOD_LABELS = {
    "field": "radiance + view (draft)",
    "field-balls": "ball loop",
    "field-oracle": "from the oracle (bound)",
}


def observed_hybrid(prior, suite, field_maps: torch.Tensor) -> torch.Tensor:
    """SHORTCUT (`--observed-hybrid`): the field's maps with every direction that the job's prior
    saw from the probe (its splat of the frame nearest the probe's time and, under static light,
    the merged viewpoints; no fill) replaced by that splat. What a field carrying the observed
    surfaces' radiance, looked up along each direction (parallax exact; not built), could answer
    at best with the same prior; the field answers the rest."""
    from core.envmap import resize_envmap

    h, out = suite.eval_height, []
    for probe, fmap in zip(suite.probes, field_maps):
        env, seen = prior.observed_envmaps(torch.tensor([probe.x], dtype=torch.float32), float(probe.t))
        weight = resize_envmap(seen[0, ..., None].float().expand(-1, -1, 3).contiguous(), h)[..., :1]
        colour = resize_envmap(env[0], h) / weight.clamp_min(1e-6)  # the splat is 0 where unseen
        out.append(torch.where(weight > 0.5, colour, fmap))
    return torch.stack(out)


def markdown_table(report: dict) -> str:
    """The docs' table of a saved report (`--table report.json`): per suite and method the worst
    field/prior ratio with its 90 % interval, si-RMSE / prior per material and / constant."""
    rows = [
        "| suite | method | probes | worst metric / prior [90 % interval] | diffuse si / prior | matte si / prior "
        "| mirror si / prior | diffuse si / const | matte si / const | CPU s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, entry in report["suites"].items():
        n = len(entry.get("probes", [])) or "?"
        for method, r in entry["ratios"].items():
            if method == "prior":
                c = r["vs_constant"]
                rows.append(
                    f"| {name} | prior (shortcut) | {n} | 1 | 1 | 1 | 1 | {c['diffuse.si_rmse']:.2f} | "
                    f"{c['matte.si_rmse']:.2f} | |"
                )
                continue
            vp, vc = r["vs_prior"], r["vs_constant"]
            worst = max(vp, key=vp.get)
            interval = entry.get("interval_90", {}).get(method, {}).get("vs_prior", {}).get(worst)
            span = f" [{interval[0]:.2f}, {interval[1]:.2f}]" if interval else ""
            label = METHOD_LABELS.get(method.removesuffix("+observed"), method)
            label += " + prior's splat where seen (shortcut)" if method.endswith("+observed") else ""
            rows.append(
                f"| {name} | {label} | {n} | {vp[worst]:.2f} ({worst}){span} "
                f"| {vp['diffuse.si_rmse']:.2f} | {vp['matte.si_rmse']:.2f} | {vp['mirror.si_rmse']:.2f} "
                f"| {vc['diffuse.si_rmse']:.2f} | {vc['matte.si_rmse']:.2f} | {entry['cpu_s'].get(method, '')} |"
            )
    return "\n".join(rows)


def level_table(paths: list[str]) -> str:
    """`--level-table R1.json R2.json ...`: one row per report and suite (its job settings, the
    jobs' temporal decision, si-RMSE of the field / the constant map, the field's level against
    the truth in stops: mean and spread over probes, the largest static-stretch deviation)."""
    rows = [
        "| report | suite | frame_ev | temporal | time input | diffuse si / const | matte si / const "
        "| level, stops: mean (sd over probes) | static stretches, max dev |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for path in paths:
        report = json.loads(Path(path).read_text())
        given = ("withheld" if report.get("withhold_frame_ev") else "as captured") + (
            f", {report['frame_ev']}" if report.get("frame_ev") else "")
        for name, entry in report["suites"].items():
            c, lv = entry["ratios"]["field"]["vs_constant"], entry["scale_stops"]["field"]
            devs = [s["max_dev_vs_truth"] for s in entry.get("series", {}).get("field", {}).get("stretches", [])]
            rows.append(f"| {Path(path).stem} | {name} | {given} | {report.get('temporal', 'auto')} "
                        f"| {entry.get('uses_time', {}).get('field', '?')} | {c['diffuse.si_rmse']:.2f} "
                        f"| {c['matte.si_rmse']:.2f} | {lv['mean']:+.2f} ({lv['sd']:.2f}) "
                        f"| {f'{max(devs):.3f}' if devs else '-'} |")
    return "\n".join(rows)


def series_checks(suite, series_preds: list[torch.Tensor]) -> dict:
    """After/before brightness at each switch and the flatness of static stretches."""
    from bench.suite.evaluation import envmap_brightness, relative_course

    switches, stretches = [], []
    for s, pred in zip(suite.series, series_preds):
        bp, bg = envmap_brightness(pred), envmap_brightness(s.gt)
        if s.kind == "switch":
            rp, rg = float(bp[-1] / bp[0]), float(bg[-1] / bg[0])
            switches.append(
                {
                    "x": list(s.x),
                    "frame": s.switch_frame,
                    "after_before": round(rp, 3),
                    "truth": round(rg, 3),
                    "abs_diff": round(abs(rp - rg), 3),
                }
            )
        else:
            # the deviation of pred/truth from its mean: on a static stretch the pred's own flatness
            dev = float((relative_course(bp, bg) - 1.0).abs().max())
            dev_gt = float(((bg - bg.mean()) / bg.mean()).abs().max())
            stretches.append({"x": list(s.x), "frames": len(s.times), "max_dev_vs_truth": round(dev, 4),
                              "truth_max_dev": round(dev_gt, 4)})
    return {"switches": switches, "stretches": stretches}


def distill_with_seed(method, suite, base, out_dir: Path, seed: int) -> Path:
    """run_job on the suite's capture (as bench.methods.distill_artefact, with a chosen seed)."""
    from core.engine import run_job
    from core.engine.params import JobParams

    prior = None
    if method.prior == "oracle":
        from core.sim.oracle import OracleSimPrior

        prior = OracleSimPrior(suite.scene)
    cfg = method.config(base)
    params = JobParams(preset="draft", prior="reprojection", field=cfg.field.kind, seed=seed, **suite.params)
    with knobs_of(cfg):
        return run_job(suite.capture_dir, None, params, out_dir, prior=prior, config=cfg).path


def scale_stops(pred: torch.Tensor, gt: torch.Tensor) -> dict:
    """How far each probe's overall level is from the truth's, in stops (log2 of the ratio of
    solid-angle-weighted mean luminances): the mean, and the spread over probes. The three-sphere
    si-RMSE and angles ignore a scale; a compositor does not: a spread means the answer's
    brightness drifts from probe to probe (e.g. it follows a video's auto-exposure)."""
    from bench.suite.evaluation import envmap_brightness

    stops = torch.log2(envmap_brightness(pred).clamp_min(1e-12) / envmap_brightness(gt).clamp_min(1e-12))
    return {"mean": round(float(stops.mean()), 3), "sd": round(float(stops.std()), 3) if stops.numel() > 1 else 0.0}


def peak_direction_error(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Degrees between the brightest direction of `pred` and of `gt` (equirect [h, 2h, 3], each at
    its own height): where a probe sees the room's strongest source, if it sees it at all."""
    from core.conventions import equirect_directions
    from core.exposure import luminance
    from core.metrics import angular_error_deg

    def peak(env):  # [1, 3]: the unit direction of the brightest pixel
        lum = luminance(env.double()).reshape(-1)
        return equirect_directions(env.shape[0], dtype=torch.float64).reshape(-1, 3)[int(lum.argmax())][None]

    return angular_error_deg(peak(pred), peak(gt))


def without_frame_ev(capture_dir: Path, out: Path) -> Path:
    """A copy of a simulator capture whose capture.json states no per-frame exposures (the files
    linked, not copied)."""
    out.mkdir(parents=True, exist_ok=True)
    for item in capture_dir.iterdir():
        if item.name != "capture.json":
            (out / item.name).symlink_to(item.resolve(), target_is_directory=item.is_dir())
    doc = json.loads((capture_dir / "capture.json").read_text())
    doc.pop("frame_ev", None)
    (out / "capture.json").write_text(json.dumps(doc, indent=2))
    return out


def main(argv: list[str] | None = None) -> int:
    from core.sim.camera_curves import add_curve_argument

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suites", default="spatial,temporal,moving-camera,hard")
    p.add_argument("--methods", default="field", help="comma list of field, field-balls")
    p.add_argument("--set", action="append", default=[], help="draft preset override key=value (JSON value)")
    p.add_argument("--gt-height", type=int, default=64)
    p.add_argument("--sphere-size", type=int, default=64)
    p.add_argument("--seed", type=int, default=0, help="distillation seed (run a few to see run-to-run noise)")
    p.add_argument(
        "--extra-probes", type=int, default=8, help="held-out probes drawn in free space besides the suite's own"
    )
    p.add_argument("--probe-seed", type=int, default=0, help="seed of the extra probes' draw")
    p.add_argument("--observed-hybrid", action="store_true",
                   help="also score each method with the prior's splat where it saw (SHORTCUT, see observed_hybrid)")
    p.add_argument("--withhold-frame-ev", action="store_true",
                   help="run on a copy of each suite's capture without its per-frame exposures (`frame_ev`): the "
                        "same frames as a plain video (auto-exposure suites)")
    p.add_argument("--temporal", default="auto", choices=("auto", "on", "off"),
                   help="the jobs' temporal mode (the prior is bound with the same decision)")
    p.add_argument("--frame-ev", default=None, choices=("estimate", "locked"),
                   help="the jobs' frame_ev parameter: 'estimate' takes the frames' overall brightness course for "
                        "the camera's exposure; 'locked' turns off the default's auto-exposure detection")
    p.add_argument("--cache-dir", default=None)
    p.add_argument("-o", "--output", default=None)
    add_curve_argument(p, allow_all=False)  # the suites' camera curve: drawn per scene, or forced
    p.add_argument(
        "--table", default=None, metavar="REPORT_JSON", help="print the markdown table of a saved report and exit"
    )
    p.add_argument("--level-table", nargs="+", default=None, metavar="REPORT_JSON",
                   help="print the exposure / level comparison of saved reports and exit")
    args = p.parse_args(argv)
    if args.table:
        print(markdown_table(json.loads(Path(args.table).read_text())))
        return 0
    if args.level_table:
        print(level_table(args.level_table))
        return 0

    from bench.methods import Method, MethodRun, query_field, run_per_probe
    from bench.run import default_cache_dir
    from bench.suite.evaluation import mean_scores, score_probe
    from bench.suite.simulated import load_suite, with_extra_probes
    from core.engine.presets import preset
    from core.exposure import luminance

    overrides = parse_set(args.set)
    base = preset("draft").with_overrides(overrides) if overrides else preset("draft")
    cache = Path(args.cache_dir) if args.cache_dir else default_cache_dir()
    scratch = tempfile.TemporaryDirectory()  # the copies of `--withhold-frame-ev`
    report: dict = {"overrides": overrides, "seed": args.seed, "extra_probes": args.extra_probes,
                    "probe_seed": args.probe_seed, "temporal": args.temporal, "frame_ev": args.frame_ev,
                    "withhold_frame_ev": args.withhold_frame_ev, "curve": args.curve, "suites": {}}
    for name in args.suites.split(","):
        suite = with_extra_probes(load_suite(name, cache, None, args.gt_height, args.curve), args.extra_probes,
                                  args.probe_seed)
        if args.withhold_frame_ev:
            suite = dataclasses.replace(
                suite, capture_dir=without_frame_ev(suite.capture_dir, Path(scratch.name) / name)
            )
        suite.params = {"temporal": args.temporal, **({"frame_ev": args.frame_ev} if args.frame_ev else {})}
        preds: dict[str, torch.Tensor] = {}
        series: dict[str, list] = {}
        seconds: dict[str, float] = {}
        uses_time: dict[str, bool] = {}
        prior_run = run_per_probe(Method("prior", "per-probe", "baseline", "prior"), suite, base)
        preds["prior"], series["prior"] = prior_run.envmaps, prior_run.series
        preds["constant"] = constant_maps(suite, suite.eval_height)
        with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for method in args.methods.split(","):
                m = probe_method(method, base)
                t0 = time.process_time()
                path = distill_with_seed(m, suite, base, Path(tmp) / method, args.seed)
                seconds[method] = round(time.process_time() - t0, 1)
                uses_time[method] = json.loads((path / "lightfield.json").read_text())["temporal"]["uses_time"]
                run = MethodRun(m)
                query_field(run, path, suite)
                preds[method], series[method] = run.envmaps, run.series
        scored = args.methods.split(",")
        if args.observed_hybrid:
            from bench.methods import _bound_prior

            bound = _bound_prior(suite, base)
            for method in list(scored):
                preds[f"{method}+observed"] = observed_hybrid(bound, suite, preds[method])
                scored.append(f"{method}+observed")
        per_probe = [
            score_probe({k: v[i] for k, v in preds.items()}, suite.gt[i], args.sphere_size)
            for i in range(len(suite.probes))
        ]
        for i, pp in enumerate(per_probe):  # where the brightest direction stands: a lamp no frame shows reads here
            pp["peak_luminance"] = {"truth": round(float(luminance(suite.gt[i]).max()), 3),
                                    **{k: round(float(luminance(v[i]).max()), 3) for k, v in preds.items()}}
            pp["peak_direction_deg"] = {k: round(peak_direction_error(v[i], suite.gt[i]), 2) for k, v in preds.items()}
        scores = {k: mean_scores([pp[k] for pp in per_probe]) for k in preds}
        entry: dict = {
            "probes": [{"x": list(p.x), "t": p.t} for p in suite.probes],
            "scores": scores,
            "cpu_s": seconds,
            "uses_time": uses_time,
            "ratios": {},
            "interval_90": {},
            "scale_stops": {k: scale_stops(v, suite.gt) for k, v in preds.items()},
            "per_probe": per_probe,
        }

        def paired(method, ref, mat, metric):  # per-probe values of both, where both were scored
            both = [pp for pp in per_probe if "non_finite" not in pp[method] and "non_finite" not in pp[ref]]
            return [pp[method][mat][metric] for pp in both], [pp[ref][mat][metric] for pp in both]

        for method in scored:
            entry["ratios"][method] = {
                "vs_prior": {
                    f"{mat}.{m}": round(scores[method][mat][m] / scores["prior"][mat][m], 3)
                    for mat in MATERIALS
                    for m in METRICS
                },
                "vs_constant": {
                    f"{mat}.si_rmse": round(scores[method][mat]["si_rmse"] / scores["constant"][mat]["si_rmse"], 3)
                    for mat in ("diffuse", "matte")
                },
            }
            entry["interval_90"][method] = {
                "vs_prior": {f"{mat}.{m}": ratio_interval(*paired(method, "prior", mat, m))
                             for mat in MATERIALS for m in METRICS},
                "vs_constant": {f"{mat}.si_rmse": ratio_interval(*paired(method, "constant", mat, "si_rmse"))
                                for mat in ("diffuse", "matte")},
            }
            if suite.series and method in series:
                entry.setdefault("series", {})[method] = series_checks(suite, series[method])
        entry["ratios"]["prior"] = {
            "vs_constant": {
                f"{mat}.si_rmse": round(scores["prior"][mat]["si_rmse"] / scores["constant"][mat]["si_rmse"], 3)
                for mat in ("diffuse", "matte")
            }
        }
        if suite.series:
            entry.setdefault("series", {})["prior"] = series_checks(suite, series["prior"])
        report["suites"][name] = entry
        print(
            json.dumps(
                {
                    name: {
                        "probes": len(suite.probes),
                        "ratios": entry["ratios"],
                        "interval_90": entry["interval_90"],
                        "cpu_s": seconds,
                        "series": entry.get("series"),
                    }
                },
                indent=1,
            ),
            flush=True,
        )
    if args.output:
        Path(args.output).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
