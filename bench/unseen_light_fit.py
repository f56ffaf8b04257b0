"""Can the seen room's change locate a light no frame shows? A one-off experiment (issue 12).

    python -m bench.unseen_light_fit [--suite temporal] [--emission isotropic|facing] [-o out.json]

The `temporal` suite's ceiling panel is out of view and switches off at frame 8; the field
cannot follow it because the prior never shows it (docs/engine.md, "Time"). Its light is still
in the frames: the walls and floor it lit go darker. This script fits that change. For sample
points of the static camera's view (depth, normals from depth, the prior's linear radiance per
time knot, points near the found emitters left out), it models

    B_k(p) = rho(p) * (a_k + sum_e v_ek G(p, c_e) + u_k G(p, q))

with an albedo rho per point, per knot an ambient a_k, the visible emitters' strengths v_ek and
an unseen source's u_k (all >= 0), G the unshadowed irradiance of a point source (isotropic, or
`facing`: a Lambertian emitter facing the points' centroid). For every candidate position q on
a 9^3 grid over the scene box, except those the camera would see, it alternates least squares
for the knots' coefficients and the albedos (relative residual), and reports the best
candidates and, from an assumed median albedo of 0.5, the source's contribution to the
brightness (solid-angle integral of luminance) at the suite's series positions just before the
switch, against the simulator's truth (brightness at frame 7 minus frame 8).

It is an experiment, not a product path: what it found decided that the engine does not model
unseen sources (see docs/engine.md).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from pathlib import Path

import torch

ASSUMED_ALBEDO = 0.5
SAMPLE_POINTS = 1500
GRID = 9
ITERATIONS = 30


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suite", default="temporal")
    p.add_argument("--emission", choices=("isotropic", "facing"), default="isotropic")
    p.add_argument("-o", "--output", default=None)
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")

    from bench.run import default_cache_dir
    from bench.suite.evaluation import envmap_brightness
    from bench.suite.simulated import load_suite, switch_frames
    from core.capture.depth import surface_normals
    from core.capture.load import load_capture
    from core.engine.distill import emitter_sources, time_knots
    from core.engine.presets import preset
    from core.engine.scene import scene_bounds
    from core.exposure import luminance
    from core.priors.registry import build_prior
    from core.sim.render import render_envmap

    suite = load_suite(args.suite, default_cache_dir(), None, 64)
    cfg = preset("draft")
    cap = load_capture(suite.capture_dir).resized(cfg.distill.work_height)  # as run_job works on it
    prior = build_prior("reprojection", cfg.prior_settings("reprojection"))
    prior.bind(cap, lighting_changes=True)  # the suite's lighting changes (its panel switches off)
    bounds = scene_bounds(cap, cfg.distill.time_normalisation_frames)
    sources = emitter_sources(cap, prior, cfg.distill, bounds, True)
    K = time_knots(cap.num_frames)
    frames = cap.nearest_frames(bounds.knot_times(K)).tolist()
    cam = cap.camera(0)
    pts = cam.unproject(cap.depth[0].double())
    nrm = surface_normals(pts, cap.poses[0, :3, 3].double())
    B = torch.stack([luminance(torch.as_tensor(prior.view_radiance(f)).double()) for f in frames], -1)
    ok = torch.isfinite(pts).all(-1) & torch.isfinite(nrm).all(-1) & torch.isfinite(B).all(-1) & (B > 0).all(-1)
    if sources is not None:
        gap = torch.cdist(pts.reshape(-1, 3), sources.centres.double()) - 2 * sources.radii.double()[None]
        ok &= ~(gap < 0).any(-1).reshape(ok.shape)
    P, N, Bk = pts[ok], nrm[ok], B[ok]
    pick = torch.randperm(P.shape[0], generator=torch.Generator().manual_seed(0))[:SAMPLE_POINTS]
    P, N, Bk = P[pick], N[pick], Bk[pick]
    M = P.shape[0]
    centroid = P.mean(0)
    w = 1.0 / Bk.mean(1)

    def facing(q: torch.Tensor, towards: torch.Tensor) -> torch.Tensor:
        """[Q, X] emission factor of sources at q [Q, 3] towards points [X, 3]."""
        if args.emission == "isotropic":
            return torch.ones(q.shape[0], towards.shape[0], dtype=torch.float64)
        f = centroid[None] - q
        f = f / f.norm(dim=-1, keepdim=True)
        d = towards[None] - q[:, None]
        return ((d / d.norm(dim=-1, keepdim=True)) * f[:, None]).sum(-1).clamp_min(0)

    def irradiance(q: torch.Tensor) -> torch.Tensor:  # [Q, M] per unit intensity
        rel = q[:, None, :] - P[None]
        r = rel.norm(dim=-1).clamp_min(0.05)
        return ((rel * N[None]).sum(-1) / r).clamp_min(0) / r.pow(2) * facing(q, P)

    def fit(basis: torch.Tensor):
        Q, _, J = basis.shape
        rho = torch.ones(Q, M, dtype=torch.float64)
        for _ in range(ITERATIONS):
            A = (rho * w)[..., None] * basis
            y = (Bk * w[:, None])[None].expand(Q, M, K)
            c = torch.linalg.solve(A.transpose(1, 2) @ A + 1e-9 * torch.eye(J, dtype=torch.float64),
                                   A.transpose(1, 2) @ y).transpose(1, 2).clamp_min(0)
            E = basis @ c.transpose(1, 2)
            rho = (E * Bk[None]).sum(-1) / E.pow(2).sum(-1).clamp_min(1e-30)
            rho = rho / rho.median(1).values[:, None].clamp_min(1e-30)
        res = ((rho[..., None] * (basis @ c.transpose(1, 2)) - Bk[None]) * w[None, :, None]).pow(2).mean((1, 2))
        return c, res

    visible = [irradiance(c[None].double())[0] for c in (sources.centres if sources is not None else [])]
    base = torch.stack([torch.ones(M, dtype=torch.float64), *visible], -1)[None]
    c0, r0 = fit(base)
    lo, hi = torch.tensor(bounds.lo, dtype=torch.float64), torch.tensor(bounds.hi, dtype=torch.float64)
    g = torch.linspace(0, 1, GRID, dtype=torch.float64)
    q = lo + torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) * (hi - lo)
    u, v, z = cam.project(q)
    k = cam.intrinsics
    inview = (z > 0) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    depth_there = torch.full_like(z, float("inf"))
    i = inview.nonzero()[:, 0]
    depth_there[i] = cap.depth[0].double()[v[i].long(), u[i].long()]
    q = q[~(inview & (z < depth_there))]
    c, r = fit(torch.cat([base.expand(q.shape[0], M, base.shape[-1]), irradiance(q)[..., None]], -1))

    switch = switch_frames(suite.scene)[0]
    before = max(k for k, f in enumerate(frames) if f < switch)
    positions = list(dict.fromkeys(tuple(s.x) for s in suite.series))
    truth = []
    for x in positions:
        gt = torch.stack([render_envmap(suite.scene, x, f / suite.scene.fps, 32) for f in (switch - 1, switch)])
        b = envmap_brightness(gt)
        truth.append(round(float(b[0] - b[1]), 3))
    scale = math.pi / ASSUMED_ALBEDO  # E = pi B / albedo, with the fitted albedos' median at 1
    best = []
    for j in r.argsort()[:5].tolist():
        xs = torch.tensor(positions, dtype=torch.float64)
        r2 = ((xs - q[j]) ** 2).sum(-1)
        contribution = float(c[j, before, -1]) * scale * facing(q[j:j + 1], xs)[0] / r2
        best.append({"position": [round(float(a), 2) for a in q[j]], "residual_vs_without": round(float(r[j] / r0[0]), 3),
                     "course": [round(float(a), 3) for a in c[j, :, -1]],
                     "brightness_before_switch": [round(float(a), 3) for a in contribution]})
    report = {"suite": args.suite, "emission": args.emission, "points": M, "knots": K, "candidates": int(q.shape[0]),
              "ambient_without_unseen": [round(float(a), 4) for a in c0[0, :, 0]],
              "series_positions": [list(x) for x in positions], "truth_brightness_of_switched_light": truth,
              "best": best}
    print(json.dumps(report, indent=1))
    if args.output:
        Path(args.output).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
