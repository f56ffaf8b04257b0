"""Can the photo predict the low-frequency shape of what it did not see? A one-off experiment (issue 12).

    python -m bench.unseen_shape_fit [--train-views 12] [--views 4] [--lambdas 1e9,10,1,0.1] [--curve drawn|NAME]
        [-o out.json]

Oracle splices (docs/engine.md, "where the prior's remaining error sits") put most of the
reprojection prior's error on real photos in the low-frequency shape of the unseen directions:
the truth's band-2 spherical harmonics there would take diffuse si-RMSE from about 0.8x to 0.2-0.3x
the constant map's. This script asks whether that shape can be LEARNED from the `dev`
panoramas (tune on dev only; test and control are never read): per photo of the panorama
protocol (bench.real_panoramas), the prior's map at the camera (draft settings), the truth's
luminance in the camera frame and the directions the camera saw. Target: the band-2 SH
coefficients least-squares fitted to the truth's luminance over the UNSEEN directions, divided
by the truth's mean seen luminance. Features (`--features`):
* `moments`: the seen luminance's projection on the 9 SH functions over its mean (where the
  photo is bright, in the camera frame);
* `fill`: the same unseen-direction SH fit of the prior's own fill (a calibration of it);
* `both`.
A ridge regression (intercept not penalised; `--lambdas`; 1e9 is the intercept alone: one
learned shape for every photo) is fitted on `--train-views` photos per panorama and scored on
the protocol's `--views` photos of the panorama it left out (leave one panorama out). Scored
variants, all at the camera, against the constant map (a SHORTCUT: the prior, not the
product): the prior; its unseen directions replaced by each ridge's predicted SH (times the
prior's mean seen luminance, floored at FLOOR of it, in the prior's colour); `oracle` (the
target itself), `oracle, band 1 only` (the truth's constant and dipole), `oracle, row means
only` (the truth's mean over each row's unseen part: its elevation profile) and `fill-sh` (the
prior's fill reduced to its own SH fit).

It is an experiment, not a product path: what it found decided that the indoor fill keeps its
fixed elevation profile (docs/engine.md).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

FLOOR = 0.05  # x the mean seen luminance: the least a predicted SH map may give a direction
FEATURES = ("moments", "fill", "both")


def photos(hdri: Path, split: str, views: int, curve: str = "drawn") -> list[dict]:
    """Per photo: the prior's map, the truth (camera frame), the seen mask, the constant map (the
    photo's mean colour linearised with its camera curve: bench.real_panoramas.photo_curve of
    `curve`), the curve's name."""
    import bench.real_panoramas as rp
    from core.camera import Camera
    from core.engine.extrapolation import observed_directions
    from core.engine.presets import preset
    from core.envmap import resize_envmap, rotate_envmap
    from core.priors.reprojection import ReprojectionPrior

    cfg = preset(rp.PRESET)
    base = dict(cfg.priors.get("reprojection", {}))
    out = []
    for photo in rp.protocol_photos(hdri, split, views, cfg.distill.work_height, curve):
        prior = ReprojectionPrior(**base)
        prior.bind(photo["work"])
        out.append(
            {
                "name": photo["name"],
                "env": prior.envmaps(torch.zeros(1, 3), 0.0, rp.GT_HEIGHT)[0].double(),
                "gt": rotate_envmap(resize_envmap(photo["pano"], rp.GT_HEIGHT), photo["rotation"].T).double(),
                "seen": observed_directions(
                    Camera(photo["intrinsics"], torch.eye(4, dtype=torch.float64)), rp.GT_HEIGHT
                ),
                "const": rp.estimate_mean_colour(photo["ldr"], photo["curve"]).double(),
                "curve": photo["curve"].name,
            }
        )
    return out


