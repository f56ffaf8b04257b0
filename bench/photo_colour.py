"""What decides a single photo's diffuse angle? The prior's map with one part swapped at a time.

    python -m bench.photo_colour [--hdri-dir DIR] [--limit N] [-o out.json]

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
and diffuse angle, over the rooms.
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


def evaluate(path: Path, overrides: dict, workdir: Path, sphere_size: int = 64) -> dict:
    """One room's photo: per variant, diffuse si-RMSE and angle, and the constant map's."""
    import bench.real_panoramas as rp
    from bench.suite.evaluation import score_probe
    from core.camera import Camera
    from core.engine.extrapolation import observed_directions
    from core.envmap import resize_envmap, rotate_envmap

    pano = rp.load_panorama(path)
    R = rp.camera_rotation(*rp.view_for(path.name, 0, 1))
    hdr, intr = rp.perspective_crop(pano, R)
    ldr = rp.ldr_photo(hdr)
    photo = rp.write_photo(ldr, workdir / (path.stem + ".png"))
    truth = rotate_envmap(resize_envmap(pano, rp.GT_HEIGHT), R.T).double()
    constant = rp.estimate_mean_colour(ldr).double()
    seen = observed_directions(Camera(intr, torch.eye(4, dtype=torch.float64)), rp.GT_HEIGHT)  # the photo's camera
    preds = variants(rp.estimate_prior(photo, overrides).double(), constant, truth, seen)
    scores = score_probe({**preds, rp.CONSTANT: constant}, truth, sphere_size)
    return {name: {k: s["diffuse"][k] for k in ("si_rmse_rel", "angular_deg")} for name, s in scores.items()}


def summarise(rows: dict[str, dict]) -> dict:
    """Per variant: its summed error over the constant map's, over the rooms."""
    from bench.real_panoramas import CONSTANT

    names = [n for n in next(iter(rows.values())) if n != CONSTANT]
    return {n: {k: round(sum(r[n][k] for r in rows.values()) / sum(r[CONSTANT][k] for r in rows.values()), 4)
                for k in ("si_rmse_rel", "angular_deg")} for n in names}


def main(argv=None) -> int:
    from bench.real_panoramas import DEFAULT_HDRI_DIR, indoor_rooms
    from bench.room_scans import DEFAULT_REFIT, cv_overrides

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hdri-dir", default=str(DEFAULT_HDRI_DIR))
    p.add_argument("--limit", type=int, default=None)
    p.add_argument("-o", "--out", default=None)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    hdri = Path(args.hdri_dir)
    overrides_for = cv_overrides(hdri, DEFAULT_REFIT)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for path in indoor_rooms(hdri, args.limit):
            rows[path.name] = evaluate(path, overrides_for(path.name), Path(tmp))
            print(path.name, json.dumps({n: round(v["angular_deg"], 2) for n, v in rows[path.name].items()}),
                  file=sys.stderr, flush=True)
    report = {"command": "python -m bench.photo_colour " + " ".join(sys.argv[1:] if argv is None else argv),
              "protocol": __doc__, "vs_constant": summarise(rows), "rooms": rows}
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1))
    print(json.dumps(report["vs_constant"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
