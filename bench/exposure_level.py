"""The prior's level on the auto-exposure pan against the same pan at one fixed exposure.

    python -m bench.exposure_level [--fixed-ev -0.7] [-o out.json]

Binds the reprojection prior as the job does (bench.methods.run_per_probe, a SHORTCUT: the
prior, not the field) on the `auto-exposure` suite (exposures stated) and on a copy of its
scene whose sensor keeps one exposure (`--fixed-ev`, not stated: frames read at ev 0), and
prints each one's level against the truth in stops (bench.accuracy_probe.scale_stops; for the
fixed copy add `-fixed_ev` to get its bias in scene units). The clip rule estimates a clipped
source in each frame's own units (white = 1), so where the pan's exposure is low, the same
window reads brighter once the exposure is removed.
"""
from __future__ import annotations

import argparse
import sys
import warnings


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fixed-ev", type=float, default=-0.7)
    p.add_argument("-o", "--output", default=None)
    args = p.parse_args(argv)

    import core.sim.suites as suites
    from bench.accuracy_probe import scale_stops
    from bench.methods import Method, run_per_probe
    from bench.run import default_cache_dir
    from bench.suite.simulated import load_suite, with_extra_probes
    from core.engine.presets import preset
    from core.sim.spec import SensorSpec

    fixed_name = "auto-exposure-fixed"
    suites.SUITES[fixed_name] = lambda: suites.auto_exposure().model_copy(update={
        "name": fixed_name, "sensor": SensorSpec(ev=args.fixed_ev, noise_sigma=0.01)})
    out = {"fixed_ev": args.fixed_ev}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name in ("auto-exposure", fixed_name):
            suite = with_extra_probes(load_suite(name, default_cache_dir(), None, 64), 8, 0)
            run = run_per_probe(Method("prior", "per-probe", "baseline", "prior"), suite, preset("draft"))
            out[name] = scale_stops(run.envmaps, suite.gt)
    out["fixed_in_scene_units"] = round(out[fixed_name]["mean"] - args.fixed_ev, 3)
    from bench.report import show_and_write

    show_and_write(out, out, args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
