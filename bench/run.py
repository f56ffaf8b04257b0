"""`lightfield bench`: accuracy vs time on simulated suites, real panoramas, scaling, stability,
camera tracking.

    lightfield bench [--quick] [-o DIR] [--hdri-dir DIR] [--sections ...]

Writes DIR/results.json (every number + the machine), DIR/results.md (tables) and Pareto
plots (DIR/pareto_*.png). `--quick` uses tiny budgets (documented in the output) so it
finishes in minutes on 2 cores; its numbers show trends, not converged accuracy.
"""
from __future__ import annotations

import shutil
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from bench.methods import Budget, config_summary, core_methods, sweep_methods
from bench.panoramas import DEFAULT_HDRI_DIR
from bench.suite.measure import machine_info

SUITE_NAMES = ("spatial", "temporal", "moving-camera", "hard")
SECTIONS = ("simulated", "panoramas", "scaling", "stability", "tracking")
DEFAULT_OUT_DIR = Path(__file__).resolve().parent / "results"


@dataclass(frozen=True)
class Mode:
    """Everything the quick and full modes differ in."""

    name: str
    resolution: tuple[int, int] | None  # suite render size (None: the suite's own 192x144)
    gt_height: int
    sphere_size: int
    base_iterations: int
    iterations: tuple[int, ...]
    widths: tuple[tuple[int, int], ...]
    work_heights: tuple[int, ...]
    probes: tuple[int, ...]
    sweep_suites: tuple[str, ...]
    panorama_limit: int | None  # panoramas per split (None: all)
    note: str

    def budget(self) -> Budget:
        from core.engine.presets import preset

        base = preset("draft").with_overrides({"distill.iterations": self.base_iterations})
        return Budget(base, self.iterations, self.widths, self.work_heights, self.probes)


QUICK = Mode(
    name="quick", resolution=(128, 96), gt_height=64, sphere_size=32, base_iterations=40,
    iterations=(20, 40, 80), widths=((32, 3), (96, 4), (256, 6)), work_heights=(48, 72, 96), probes=(1, 9, 16),
    sweep_suites=("spatial",), panorama_limit=3,
    note=("QUICK MODE: {it} distillation steps for the reference MLP (the draft preset uses {draft}), "
          "suites rendered at 128x96, spheres rendered at 32 px, budget sweep and ablations on {sweep}, "
          "3 panoramas per split. Small budgets show trends and costs, not converged accuracy."),
)
FULL = Mode(
    name="full",
    resolution=None,
    gt_height=64,
    sphere_size=64,
    base_iterations=300,
    iterations=(100, 300, 800),
    widths=((32, 3), (96, 4), (128, 6), (256, 6)),
    work_heights=(48, 72, 120),
    probes=(1, 4, 9, 16),
    sweep_suites=SUITE_NAMES,
    panorama_limit=None,
    note="FULL MODE: {it} steps for the reference MLP (the draft preset has {draft}), budget sweep and ablations on "
         "{sweep}.",
)


@dataclass
class BenchOptions:
    quick: bool = False
    out_dir: Path = DEFAULT_OUT_DIR
    hdri_dir: Path = DEFAULT_HDRI_DIR
    cache_dir: Path | None = None
    suites: tuple[str, ...] = SUITE_NAMES
    sections: tuple[str, ...] = SECTIONS
    keep_artefacts: bool = False
    iterations: int | None = None  # override the reference budget (the sweep scales with it)
    sweep_suites: tuple[str, ...] | None = None  # override the mode's (empty: core methods only)
    diffusion_weights: Path | None = None  # local diffusion prior weights: adds mlp/grid-diffusion
    diffusionlight_weights: Path | None = None  # imported DiffusionLight weights: adds diffusionlight(-distilled)
    # the captures' camera curve (core.sim.camera_curves): "drawn" per capture, or a name (every
    # section's captures encoded with it); a per-curve run of a bench is its own CLI's `--curve all`
    curve: str = "drawn"


def log(msg: str) -> None:
    print(f"[bench] {msg}", file=sys.stderr, flush=True)


def default_cache_dir() -> Path:
    import os

    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "lightfield" / "bench"