class ShapeBasis:
    """Band-2 SH on an equirect grid: per-pixel values, per-cell integrals and solid angles."""

    def __init__(self, height: int):
        from core.conventions import equirect_directions
        from core.envmap import solid_angles
        from core.sh import pixel_basis_integrals, sh_basis

        self.Y = sh_basis(equirect_directions(height, dtype=torch.float64))  # [h, w, 9]
        self.cells = pixel_basis_integrals(height).double()  # [h, w, 9]
        self.area = solid_angles(height, dtype=torch.float64)

    def mean(self, lum: torch.Tensor, region: torch.Tensor) -> torch.Tensor:
        return (lum * self.area * region).sum() / (self.area * region).sum()

    def moments(self, lum: torch.Tensor, region: torch.Tensor) -> torch.Tensor:
        return torch.einsum("hwk,hw->k", self.cells, lum * region) / (
            self.mean(lum, region) * (self.area * region).sum()
        )

    def fit(self, lum: torch.Tensor, region: torch.Tensor, bands: int = 3) -> torch.Tensor:
        """Solid-angle-weighted least-squares SH coefficients [9] of `lum` over `region`, with
        `bands` bands (1: the constant, 2: and the dipole, 3: band 2 too; the rest zero)."""
        k = bands * bands
        w = self.area[region].sqrt()
        c = torch.linalg.lstsq(self.Y[region][:, :k] * w[:, None], (lum[region] * w)[:, None]).solution[:, 0]
        return torch.cat([c, torch.zeros(9 - k, dtype=c.dtype)])


