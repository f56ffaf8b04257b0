"""Bench output: results.json (every number), results.md (tables), Pareto plots (PNG, Agg).

Only numbers present in the results dict are printed; nothing here computes a metric.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Iterable

MATERIALS = ("diffuse", "matte", "mirror")


# ---------------------------------------------------------------------------------------
# JSON
# ---------------------------------------------------------------------------------------
def sanitize(value):
    """Plain JSON: NaN/inf -> None, tuples -> lists, tensors/numpy -> lists, Paths -> str."""
    if isinstance(value, dict):
        return {str(k): sanitize(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [sanitize(v) for v in value]
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "tolist"):
        return sanitize(value.tolist())
    return str(value)


def write_json(results: dict, path: Path) -> None:
    path.write_text(json.dumps(sanitize(results), indent=1, allow_nan=False) + "\n")


def show_and_write(shown: dict, report: dict, output: str | None) -> None:
    """A one-off bench script's ending: print `shown` (the report or its summary), write the
    whole report to `output` when given."""
    print(json.dumps(sanitize(shown), indent=1))
    if output:
        write_json(report, Path(output))


# ---------------------------------------------------------------------------------------
# Table helpers
# ---------------------------------------------------------------------------------------
def fmt(value, digits: int = 3) -> str:
    """Compact number: None -> '–', large/small values in scientific notation."""
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return "–"
        if value != 0 and (abs(value) >= 1e4 or abs(value) < 10 ** -(digits)):
            return f"{value:.{max(1, digits - 1)}e}"
        return f"{value:.{digits}g}" if abs(value) >= 1 else f"{value:.{digits}f}"
    return str(value)


def table(headers: list[str], rows: Iterable[list]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(fmt(v) if not isinstance(v, str) else v for v in row) + " |")
    return "\n".join(lines)


def _get(d: dict | None, *keys):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _mean(values: list) -> float | None:
    vals = [v for v in values if isinstance(v, (int, float)) and math.isfinite(v)]
    return sum(vals) / len(vals) if vals else None


def time_to_answer(entry: dict, n_queries: int, cpu: bool = False) -> float | None:
    """Seconds from input to the held-out answers: preparation (+ bake) + one query per probe.
    `cpu=True` sums CPU time instead of wall time (robust to other load on the machine)."""
    prep = _get(entry, "time", "prepare_cpu_s" if cpu else "prepare_s")
    q = _get(entry, "time", "query_cpu_ms" if cpu else "query_ms")
    if prep is None:
        return None
    bake = _get(entry, "extra", "bake", "cpu_seconds" if cpu else "seconds") or 0.0
    return prep + (q or 0.0) * n_queries / 1000.0 + bake


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of points no other point beats in both time and error (lower is better),
    sorted by time. Ties in both keep the first."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


# ---------------------------------------------------------------------------------------
# Markdown
# ---------------------------------------------------------------------------------------
SUITE_HEADERS = [
    "method",
    "group",
    "prior",
    "CPU s to answer",
    "wall s to answer",
    "query CPU (ms)",
    "peak RSS Δ (MB)",
    "diffuse rel si-RMSE",
    "matte rel si-RMSE",
    "mirror rel si-RMSE",
    "diffuse ang (°)",
    "matte ang (°)",
    "mirror ang (°)",
    "diffuse nRMSE",
    "matte nRMSE",
    "mirror nRMSE",
    "flicker (gt)",
    "switch lag (frames)",
    "switch captured",
]


def suite_rows(suite: dict) -> list[list]:
    rows = []
    n = len(_get(suite, "suite", "held_out_probes") or [])
    for name, e in suite["methods"].items():
        m = e.get("method", {})
        if e.get("error"):
            rows.append(
                [name, m.get("group", ""), m.get("prior", ""), f"ERROR: {e['error'][:80]}"]
                + ["–"] * (len(SUITE_HEADERS) - 4)
            )
            continue
        met, tmp = e.get("metrics", {}), e.get("temporal") or {}
        nonfinite = met.get("probes_non_finite") or 0
        fl = tmp.get("flicker")
        rows.append(
            [
                name + (f" ({nonfinite} NON-FINITE)" if nonfinite else ""),
                m.get("group", ""),
                m.get("prior", ""),
                time_to_answer(e, n, cpu=True),
                time_to_answer(e, n),
                _get(e, "time", "query_cpu_ms"),
                _get(e, "time", "peak_rss_delta_mb"),
                *[_get(met, mat, "si_rmse_rel") for mat in MATERIALS],
                *[_get(met, mat, "angular_deg") for mat in MATERIALS],
                *[_get(met, mat, "nrmse") for mat in MATERIALS],
                "–" if fl is None else f"{fmt(fl)} ({fmt(tmp.get('gt_flicker'))})",
                tmp.get("lag_frames"),
                tmp.get("contrast_captured"),
            ]
        )
    return rows


def headline_rows(sim: dict) -> tuple[list[str], list[list]]:
    """Methods run on every suite, averaged over suites (the same inputs for all)."""
    suites = sim.get("suites", {})
    names = None
    for s in suites.values():
        ok = {k for k, e in s["methods"].items() if not e.get("error")}
        names = ok if names is None else names & ok
    order = [k for k in next(iter(suites.values()))["methods"]] if suites else []
    headers = [
        "method",
        "prior",
        "CPU s to answer",
        "wall s to answer",
        "query CPU (ms)",
        "diffuse rel si-RMSE",
        "matte rel si-RMSE",
        "mirror rel si-RMSE",
        "diffuse ang (°)",
        "mirror ang (°)",
        "excess flicker",
        "switch lag (frames)",
        "switch captured",
    ]
    rows = []
    for name in order:
        if name not in (names or set()):
            continue
        es = [s["methods"][name] for s in suites.values()]
        ns = [len(_get(s, "suite", "held_out_probes") or []) for s in suites.values()]
        rows.append(
            [
                name,
                es[0]["method"].get("prior", ""),
                _mean([time_to_answer(e, n, cpu=True) for e, n in zip(es, ns)]),
                _mean([time_to_answer(e, n) for e, n in zip(es, ns)]),
                _mean([_get(e, "time", "query_cpu_ms") for e in es]),
                *[_mean([_get(e, "metrics", mat, "si_rmse_rel") for e in es]) for mat in MATERIALS],
                _mean([_get(e, "metrics", "diffuse", "angular_deg") for e in es]),
                _mean([_get(e, "metrics", "mirror", "angular_deg") for e in es]),
                _mean([_get(e, "temporal", "excess_flicker") for e in es]),
                _mean([_get(e, "temporal", "lag_frames") for e in es]),
                _mean([_get(e, "temporal", "contrast_captured") for e in es]),
            ]
        )
    return headers, rows


def machine_lines(machine: dict) -> list[str]:
    return [
        f"- machine: {machine.get('cpu_model')}, {machine.get('cores')} cores, load average "
        f"{machine.get('load_average_1_5_15min')} "
        f"(wall times are inflated by other processes when the load exceeds the core count)",
        f"- torch {machine.get('torch_version')}, python {machine.get('python')}, {machine.get('date_utc')}, "
        f"commit {str(machine.get('git_commit'))[:12]}"
        f"{' (+ uncommitted changes)' if machine.get('git_tracked_files_modified') else ''}",
        f"- memory: {machine.get('memory_method')}",
    ]


def markdown(results: dict) -> str:
    out = [f"# lightfield bench ({results.get('mode')})", "", f"> {results.get('note')}", ""]
    out += machine_lines(results.get("machine", {}))
    out += [f"- total wall time: {results.get('total_wall_s')} s", ""]
    sim = results.get("simulated")
    if sim:
        base = _get(sim, "budget", "base") or {}
        out += [
            "## Simulated suites: accuracy vs time",
            "",
            f"Reference distillation: {base.get('field_kind')} {base.get('field_width')}x{base.get('field_layers')}, "
            f"{base.get('iterations')} steps, {base.get('n_probes')} probes/step, frames at {base.get('work_height')} "
            "rows, "
            f"reprojection prior at {base.get('prior_env_height')} rows. Errors are means over the held-out probes; "
            "lower is better. 'time to answer' = distillation (or prior set-up) + one query per held-out probe. "
            "Oracle rows read the simulator's ground truth: upper bounds, not estimators.",
            "",
        ]
        headers, rows = headline_rows(sim)
        out += ["### Headline: mean over all suites", "", table(headers, rows), ""]
        for name, suite in sim.get("suites", {}).items():
            out += [f"### Suite `{name}`", "", table(SUITE_HEADERS, suite_rows(suite)), ""]
    pano = results.get("real_panoramas")
    if pano:
        out += panorama_markdown(pano)
    scaling = results.get("scaling")
    if scaling:
        out += scaling_markdown(scaling)
    stab = results.get("stability")
    if stab:
        out += stability_markdown(stab)
    tracking = results.get("tracking")
    if tracking:
        out += tracking_markdown(tracking)
    return "\n".join(out) + "\n"


def _with_interval(method: dict, ratio: str) -> str:
    """A ratio to the constant map with its 90 % interval over the panoramas, when the report has one."""
    value, interval = _get(method, "vs_constant", ratio), _get(method, "interval_90", ratio)
    return fmt(value) + (f" [{fmt(interval[0])}, {fmt(interval[1])}]" if interval else "")


def panorama_markdown(pano: dict) -> list[str]:
    out = ["## Real panoramas, end to end (LDR photo -> `estimate` -> env map at the camera)", ""]
    if pano.get("skipped"):
        return out + [f"Skipped: {pano['skipped']}", ""]
    out += [pano.get("protocol", ""), ""]
    headers = [
        "split",
        "method",
        "images",
        "time (s)",
        "diffuse si-RMSE vs const [90 % interval]",
        "diffuse ang vs const [90 %]",
        "matte si-RMSE vs const [90 %]",
        "observed corr.",
        "diffuse rel si-RMSE",
        "diffuse ang (°)",
        "mirror ang (°)",
    ]
    rows = []
    for split, s in pano.get("splits", {}).items():
        for method, m in s.get("methods", {}).items():
            if method == "truth":
                rows.append(
                    [
                        split,
                        "truth (protocol ceiling)",
                        m.get("images"),
                        "–",
                        "–",
                        "–",
                        "–",
                        m.get("observed_corr"),
                        "–",
                        "–",
                        "–",
                    ]
                )
                continue
            rows.append([split, method, m.get("images"), m.get("seconds_per_image"),
                         _with_interval(m, "diffuse_si_rmse_rel"), _with_interval(m, "diffuse_angular_deg"),
                         _with_interval(m, "matte_si_rmse_rel"), m.get("observed_corr"),
                         _get(m, "metrics", "diffuse", "si_rmse_rel"), _get(m, "metrics", "diffuse", "angular_deg"),
                         _get(m, "metrics", "mirror", "angular_deg")])
    out += [table(headers, rows), ""]
    # how the scores move with the photos' camera curves (core.sim.camera_curves)
    curve_rows = [[split, label, method, m.get("images"), _with_interval(m, "diffuse_si_rmse_rel"),
                   _with_interval(m, "diffuse_angular_deg"), m.get("observed_corr")]
                  for split, s in pano.get("splits", {}).items() for label, ms in s.get("per_curve", {}).items()
                  for method, m in ms.items() if method != "truth" and "vs_constant" in m]
    if curve_rows:
        out += ["Per camera curve (each photo's curve is its row's `curve`):", "",
                table(["split", "camera curve", "method", "images", "diffuse si-RMSE vs const [90 %]",
                       "diffuse ang vs const [90 %]", "observed corr."], curve_rows), ""]
    return out


def scaling_markdown(scaling: dict) -> list[str]:
    out = ["## Scaling", "", scaling.get("note", ""), ""]
    headers = [
        "sweep",
        "values",
        "CPU seconds",
        "peak RSS Δ (MB)",
        "log-log exponent (time)",
        "log-log exponent (memory)",
    ]
    rows = []
    for name, s in scaling.get("sweeps", {}).items():
        rows.append(
            [
                name,
                ", ".join(fmt(v) for v in s.get("values", [])),
                ", ".join(fmt(v) for v in s.get("seconds", [])),
                ", ".join(fmt(v) for v in s.get("peak_rss_delta_mb", [])),
                s.get("time_exponent"),
                s.get("memory_exponent"),
            ]
        )
    return out + [table(headers, rows), ""]


def stability_markdown(stab: dict) -> list[str]:
    out = ["## Hard cases end to end (stability)", "", stab.get("note", ""), ""]
    headers = ["case", "passed", "seconds", "peak RSS Δ (MB)", "output range", "detail"]
    rows = [[c["name"], "PASS" if c.get("passed") else "FAIL", c.get("seconds"), c.get("peak_rss_delta_mb"),
             c.get("output_range", "–"), c.get("detail", "")] for c in stab.get("cases", [])]
    return out + [table(headers, rows), ""]


def tracking_markdown(tr: dict) -> list[str]:
    speed = tr.get("speed", {})
    out = [
        "## Camera tracking (captures without poses)",
        "",
        f"Speed: `track_camera` on {speed.get('frames')}-frame {'x'.join(str(v) for v in speed.get('size', []))} clips "
        f"rendered from the bundled dev panorama (target: <= {fmt(speed.get('target_cpu_s'))} s CPU). CPU seconds "
        "count "
        "every thread of the process.",
        "",
    ]
    headers = ["clip", "method", "CPU s", "wall s", "within target", "frames kept", "reprojection error (px)",
               "max rotation error (°)", "scale"]
    rows = [[name, c.get("method"), c.get("cpu_s"), c.get("wall_s"), c.get("within_target"), c.get("frames_kept"),
             c.get("reprojection_error_px"), c.get("max_rotation_error_deg"), c.get("scale_source")]
            for name, c in speed.get("clips", {}).items()]
    out += [table(headers, rows), ""]
    if tr.get("skipped"):
        return out + [f"Accuracy: skipped ({tr['skipped']})", ""]
    out += [f"Accuracy (the product, as a user runs it): {tr.get('protocol', '')}. Diffuse rel si-RMSE of the env map "
            "at the first camera at t = 0; `tracked` gives no poses, `true-poses` gives the true ones, `static` turns "
            "tracking off (the product before it tracked), `mean-colour` is a constant map.", ""]
    headers = ["split", "panoramas", "tracked", "true-poses", "static", "mean-colour", "tracked vs true", "within 5 %",
               "better than constant"]
    rows = []
    for split, s in tr.get("splits", {}).items():
        m = s.get("methods", {})
        rows.append(
            [
                split,
                len(s.get("files", [])),
                *[
                    _get(m, name, "diffuse", "si_rmse_rel")
                    for name in ("tracked", "true-poses", "static", "mean-colour")
                ],
                s.get("tracked_vs_true_poses"),
                s.get("within_5_percent"),
                s.get("better_than_constant"),
            ]
        )
    return out + [table(headers, rows), ""]


# ---------------------------------------------------------------------------------------
# Plots
# ---------------------------------------------------------------------------------------
def pareto_plot(sim: dict, path: Path) -> Path | None:
    """Error vs time to answer, one column per suite, one row per sphere material."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    suites = sim.get("suites", {})
    if not suites:
        return None
    fig, axes = plt.subplots(
        len(MATERIALS), len(suites), figsize=(4.6 * len(suites), 3.6 * len(MATERIALS)), squeeze=False
    )
    colors = {"baseline": "tab:gray", "paper": "tab:blue", "budget": "tab:cyan", "ablation": "tab:orange",
              "query": "tab:purple", "upper-bound": "tab:green"}
    for col, (sname, suite) in enumerate(suites.items()):
        n = len(_get(suite, "suite", "held_out_probes") or [])
        for row, mat in enumerate(MATERIALS):
            ax = axes[row][col]
            pts, labels, groups = [], [], []
            for name, e in suite["methods"].items():
                t, err = time_to_answer(e, n, cpu=True), _get(e, "metrics", mat, "si_rmse_rel")
                if t is None or err is None:
                    continue
                pts.append((max(t, 1e-4), err))
                labels.append(name)
                groups.append(_get(e, "method", "group") or "")
            for (t, err), name, g in zip(pts, labels, groups):
                ax.scatter(t, err, color=colors.get(g, "black"), s=18, marker="^" if "oracle" in name else "o")
                ax.annotate(name, (t, err), fontsize=6, xytext=(2, 2), textcoords="offset points")
            est = [i for i, name in enumerate(labels) if "oracle" not in name]
            front = [est[i] for i in pareto_front([pts[i] for i in est])]
            if front:
                ax.step(
                    [pts[i][0] for i in front],
                    [pts[i][1] for i in front],
                    where="post",
                    color="tab:red",
                    lw=0.8,
                    alpha=0.7,
                )
            ax.set_xscale("log")
            ax.set_title(f"{sname}: {mat}", fontsize=9)
            ax.set_xlabel("CPU seconds to answer (log)", fontsize=8)
            ax.set_ylabel("si-RMSE / RMS(gt)", fontsize=8)
            ax.tick_params(labelsize=7)
    handles = [plt.Line2D([], [], marker="o", ls="", color=c, label=g) for g, c in colors.items()]
    handles.append(plt.Line2D([], [], color="tab:red", label="Pareto front (estimators)"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def scaling_plot(scaling: dict, path: Path) -> Path | None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    sweeps = scaling.get("sweeps", {})
    if not sweeps:
        return None
    fig, axes = plt.subplots(1, len(sweeps), figsize=(3.8 * len(sweeps), 3.2), squeeze=False)
    for ax, (name, s) in zip(axes[0], sweeps.items()):
        xs, ys = s.get("values", []), s.get("seconds", [])
        pairs = [(x, y) for x, y in zip(xs, ys) if x and y]
        if pairs:
            ax.loglog([p[0] for p in pairs], [p[1] for p in pairs], "o-")
            for x, y in pairs:  # log axes spanning less than a decade have no labelled ticks
                ax.annotate(fmt(y), (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_title(f"{name} (slope {fmt(s.get('time_exponent'))})", fontsize=9)
        ax.set_xlabel(s.get("unit", name), fontsize=8)
        ax.set_ylabel("CPU seconds", fontsize=8)
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def write_all(results: dict, out_dir: Path) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    if results.get("simulated"):
        p = pareto_plot(results["simulated"], out_dir / "pareto_simulated.png")
        if p:
            written.append(p)
    if results.get("scaling"):
        p = scaling_plot(results["scaling"], out_dir / "scaling.png")
        if p:
            written.append(p)
    results["plots"] = [p.name for p in written]
    write_json(results, out_dir / "results.json")
    (out_dir / "results.md").write_text(markdown(results))
    return [out_dir / "results.json", out_dir / "results.md", *written]


# ---------------------------------------------------------------------------------------
# README
# ---------------------------------------------------------------------------------------
def readme_markers(block: str | None = None) -> tuple[str, str]:
    """Start/end markers of a generated README block (`block` names a second one)."""
    name = "bench-results" + (f"-{block}" if block else "")
    return f"<!-- {name}:start (generated by `lightfield bench`; do not edit by hand) -->", f"<!-- {name}:end -->"


def readme_section(results: dict, command: str, block: str | None = None, prefix: str = "results/") -> str:
    """The README's results block: headline table, plot, and where every number came from."""
    start, end = readme_markers(block)
    lines = [
        start,
        "",
        f"Generated by `{command}` on {_get(results, 'machine', 'date_utc')} "
        f"(commit {str(_get(results, 'machine', 'git_commit'))[:12]}, total {results.get('total_wall_s')} s wall).",
        "",
        f"> {results.get('note')}",
        "",
    ]
    lines += machine_lines(results.get("machine", {}))
    sim = results.get("simulated")
    if sim:
        headers, rows = headline_rows(sim)
        lines += ["", f"Mean over the simulated suites (full tables: [{prefix}results.md]({prefix}results.md)):", "",
                  table(headers, rows), "", f"![Pareto plots]({prefix}pareto_simulated.png)", ""]
    pano = results.get("real_panoramas")
    if pano:
        lines += panorama_markdown(pano)
    stab = results.get("stability")
    if stab:
        lines += [
            f"Stability: {len(stab.get('cases', [])) - stab.get('failures', 0)} of {len(stab.get('cases', []))} hard "
            "cases pass "
            "(table in results.md).",
            "",
        ]
    tracking = results.get("tracking")
    if tracking:
        lines += tracking_markdown(tracking)
    lines.append(end)
    return "\n".join(lines)


def update_readme(
    readme: Path, results: dict, command: str, block: str | None = None, prefix: str = "results/"
) -> bool:
    """Replace a generated block of `readme` (between its markers); False if absent."""
    if not readme.is_file():
        return False
    start, end = readme_markers(block)
    text = readme.read_text()
    a, b = text.find(start), text.find(end)
    if a < 0 or b < a:
        return False
    readme.write_text(text[:a] + readme_section(results, command, block, prefix) + text[b + len(end):])
    return True


def main(argv: list[str] | None = None) -> int:
    """Re-render results.md, the plots (and, with --readme, the README block) from a results.json.

    The numbers are the JSON's: nothing is re-measured."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__.split("\n")[0])
    parser.add_argument("results_json", type=Path)
    parser.add_argument("--readme", type=Path, default=None, help="README whose generated block to refresh")
    parser.add_argument("--command", default="lightfield bench --quick", help="the command that produced the JSON")
    parser.add_argument("--block", default=None, help="name of the README block (default: the main one)")
    args = parser.parse_args(argv)
    results = json.loads(args.results_json.read_text())
    write_all(results, args.results_json.parent)
    prefix = (
        str(args.results_json.parent.resolve().relative_to(args.readme.parent.resolve())) + "/" if args.readme else ""
    )
    if args.readme is not None and not update_readme(args.readme, results, args.command, args.block, prefix):
        print(f"{args.readme}: no generated block markers", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
