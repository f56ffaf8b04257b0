"""How sharply the prior's answer depends on the exact probe position (issue 12's remaining misses).

    python -m bench.prior_smoothness [--suites spatial,temporal,moving-camera,hard]
        [--lattices 4,2,4:8,4,8:16,8,16] [--field-json bench/results/accuracy_probe.json] [-o smooth.json]

A field is a smooth function of position: it cannot answer at a held-out probe more exactly
than its positional resolution allows. This asks how much the prior itself loses when it is
made that smooth: for each held-out probe of the accuracy probe (same suites, extra probes and
seeds) it asks the job's prior (bench.methods._bound_prior) at the 8 corner nodes of the probe's
cell on a lattice over the field's box (core.engine.scene.scene_bounds, nodes as the room
lattice's, core.fields.components.encodings.lattice_corners) at the probe's time, blends those maps
trilinearly in log radiance (as the room lattice adds its maps to the field's logits) and
scores the blend on the three-sphere metrics, beside the prior asked at the probe itself and,
with `--field-json`, the field. A blend that scores worse than the prior says the prior's
answer varies between the nodes in ways that carry information (parallax: which surface a
direction hits moves with the probe), so a field no finer than that lattice loses it too.
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
METRICS = ("si_rmse", "angular_deg", "nrmse")


def parse_lattices(text: str) -> list[tuple[int, int, int]]:
    out = []
    for part in text.split(":"):
        dims = tuple(int(v) for v in part.split(","))
        if len(dims) != 3 or min(dims) < 2:
            raise SystemExit(f"--lattices: {part!r} is not nx,ny,nz with each >= 2")
        out.append(dims)
    return out


def blended_prior(prior, x: torch.Tensor, t: float, bounds, dims: tuple[int, int, int], height: int) -> torch.Tensor:
    """The prior's maps at the 8 lattice nodes around world point x [3] (lattice over the
    SceneBounds `bounds`), blended trilinearly in log radiance -> [height, 2 height, 3]."""
    from core.fields.components.encodings import lattice_corners

    index, weight = lattice_corners(bounds.normalize_x(x).clamp(-1.0, 1.0)[None], dims)
    node = torch.stack(torch.unravel_index(index[0], dims), dim=-1).float()  # [8, 3] lattice coordinates
    lo, hi = torch.tensor(bounds.lo, dtype=x.dtype), torch.tensor(bounds.hi, dtype=x.dtype)
    nodes = lo + node / (torch.tensor(dims, dtype=x.dtype) - 1) * (hi - lo)  # node r at -1 + 2 r / (n - 1)
    maps = prior.envmaps(nodes, t, height)  # [8, h, 2h, 3]
    log_maps = torch.log(maps.clamp_min(1e-8))
    return torch.exp((weight[0, :, None, None, None] * log_maps).sum(0))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suites", default="spatial,temporal,moving-camera,hard")
    p.add_argument(
        "--lattices", default="4,2,4:8,4,8:16,8,16", help="colon-separated nx,ny,nz (the draft's lattice: 8,4,8)"
    )
    p.add_argument("--extra-probes", type=int, default=8, help="as the accuracy probe's (same draws for the same seed)")
    p.add_argument("--probe-seed", type=int, default=0)
    p.add_argument("--gt-height", type=int, default=64)
    p.add_argument("--sphere-size", type=int, default=64)
    p.add_argument("--field-json", default=None, help="an accuracy probe report to set the field's scores beside")
    p.add_argument("--cache-dir", default=None)
    p.add_argument("-o", "--output", default=None)
    args = p.parse_args(argv)
    lattices = parse_lattices(args.lattices)

    from bench.methods import _bound_prior
    from bench.prior_frames import field_from_report, write_report
    from bench.run import default_cache_dir
    from bench.suite.evaluation import mean_scores, score_probe
    from bench.suite.simulated import load_suite, with_extra_probes
    from core.engine.presets import preset
    from core.engine.scene import scene_bounds

    field_report = json.loads(Path(args.field_json).read_text()) if args.field_json else None
    cache = Path(args.cache_dir) if args.cache_dir else default_cache_dir()
    cfg = preset("draft")
    report: dict = {"extra_probes": args.extra_probes, "probe_seed": args.probe_seed,
                    "lattices": [list(d) for d in lattices], "suites": {}}
    for name in args.suites.split(","):
        suite = with_extra_probes(load_suite(name, cache, None, args.gt_height), args.extra_probes, args.probe_seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            prior = _bound_prior(suite, cfg)
            bounds = scene_bounds(prior._capture, cfg.distill.time_normalisation_frames)
            per_probe: dict[str, list] = {"prior": []} | {"x".join(map(str, d)): [] for d in lattices}
            for i, probe in enumerate(suite.probes):
                x = torch.tensor(probe.x, dtype=torch.float32)
                gt, h = suite.gt[i], suite.eval_height
                per_probe["prior"].append(
                    score_probe({"m": prior.envmaps(x[None], float(probe.t), h)[0]}, gt, args.sphere_size)["m"]
                )
                for dims in lattices:
                    blend = blended_prior(prior, x, float(probe.t), bounds, dims, h)
                    per_probe["x".join(map(str, dims))].append(score_probe({"m": blend}, gt, args.sphere_size)["m"])
        entry = {k: mean_scores(v) for k, v in per_probe.items()}
        entry = {k: {mat: {m: v[mat][m] for m in METRICS} for mat in MATERIALS} for k, v in entry.items()}
        field = field_from_report(field_report, name, [q.x for q in suite.probes], args.field_json, METRICS)
        if field is not None:
            entry["field"] = field
        report["suites"][name] = {"box_lo": bounds.lo, "box_hi": bounds.hi, "means": entry}
        print(
            f"{name} ({len(suite.probes)} probes; box {[round(v, 2) for v in bounds.lo]} .. "
            f"{[round(v, 2) for v in bounds.hi]}):"
            " mean over probes, ratio to the prior at the probe in ()"
        )
        for mat in MATERIALS:
            for m in METRICS:
                ref = entry["prior"][mat][m]
                row = "  ".join(f"{k} {v[mat][m]:.3f} ({v[mat][m] / ref:.2f})" for k, v in entry.items())
                print(f"  {mat}.{m}: {row}")
    write_report(report, args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
