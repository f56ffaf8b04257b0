"""What decides a single photo's diffuse angle? The prior's map with one part swapped at a time.

    python -m bench.photo_colour [--hdri-dir DIR] [--limit N] [--curve drawn|NAME|all] [-o out.json]

The real-panorama protocol (bench.real_panoramas: one 60° photo per indoor room, each job with
its fold's settings as in the room-scan bench, `bench.room_scans.cv_overrides`), scored with the
prior shortcut (the job's prior queried at the camera; its diffuse angle equals the field's
under CV). Besides the prior's map, each photo scores `variants` of it (SHORTCUTS, not
methods: the truth is used to build some of them):
* `fill xN`            the unseen directions N times brighter (is it the fill's level?)
* `seen exact`         the seen directions replaced by the truth at the map's scale (is it
                       what the photo shows, clipped lamps included?)
* `unseen in constant colour`  the unseen directions in the constant map's colour at the
                       map's luminance (the fill's colour as the photo's plain mean)
* `unseen in true colour`      the same in the truth's chromaticity (an oracle)
Ratios are the variant's mean error over the constant map's (< 1 beats it), diffuse si-RMSE
and diffuse angle, over the rooms; per camera curve too (`--curve`, core.sim.camera_curves:
each photo's camera as bench.real_panoramas draws it, a name, or all of them).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import torch

from core.exposure import chromaticity, luminance

FILL_SCALES = (2.0, 6.0)


def variants(prior: torch.Tensor, constant: torch.Tensor, truth: torch.Tensor, seen: torch.Tensor) -> dict:
    """The prior's map [H, W, 3] and the variants of the module docstring (seen: [H, W] bool)."""
    lum, true_lum = luminance(prior), luminance(truth)
    ok = seen & (true_lum > 0)
    scale = float((lum[ok] / true_lum[ok]).median()) if bool(ok.any()) else 1.0  # the map's units per truth's
    s = seen[..., None]
    out = {"prior": prior}
    out.update({f"fill x{f:g}": torch.where(s, prior, f * prior) for f in FILL_SCALES})
    out["seen exact"] = torch.where(s, scale * truth, prior)
    out["unseen in constant colour"] = torch.where(s, prior, lum[..., None] * chromaticity(constant.reshape(-1, 3)[0]))
    out["unseen in true colour"] = torch.where(s, prior, lum[..., None] * chromaticity(truth))
    return out


def evaluate(path: Path, overrides: dict, workdir: Path, sphere_size: int = 64, curve: str = "drawn") -> dict:
    """One room's photo (its camera: bench.real_panoramas.photo_curve of `curve`): per variant,
    diffuse si-RMSE and angle, and the constant map's."""
    import bench.real_panoramas as rp
    from bench.suite.evaluation import score_probe
    from core.camera import Camera
    from core.engine.extrapolation import observed_directions
    from core.envmap import resize_envmap, rotate_envmap

    pano = rp.load_panorama(path)
    R = rp.camera_rotation(*rp.view_for(path.name, 0, 1))
    hdr, intr = rp.perspective_crop(pano, R)
    cam = rp.photo_curve(path.name, 0, curve)
    ldr = rp.ldr_photo(hdr, cam)
    photo = rp.write_photo(ldr, workdir / f"{path.stem}_{cam.name}.png", cam)
    truth = rotate_envmap(resize_envmap(pano, rp.GT_HEIGHT), R.T).double()
    constant = rp.estimate_mean_colour(ldr, cam).double()
    seen = observed_directions(Camera(intr, torch.eye(4, dtype=torch.float64)), rp.GT_HEIGHT)  # the photo's camera
    preds = variants(rp.estimate_prior(photo, overrides, cam).double(), constant, truth, seen)
    scores = score_probe({**preds, rp.CONSTANT: constant}, truth, sphere_size)
    return {name: {k: s["diffuse"][k] for k in ("si_rmse_rel", "angular_deg")} for name, s in scores.items()}


def summarise(rows: dict[str, dict]) -> dict:
    """Per variant: its summed error over the constant map's, over the rooms."""
    from bench.real_panoramas import CONSTANT

    names = [n for n in next(iter(rows.values())) if n != CONSTANT]
    return {n: {k: round(sum(r[n][k] for r in rows.values()) / sum(r[CONSTANT][k] for r in rows.values()), 4)
                for k in ("si_rmse_rel", "angular_deg")} for n in names}


def main(argv=None) -> int:
    import bench.real_panoramas as rp
    from bench.panoramas import DEFAULT_HDRI_DIR, indoor_rooms
    from bench.room_scans import DEFAULT_REFIT, cv_overrides
    from core.sim.camera_curves import ALL, REFERENCE, STILL, add_curve_argument, group_by_curve, run_choices

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hdri-dir", default=str(DEFAULT_HDRI_DIR))
    p.add_argument("--limit", type=int, default=None)
    p.add_argument("-o", "--out", default=None)
    add_curve_argument(p)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    hdri = Path(args.hdri_dir)
    overrides_for = cv_overrides(hdri, DEFAULT_REFIT)
    rows, curves = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for path in indoor_rooms(hdri, args.limit):
            for choice in run_choices(args.curve, STILL):
                key = path.name if args.curve != ALL else f"{path.name} · {choice}"
                curves[key] = rp.photo_curve(path.name, 0, choice).name
                rows[key] = evaluate(path, overrides_for(path.name), Path(tmp), curve=choice)
                print(key, curves[key], json.dumps({n: round(v["angular_deg"], 2) for n, v in rows[key].items()}),
                      file=sys.stderr, flush=True)
    per_curve = group_by_curve([{"key": k, "curve": c} for k, c in curves.items()],
                               lambda items: summarise({i["key"]: rows[i["key"]] for i in items}))
    report = {"command": "python -m bench.photo_colour " + " ".join(sys.argv[1:] if argv is None else argv),
              "protocol": __doc__, "curve": args.curve,
              # over the realistic cameras (the reference only when it alone was run)
              "vs_constant": summarise({k: rows[k] for k, c in curves.items() if c != REFERENCE} or rows),
              "vs_constant_per_curve": per_curve, "curves": curves, "rooms": rows}
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1))
    print(json.dumps(report["vs_constant"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
