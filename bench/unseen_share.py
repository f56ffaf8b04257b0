"""Where the prior loses at held-out probes: in the directions it saw, or in those it filled?

    python -m bench.unseen_share [--suites spatial,temporal,moving-camera] [--extra-probes 8] [-o out.json]

For each suite, the job's prior (bench.methods._bound_prior, as the accuracy probe binds it) is
queried at the suite's probes and at `--extra-probes` drawn in free space (seed 0), at its own
env height, with the mask of directions its splat saw (`observed_envmaps`). Each probe is scored
(three-sphere relative si-RMSE against the simulator's truth at the same height) four ways:
* `prior`: the prior's map as it is;
* `truth_where_unseen`: the prior where it saw, the truth where it filled (what a perfect fill
  of the unseen directions would reach);
* `truth_where_seen`: the truth where the prior saw, the prior's fill elsewhere (what perfect
  observed directions would reach);
* `constant`: a constant map of the prior's mean colour.
A SHORTCUT measurement (the prior, not the field; the truth spliced in): it says which part of
the map a better prior must improve, not what users get.
"""
from __future__ import annotations

import argparse
import sys
import warnings

import torch

MATERIALS = ("diffuse", "matte")


def suite_share(name: str, extra_probes: int) -> dict:
    from bench.methods import _bound_prior
    from bench.run import default_cache_dir
    from bench.suite.evaluation import score_probe
    from bench.suite.simulated import load_suite, with_extra_probes
    from core.engine.presets import preset
    from core.envmap import resize_envmap

    suite = with_extra_probes(load_suite(name, default_cache_dir(), None, 64), extra_probes, 0)
    prior = _bound_prior(suite, preset("draft"))
    h = prior.env_height
    sums: dict[str, dict[str, list[float]]] = {}
    seen_share = []
    for i, probe in enumerate(suite.probes):
        x = torch.tensor([probe.x], dtype=torch.float32)
        env = prior.envmaps(x, float(probe.t), h)[0]
        seen = prior.observed_envmaps(x, float(probe.t))[1][0].bool()[..., None]
        gt = resize_envmap(suite.gt[i], h)
        preds = {"prior": env, "truth_where_unseen": torch.where(seen, env, gt),
                 "truth_where_seen": torch.where(seen, gt, env),
                 "constant": env.reshape(-1, 3).mean(0).expand_as(env).clone()}
        for method, scores in score_probe(preds, gt, 64).items():
            for m in MATERIALS:
                sums.setdefault(method, {}).setdefault(m, []).append(scores[m]["si_rmse_rel"])
        seen_share.append(float(seen.float().mean()))
    return {"probes": len(suite.probes), "env_height": h, "seen_share_mean": round(sum(seen_share) / len(seen_share), 3),
            "si_rmse_rel_mean": {k: {m: round(sum(v) / len(v), 4) for m, v in d.items()} for k, d in sums.items()}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suites", default="spatial,temporal,moving-camera")
    p.add_argument("--extra-probes", type=int, default=8)
    p.add_argument("-o", "--output", default=None)
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")
    out = {"extra_probes": args.extra_probes,
           "suites": {name: suite_share(name, args.extra_probes) for name in args.suites.split(",")}}
    from bench.report import show_and_write

    show_and_write(out, out, args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
