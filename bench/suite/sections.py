"""The simulated accuracy-vs-time section: every method on every suite, scored together."""
from __future__ import annotations

import sys
from pathlib import Path

from bench.methods import Budget, Method, MethodRun, run_method
from bench.suite.evaluation import envmap_brightness, flicker, mean_scores, score_probe, switch_lag
from bench.suite.simulated import SuiteData


def _log(msg: str) -> None:
    print(f"[bench] {msg}", file=sys.stderr, flush=True)


def temporal_scores(run: MethodRun, suite: SuiteData) -> dict:
    """Flicker on stretches without switches (pred vs gt) and lag at each switch."""
    stretches, switches = [], []
    for s, pred in zip(suite.series, run.series):
        if s.kind == "stretch":
            fp, fg = flicker(pred), flicker(s.gt)
            stretches.append({"x": list(s.x), "frames": len(s.times), "flicker": fp, "gt_flicker": fg,
                              "excess": None if fp is None else fp - fg})
        else:
            lag = switch_lag(s.times, envmap_brightness(pred), envmap_brightness(s.gt), suite.scene.fps)
            switches.append({"x": list(s.x), "switch_frame": s.switch_frame, **lag})
    def mean(key, rows):
        vals = [r[key] for r in rows if r.get(key) is not None]
        return sum(vals) / len(vals) if vals else None
    return {
        "flicker": mean("flicker", stretches), "gt_flicker": mean("gt_flicker", stretches),
        "excess_flicker": mean("excess", stretches), "lag_frames": mean("lag_frames", switches),
        "contrast_captured": mean("contrast_captured", switches),
        "stretches": stretches, "switches": switches,
    }


def run_suite(suite: SuiteData, methods: list[Method], budget: Budget, workdir: Path, sphere_size: int) -> dict:
    """Run `methods` on one suite and score them on identical held-out probes."""
    artefacts: dict = {}
    runs: list[MethodRun] = []
    for method in methods:
        _log(f"{suite.name}: {method.name} ...")
        run = run_method(method, suite, budget.base, workdir, artefacts)
        _log(
            f"{suite.name}: {method.name} prepare {run.prepare.seconds:.1f}s"
            + (f" ERROR {run.error}" if run.error else "")
        )
        runs.append(run)
    per_probe = []
    for i in range(len(suite.probes)):
        preds = {r.method.name: r.envmaps[i] for r in runs if r.envmaps is not None}
        per_probe.append(score_probe(preds, suite.gt[i], sphere_size))
    out: dict = {}
    for r in runs:
        name = r.method.name
        entry: dict = {"method": r.method.describe(budget.base), "error": r.error}
        if r.error is None:
            scores = [p[name] for p in per_probe]
            entry.update({
                "time": {"prepare_s": round(r.prepare.seconds, 3), "prepare_cpu_s": round(r.prepare.cpu_seconds, 3),
                         "peak_rss_delta_mb": round(r.prepare.peak_rss_delta_mb, 1),
                         "query_ms": None if r.query_ms is None else round(r.query_ms, 3),
                         "query_cpu_ms": None if r.query_cpu_ms is None else round(r.query_cpu_ms, 3)},
                "metrics": mean_scores(scores),
                "per_probe": scores,
                "temporal": temporal_scores(r, suite) if suite.series else None,
                "extra": r.extra,
            })
        out[name] = entry
    return out
