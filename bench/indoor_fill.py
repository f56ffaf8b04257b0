"""Fit core.priors.indoor_fill.ELEVATION_GAIN on the `dev` panoramas (never test/control).

    python -m bench.indoor_fill [--hdri-dir DIR]             # fit, print the table
    python -m bench.indoor_fill --ablation [--split dev]       # the prior's fill/clip variants

Per panorama (area-downsampled to GAIN_ROWS rows, +y up as stored): log of each row's mean
luminance over the mean luminance within +-HORIZON_BAND_DEG of the horizon; averaged over
the dev panoramas and exponentiated. Prints the tuple to paste into core/priors/indoor_fill.py.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch


def row_profile(pano: torch.Tensor, rows: int, band_deg: float) -> torch.Tensor:
    from core.envmap import resize_envmap
    from core.exposure import luminance

    y = luminance(resize_envmap(pano.double(), rows)).mean(1)
    elev = 90.0 - (torch.arange(rows, dtype=torch.float64) + 0.5) * 180.0 / rows
    band = elev.abs() <= band_deg
    return torch.log(y.clamp_min(1e-12) / y[band].mean())


def smooth(log_gain: torch.Tensor, sigma_rows: float) -> torch.Tensor:
    """Gaussian smoothing over rows (reflected at the poles): a gradient, not 24 free steps
    (steps would read as structure the photo never showed, and overfit 13 panoramas)."""
    if sigma_rows <= 0:
        return log_gain
    r = int(math.ceil(3 * sigma_rows))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float64) / sigma_rows) ** 2)
    padded = torch.nn.functional.pad(log_gain[None, None], (r, r), mode="reflect")[0, 0]
    return torch.nn.functional.conv1d(padded[None, None], (k / k.sum())[None, None])[0, 0]


def fit_gain(paths: list[Path], sigma_rows: float | None = None) -> list[float]:
    from bench.real_panoramas import load_panorama
    from core.priors.indoor_fill import GAIN_ROWS, GAIN_SMOOTHING_ROWS, HORIZON_BAND_DEG

    logs = torch.stack([row_profile(load_panorama(p), GAIN_ROWS, HORIZON_BAND_DEG) for p in paths])
    mean = smooth(logs.mean(0), GAIN_SMOOTHING_ROWS if sigma_rows is None else sigma_rows)
    return [round(math.exp(v), 3) for v in mean.tolist()]


ABLATION = {
    "pull-push, fixed 8x": {"unseen_fill": "push-pull", "clip_rule": "fixed"},
    "pull-push, clip rule": {"unseen_fill": "push-pull"},
    "indoor fill, fixed 8x": {"clip_rule": "fixed"},
    "indoor fill, clip rule (default)": {},
}


def ablation(hdri: Path, split: str) -> list[str]:
    """The reprojection prior alone at the camera centre, draft settings (24-row maps, frames
    at 72 rows), per fill/clip variant, on the panorama protocol: mean ratios to the constant map."""
    import tempfile

    import bench.real_panoramas as rp
    from bench.suite.evaluation import score_probe
    from core.camera import Camera
    from core.capture.load import load_capture
    from core.conventions import inverse_tonemap
    from core.engine.presets import preset
    from core.envmap import resize_envmap, rotate_envmap
    from core.metrics import observed_region_correlation
    from core.priors.reprojection import ReprojectionPrior

    cfg = preset(rp.PRESET)
    base = dict(cfg.priors.get("reprojection", {}))
    files = sorted(r["filename"] for r in rp.read_manifest(hdri) if r.get("split") == split and (hdri / r["filename"]).is_file())
    acc: dict = {k: [] for k in [*ABLATION, "mean-colour"]}
    with tempfile.TemporaryDirectory() as tmp:
        for f in files:
            pano = rp.load_panorama(hdri / f)
            R = rp.camera_rotation(*rp.view_for(f))
            hdr, intr = rp.perspective_crop(pano, R)
            ldr = rp.ldr_photo(hdr)
            work = load_capture(rp.write_photo(ldr, Path(tmp) / f"{f}.png"), None, rp.job_params(), track=False).resized(cfg.distill.work_height)
            preds = {}
            for name, settings in ABLATION.items():
                prior = ReprojectionPrior(**{**base, **settings})
                prior.bind(work)
                preds[name] = prior.envmaps(torch.zeros(1, 3), 0.0, rp.GT_HEIGHT)[0]
            preds["mean-colour"] = rp.estimate_mean_colour(ldr)
            scores = score_probe(preds, rotate_envmap(resize_envmap(pano, rp.GT_HEIGHT), R.T), 64)
            rays = Camera(intr, torch.eye(4, dtype=torch.float64)).pixel_rays(dtype=torch.float64)[1]
            for name, env in preds.items():
                acc[name].append((scores[name]["diffuse"]["si_rmse_rel"], scores[name]["diffuse"]["angular_deg"],
                                  observed_region_correlation(env, inverse_tonemap(ldr), rays)))
    const = acc["mean-colour"]
    mean = lambda rows, i: sum(r[i] for r in rows) / len(rows)  # noqa: E731
    lines = [f"{split}, {len(files)} panoramas, prior at the camera (shortcut, not the product):", "",
             "| variant | diffuse si-RMSE vs const | diffuse ang vs const | observed corr. |", "|---|---|---|---|"]
    for name, rows in acc.items():
        lines.append(f"| {name} | {mean(rows, 0) / mean(const, 0):.3f} | {mean(rows, 1) / mean(const, 1):.3f} | {mean(rows, 2):.3f} |")
    return lines


def main(argv=None) -> int:
    from bench.real_panoramas import read_manifest
    from bench.run import DEFAULT_HDRI_DIR

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hdri-dir", default=str(DEFAULT_HDRI_DIR))
    p.add_argument("--ablation", action="store_true", help="score the prior's fill/clip variants instead of fitting")
    p.add_argument("--split", default="dev", help="split for --ablation (tune on dev only)")
    args = p.parse_args(argv)
    hdri = Path(args.hdri_dir)
    torch.set_num_threads(1)
    if args.ablation:
        print("\n".join(ablation(hdri, args.split)))
        return 0
    dev = [hdri / r["filename"] for r in read_manifest(hdri) if r.get("split") == "dev" and (hdri / r["filename"]).is_file()]
    gain = fit_gain(sorted(dev))
    print(f"# {len(dev)} dev panoramas\nELEVATION_GAIN = {tuple(gain)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
