"""How closely the distilled field reproduces its own prior, where it was trained and where not.

    python -m bench.prior_fit [--suites spatial,temporal,hard] [--set distill.envmap_free_probes=0 ...]
        [--seed 0] [--draws 12] [-o fit.json]

bench/accuracy_probe.py scores field and prior against the simulator's truth. When the field
loses to its prior there, this says why: for each suite it distils the draft preset (as the
probe does), rebuilds the job's prior (the preset's settings, bound to the working-resolution
capture as `run_job` binds it) and compares the field's env map with the prior's at
* the probe kinds of a radiance step (core.engine.radiance: surface, room, camera centre, and
  free-space points, core.engine.free_space), drawn afresh from `--draws` steps' frames (the
  training distribution, not the exact training draws), and
* the suite's held-out probes (bench.suite.simulated, with the accuracy probe's extra probes),
as the log-radiance RMSE (floor 1e-3 x the map's mean) and the mean colour angle (degrees,
solid-angle weighted), at the prior's own env-map height. Field == prior would give 0 / 0: a
large value on the training kinds means the field underfits its prior (capacity or steps), a
large value only on held-out probes means it generalises poorly between probes.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

import torch

from bench.overrides import parse_set


def map_differences(field_maps: torch.Tensor, prior_maps: torch.Tensor) -> list[tuple[float, float]]:
    """Per map (log RMSE, solid-angle-weighted mean colour angle in degrees)."""
    from core.conventions import equirect_pixel_centres

    f, p = field_maps.double(), prior_maps.double()
    h = f.shape[1]
    theta, _ = equirect_pixel_centres(h, dtype=torch.float64)
    w = torch.sin(theta).reshape(1, h, 1).expand(f.shape[0], h, 2 * h)
    floor = 1e-3 * p.mean(dim=(1, 2, 3), keepdim=True).clamp_min(1e-12)
    log_rmse = ((f + floor).log() - (p + floor).log()).pow(2).mean(dim=(1, 2, 3)).sqrt()
    cos = (f * p).sum(-1) / (f.norm(dim=-1) * p.norm(dim=-1)).clamp_min(1e-30)
    angle = torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))
    colour = (angle * w).sum(dim=(1, 2)) / w.sum(dim=(1, 2))
    return [(round(float(a), 4), round(float(b), 3)) for a, b in zip(log_rmse, colour)]


def suite_fit(name: str, base, seed: int, draws: int, cache: Path) -> dict:
    from bench.accuracy_probe import distill_with_seed
    from bench.methods import Method
    from bench.suite.simulated import load_suite, with_extra_probes
    from core.capture.load import load_capture
    from core.engine.free_space import FreeSpaceSampler
    from core.engine.job import job_prior_settings
    from core.engine.params import JobParams
    from core.engine.radiance import supervision_probes
    from core.engine.scene import scene_bounds
    from core.fields.stored.artefact import LightFieldArtefact
    from core.priors.registry import build_prior

    suite = with_extra_probes(load_suite(name, cache, None, 64), 8, 0)
    method = Method("field", "field", "paper", "field", field=base.field.kind, overrides=(), prior="reprojection")
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        art = LightFieldArtefact.load(distill_with_seed(method, suite, base, Path(tmp) / "field", seed))
    work = load_capture(suite.capture_dir).resized(base.distill.work_height)
    prior = build_prior("reprojection", job_prior_settings(base, JobParams(preset="draft", prior="reprojection")))
    prior.bind(work, lighting_changes=art.uses_time)
    cfg, height = base.distill, base.distill.envmap_height
    sampler = FreeSpaceSampler.for_capture(work, scene_bounds(work, cfg.time_normalisation_frames))
    gen = torch.Generator().manual_seed(1234)
    kinds = ["surface"] * cfg.envmap_surface_probes + ["room"] * cfg.envmap_room_probes
    found: dict[str, list] = {"surface": [], "room": [], "camera": [], "free space": [], "held out": []}

    def compare(centers: torch.Tensor, t: float) -> list[tuple[float, float]]:
        with torch.no_grad():
            fm = art.envmaps(centers, [t] * centers.shape[0] if art.uses_time else None, height)[0]
        return map_differences(fm, prior.envmaps(centers, t, height))

    for _ in range(draws):
        i = int(torch.randint(work.num_frames, (1,), generator=gen))
        t = float(work.times[i])
        on_rays = supervision_probes(work, i, cfg.model_copy(update={"envmap_free_probes": 0}), gen)
        free = sampler.sample(2, gen)
        for kind, diff in zip(kinds + ["camera"] * int(cfg.envmap_camera_probe) + ["free space"] * free.shape[0],
                              compare(torch.cat((on_rays, free)), t)):
            found[kind].append(diff)
    for p in suite.probes:
        found["held out"] += compare(torch.tensor([p.x], dtype=torch.float32), float(p.t))
    return {kind: {"maps": len(v), "log_rmse": round(sum(a for a, _ in v) / len(v), 3),
                   "colour_angle_deg": round(sum(b for _, b in v) / len(v), 2)} for kind, v in found.items() if v}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suites", default="spatial,temporal,hard")
    p.add_argument("--set", action="append", default=[], help="draft preset override key=value (JSON value)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--draws", type=int, default=12, help="radiance-step frames whose probe kinds are compared")
    p.add_argument("--cache-dir", default=None)
    p.add_argument("-o", "--output", default=None)
    args = p.parse_args(argv)

    from bench.run import default_cache_dir
    from core.engine.presets import preset

    overrides = parse_set(args.set)
    base = preset("draft").with_overrides(overrides) if overrides else preset("draft")
    cache = Path(args.cache_dir) if args.cache_dir else default_cache_dir()
    report = {"overrides": overrides, "seed": args.seed, "suites": {}}
    for name in args.suites.split(","):
        report["suites"][name] = suite_fit(name, base, args.seed, args.draws, cache)
        for kind, r in report["suites"][name].items():
            print(f"{name:14s} {kind:10s} maps {r['maps']:3d}  field vs prior: log RMSE {r['log_rmse']:.3f}  "
                  f"colour {r['colour_angle_deg']:.2f} deg", flush=True)
    if args.output:
        Path(args.output).write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