def resolve_mode(opts: BenchOptions) -> Mode:
    """The quick or full mode with the user's overrides (recorded in the results' note)."""
    from dataclasses import replace

    mode = QUICK if opts.quick else FULL
    if opts.iterations is not None:
        n = int(opts.iterations)
        mode = replace(mode, base_iterations=n, iterations=(max(1, n // 2), n, 2 * n))
    if opts.sweep_suites is not None:
        mode = replace(mode, sweep_suites=tuple(opts.sweep_suites))
    from core.engine.presets import preset

    sweep = ", ".join(mode.sweep_suites) if mode.sweep_suites else "no suite"
    note = mode.note.format(it=mode.base_iterations, draft=preset("draft").distill.iterations, sweep=sweep)
    return replace(mode, note=note)


def run_simulated(mode: Mode, opts: BenchOptions, workdir: Path) -> dict:
    from bench.suite.sections import run_suite
    from bench.suite.simulated import load_suite

    budget = mode.budget()
    cache = opts.cache_dir or default_cache_dir()
    out: dict = {
        "budget": {
            "base": config_summary(budget.base),
            "iterations": budget.iterations,
            "widths": budget.widths,
            "work_heights": budget.work_heights,
            "probes": budget.probes,
        },
        "sweep_suites": list(mode.sweep_suites),
        "suites": {},
    }
    for name in opts.suites:
        log(f"suite {name}: preparing capture")
        suite = load_suite(name, cache, mode.resolution, mode.gt_height, opts.curve)
        methods = core_methods(opts.diffusion_weights, opts.diffusionlight_weights) + (
            sweep_methods(budget) if name in mode.sweep_suites else []
        )
        t0 = time.perf_counter()
        results = run_suite(suite, methods, budget, workdir, mode.sphere_size)
        out["suites"][name] = {
            "suite": suite.describe(),
            "wall_s": round(time.perf_counter() - t0, 1),
            "methods": results,
        }
    return out


def run_bench(opts: BenchOptions) -> dict:
    """Run the selected sections and write results.json, results.md and the plots."""
    import torch

    from bench import report

    mode = resolve_mode(opts)
    started = time.perf_counter()
    # One intra-op thread everywhere: distillation already runs single-threaded (the engine's
    # default), and on a shared or oversubscribed CPU extra threads make latencies erratic.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    results: dict = {"mode": mode.name, "note": mode.note, "mode_settings": asdict(mode), "machine": machine_info(),
                     "sections": list(opts.sections), "curve": opts.curve}
    workdir = Path(tempfile.mkdtemp(prefix="lightfield-bench-"))
    try:
        if "simulated" in opts.sections:
            results["simulated"] = run_simulated(mode, opts, workdir)
        if "panoramas" in opts.sections:
            from bench.real_panoramas import run_panoramas

            results["real_panoramas"] = run_panoramas(
                opts.hdri_dir, mode.panorama_limit, mode.sphere_size, quick=opts.quick, workdir=workdir, log=log,
                curve=opts.curve,
            )
        if "scaling" in opts.sections:
            from bench.scaling import run_scaling

            results["scaling"] = run_scaling(quick=opts.quick, workdir=workdir)
        if "stability" in opts.sections:
            from bench.suite.stability import run_stability

            results["stability"] = run_stability(quick=opts.quick, workdir=workdir)
        if "tracking" in opts.sections:
            from bench.tracking import run_tracking

            log("tracking: speed clips and panorama pans")
            results["tracking"] = run_tracking(
                opts.hdri_dir, mode.panorama_limit, mode.sphere_size, opts.quick, workdir, curve=opts.curve
            )
    finally:
        torch.set_num_threads(threads)
        if opts.keep_artefacts:
            log(f"artefacts kept in {workdir}")
        else:
            shutil.rmtree(workdir, ignore_errors=True)
    results["total_wall_s"] = round(time.perf_counter() - started, 1)
    report.write_all(results, Path(opts.out_dir))
    complete = (
        opts.sections == SECTIONS
        and opts.suites == SUITE_NAMES
        and opts.iterations is None
        and opts.sweep_suites is None
        and opts.curve == "drawn"
    )
    if Path(opts.out_dir).resolve() == DEFAULT_OUT_DIR.resolve() and complete:
        # only a complete run into the committed results directory refreshes the README
        command = "lightfield bench" + (" --quick" if opts.quick else "")
        report.update_readme(DEFAULT_OUT_DIR.parent / "README.md", results, command)
        report.update_readme(DEFAULT_OUT_DIR.parents[1] / "README.md", results, command, prefix="bench/results/")
    return results
