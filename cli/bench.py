"""`lightfield bench`: what accuracy costs in time (see bench/README.md); `lightfield bench list`
and `lightfield bench run NAME [--quick] [ARGS ...]`: every bench by name (bench/registry.py)."""
from __future__ import annotations

import argparse

HELP = "benchmark accuracy vs time (simulated suites, real panoramas, scaling, stability); list, run NAME"
# core.sim.camera_curves.CHOICES less "all" (not imported here: the CLI starts without torch)
CURVE_CHOICES = ("drawn", "srgb", "rec709", "filmic", "hlg10", "gamma2.4")


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="bench_command", metavar="{list,run}", required=False)
    sub.add_parser("list", help="every registered bench: name, kind, quick mode, what it measures")
    r = sub.add_parser("run", help="run one bench by name in its own process",
                       description="Run a registered bench. --quick (anywhere after NAME) becomes the bench's own "
                                   "quick arguments; every other argument goes to the bench unchanged.")
    r.add_argument("name", help="a name from `lightfield bench list`")
    r.add_argument("bench_args", nargs=argparse.REMAINDER, help="[--quick] and the bench's own arguments")
    p.add_argument(
        "--quick", action="store_true", help="tiny budgets: a few minutes on 2 cores (trends, not converged numbers)"
    )
    p.add_argument(
        "-o",
        "--out",
        default=None,
        help="output directory (default: bench/results in the repo; a complete run there also refreshes "
             "bench/README.md)",
    )
    p.add_argument(
        "--hdri-dir",
        default=None,
        help="indoor HDR panoramas with MANIFEST.tsv (default: ../shared/hdri from the repo)",
    )
    p.add_argument(
        "--cache-dir",
        default=None,
        help="where rendered suite captures are cached (default: ~/.cache/lightfield/bench)",
    )
    p.add_argument("--suites", default=None, help="comma-separated subset of spatial,temporal,moving-camera,hard")
    p.add_argument(
        "--sections", default=None, help="comma-separated subset of simulated,panoramas,scaling,stability,tracking"
    )
    p.add_argument("--keep-artefacts", action="store_true", help="keep the distilled artefacts (printed path)")
    p.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="override the reference distillation budget (steps); the iteration sweep uses half and double",
    )
    p.add_argument(
        "--diffusion-weights", default=None, help="local diffusion prior model directory: also distil mlp/grid from it"
    )
    p.add_argument(
        "--diffusionlight-weights",
        default=None,
        help="imported DiffusionLight prior directory (lightfield prior import): adds diffusionlight and "
             "diffusionlight-distilled",
    )
    p.add_argument(
        "--sweep-suites",
        default=None,
        help="suites that get the budget sweep and ablations ('none' for core methods only)",
    )
    p.add_argument(
        "--curve",
        default="drawn",
        choices=CURVE_CHOICES,
        help="the camera curve every section's captures are encoded with (core.sim.camera_curves): 'drawn' "
             "(default) per capture from the realistic set, or a name (gamma2.4: the reference, the curve the product "
             "used to assume); per-curve runs: a bench module's own `--curve all` (e.g. python -m bench.room_scans)",
    )


def _subset(value: str | None, allowed: tuple[str, ...], flag: str) -> tuple[str, ...]:
    if value is None:
        return allowed
    items = tuple(v.strip() for v in value.split(",") if v.strip())
    bad = [v for v in items if v not in allowed]
    if bad or not items:
        raise SystemExit(
            f"lightfield bench: {flag} must be a comma-separated subset of {','.join(allowed)}; got {value!r}"
        )
    return items


def _positive(value: int | None, flag: str) -> int | None:
    if value is not None and value < 1:
        raise SystemExit(f"lightfield bench: {flag} must be >= 1, got {value}")
    return value


def list_benches() -> int:
    from bench.registry import BENCHES

    width = max(len(name) for name in BENCHES)
    for b in BENCHES.values():
        tags = ", ".join(t for t in (b.kind if b.kind != "bench" else "", "quick" if b.quick is not None else "") if t)
        print(f"{b.name:<{width}}  {b.summary}" + (f" [{tags}]" if tags else ""))
    return 0


def run_named(name: str, bench_args: list[str]) -> int:
    """`--quick` before any `--` is the front door's; what follows `--` goes to the bench verbatim."""
    from bench.registry import run_bench

    cut = bench_args.index("--") if "--" in bench_args else len(bench_args)
    head, tail = bench_args[:cut], bench_args[cut + 1:]
    try:
        return run_bench(name, [a for a in head if a != "--quick"] + tail, quick="--quick" in head)
    except ValueError as exc:
        raise SystemExit(f"lightfield bench run: {exc}") from None


def run(args) -> int:
    from pathlib import Path

    command = getattr(args, "bench_command", None)
    if command == "list":
        return list_benches()
    if command == "run":
        return run_named(args.name, args.bench_args)

    from bench.run import DEFAULT_HDRI_DIR, DEFAULT_OUT_DIR, SECTIONS, SUITE_NAMES, BenchOptions, run_bench

    opts = BenchOptions(
        quick=args.quick,
        out_dir=Path(args.out) if args.out else DEFAULT_OUT_DIR,
        hdri_dir=Path(args.hdri_dir) if args.hdri_dir else DEFAULT_HDRI_DIR,
        cache_dir=Path(args.cache_dir) if args.cache_dir else None,
        suites=_subset(args.suites, SUITE_NAMES, "--suites"),
        sections=_subset(args.sections, SECTIONS, "--sections"),
        keep_artefacts=args.keep_artefacts,
        iterations=_positive(args.iterations, "--iterations"),
        diffusion_weights=Path(args.diffusion_weights) if args.diffusion_weights else None,
        diffusionlight_weights=Path(args.diffusionlight_weights) if args.diffusionlight_weights else None,
        curve=args.curve,
        sweep_suites=None
        if args.sweep_suites is None
        else (() if args.sweep_suites.strip() == "none" else _subset(args.sweep_suites, SUITE_NAMES, "--sweep-suites")),
    )
    results = run_bench(opts)
    print(f"wrote {opts.out_dir / 'results.json'}, {opts.out_dir / 'results.md'} ({results['total_wall_s']} s)")
    return 0