def table(basis: ShapeBasis, data: list[dict], features: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(features [N, k], targets [N, 9], the prior's mean seen luminance [N])."""
    from core.exposure import luminance

    X, T, M = [], [], []
    for p in data:
        seen = p["seen"]
        lum, truth = luminance(p["env"]), luminance(p["gt"])
        m = basis.mean(lum, seen)
        parts = {"moments": basis.moments(lum, seen), "fill": basis.fit(lum / m, ~seen)}
        X.append(torch.cat([parts[k] for k in (("moments", "fill") if features == "both" else (features,))]))
        T.append(basis.fit(truth / basis.mean(truth, seen), ~seen))
        M.append(m)
    return torch.stack(X), torch.stack(T), torch.stack(M)


def ridge(X: torch.Tensor, T: torch.Tensor, lam: float) -> torch.Tensor:
    Xa = torch.cat([X, torch.ones(len(X), 1, dtype=X.dtype)], 1)
    reg = lam * torch.eye(Xa.shape[1], dtype=X.dtype)
    reg[-1, -1] = 0.0  # the intercept is not penalised
    return torch.linalg.solve(Xa.T @ Xa + reg, Xa.T @ T)


def leave_one_out(train, evaluate, Xtr, Ttr, Xev, lam: float) -> torch.Tensor:
    """Each evaluated photo's predicted targets from a ridge fitted without its panorama."""
    pred = torch.zeros(len(evaluate), Ttr.shape[1], dtype=Ttr.dtype)
    names_tr = [p["name"] for p in train]
    for name in sorted({p["name"] for p in evaluate}):
        keep = torch.tensor([n != name for n in names_tr])
        W = ridge(Xtr[keep], Ttr[keep], lam)
        idx = torch.tensor([p["name"] == name for p in evaluate])
        pred[idx] = torch.cat([Xev[idx], torch.ones(int(idx.sum()), 1, dtype=Xev.dtype)], 1) @ W
    return pred


def main(argv=None) -> int:
    from bench.panoramas import DEFAULT_HDRI_DIR
    from bench.suite.evaluation import score_probe
    from core.exposure import luminance
    from core.sim.camera_curves import add_curve_argument

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hdri-dir", default=str(DEFAULT_HDRI_DIR))
    p.add_argument("--train-views", type=int, default=12, help="photos per dev panorama to fit on")
    p.add_argument("--views", type=int, default=4, help="the protocol's photos per dev panorama to score")
    p.add_argument("--features", default="moments,fill", help=f"comma-separated, of {FEATURES}")
    p.add_argument("--lambdas", default="1e9,10,1,0.1")
    p.add_argument("-o", "--output", default=None)
    add_curve_argument(p, allow_all=False)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    hdri = Path(args.hdri_dir)
    lambdas = [float(v) for v in args.lambdas.split(",")]
    train, evaluate = photos(hdri, "dev", args.train_views, args.curve), photos(hdri, "dev", args.views, args.curve)
    import bench.real_panoramas as rp

    basis = ShapeBasis(rp.GT_HEIGHT)
    preds: dict[str, torch.Tensor] = {}
    r2: dict[str, float] = {}
    for features in args.features.split(","):
        Xtr, Ttr, _ = table(basis, train, features)
        Xev, Tev, Mev = table(basis, evaluate, features)  # targets and levels do not depend on the features
        for lam in lambdas:
            key = f"{features}, ridge {lam:g}"
            preds[key] = leave_one_out(train, evaluate, Xtr, Ttr, Xev, lam)
            r2[key] = round(float(1 - ((preds[key] - Tev) ** 2).sum() / ((Tev - Tev.mean(0)) ** 2).sum()), 4)
    preds["oracle"] = Tev
    preds["oracle, band 1 only"] = torch.stack(
        [
            basis.fit(luminance(q["gt"]) / basis.mean(luminance(q["gt"]), q["seen"]), ~q["seen"], bands=2)
            for q in evaluate
        ]
    )
    preds["fill-sh"] = torch.stack([basis.fit(luminance(q["env"]) / m, ~q["seen"]) for q, m in zip(evaluate, Mev)])
    scores: dict[str, list] = {}
    for i, photo in enumerate(evaluate):
        env, seen = photo["env"], photo["seen"][..., None]
        colour = env / luminance(env).clamp_min(1e-12)[..., None]
        maps = {"prior": env, "mean-colour": photo["const"]}
        for key, P in preds.items():
            lum = ((basis.Y @ P[i]) * Mev[i]).clamp_min(FLOOR * float(Mev[i]))
            maps[key] = torch.where(seen, env, lum[..., None] * colour)
        truth = luminance(photo["gt"]) / basis.mean(luminance(photo["gt"]), photo["seen"]) * Mev[i]
        unseen = (~photo["seen"]).double()
        # the unseen part of each row
        rows = (truth * unseen).sum(1, keepdim=True) / unseen.sum(1, keepdim=True).clamp_min(1)
        maps["oracle, row means only"] = torch.where(seen, env, rows.expand_as(truth)[..., None] * colour)
        for key, s in score_probe(maps, photo["gt"], 64).items():
            scores.setdefault(key, []).append(
                [s["diffuse"]["si_rmse_rel"], s["diffuse"]["angular_deg"], s["matte"]["si_rmse_rel"]]
            )
    const = torch.tensor(scores["mean-colour"]).mean(0)
    rows = {k: [round(float(v), 3) for v in torch.tensor(s).mean(0) / const] for k, s in scores.items()}
    print(
        f"dev, {len(evaluate)} photos (leave one panorama out; fitted on {len(train)}), prior at the camera "
        "(shortcut):\n"
    )
    print(
        "| variant | target R² | diffuse si-RMSE vs const | diffuse ang vs const | matte si-RMSE vs const "
        "|\n|---|---|---|---|---|"
    )
    for k, v in rows.items():
        print(f"| {k} | {r2.get(k, '–')} | {v[0]:.3f} | {v[1]:.3f} | {v[2]:.3f} |")
    if args.output:
        Path(args.output).parent.mkdir(parents=True, exist_ok=True)
        Path(args.output).write_text(
            json.dumps(
                {
                    "curve": args.curve,
                    "photo_curves": [[q["name"], q["curve"]] for q in evaluate],
                    "train_photos": len(train),
                    "photos": len(evaluate),
                    "floor": FLOOR,
                    "target_r2": r2,
                    "vs_constant": rows,
                    "columns": ["diffuse_si_rmse_rel", "diffuse_angular_deg", "matte_si_rmse_rel"],
                },
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
