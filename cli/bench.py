"""`lightfield bench`: what accuracy costs in time (see bench/README.md)."""
from __future__ import annotations

HELP = "benchmark accuracy vs time (simulated suites, real panoramas, scaling, stability)"


def add_arguments(p) -> None:
    p.add_argument("--quick", action="store_true", help="tiny budgets: a few minutes on 2 cores (trends, not converged numbers)")
    p.add_argument("-o", "--out", default=None, help="output directory (default: bench/results in the repo; a complete run there also refreshes bench/README.md)")
    p.add_argument("--hdri-dir", default=None, help="indoor HDR panoramas with MANIFEST.tsv (default: ../shared/hdri from the repo)")
    p.add_argument("--cache-dir", default=None, help="where rendered suite captures are cached (default: ~/.cache/lightfield/bench)")
    p.add_argument("--suites", default=None, help="comma-separated subset of spatial,temporal,moving-camera,hard")
    p.add_argument("--sections", default=None, help="comma-separated subset of simulated,panoramas,scaling,stability")
    p.add_argument("--keep-artefacts", action="store_true", help="keep the distilled artefacts (printed path)")


def _subset(value: str | None, allowed: tuple[str, ...], flag: str) -> tuple[str, ...]:
    if value is None:
        return allowed
    items = tuple(v.strip() for v in value.split(",") if v.strip())
    bad = [v for v in items if v not in allowed]
    if bad or not items:
        raise SystemExit(f"lightfield bench: {flag} must be a comma-separated subset of {','.join(allowed)}; got {value!r}")
    return items


def run(args) -> int:
    from pathlib import Path

    from bench.run import DEFAULT_HDRI_DIR, DEFAULT_OUT_DIR, SECTIONS, SUITE_NAMES, BenchOptions, run_bench

    opts = BenchOptions(
        quick=args.quick,
        out_dir=Path(args.out) if args.out else DEFAULT_OUT_DIR,
        hdri_dir=Path(args.hdri_dir) if args.hdri_dir else DEFAULT_HDRI_DIR,
        cache_dir=Path(args.cache_dir) if args.cache_dir else None,
        suites=_subset(args.suites, SUITE_NAMES, "--suites"),
        sections=_subset(args.sections, SECTIONS, "--sections"),
        keep_artefacts=args.keep_artefacts,
    )
    results = run_bench(opts)
    print(f"wrote {opts.out_dir / 'results.json'}, {opts.out_dir / 'results.md'} ({results['total_wall_s']} s)")
    return 0
