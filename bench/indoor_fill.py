"""Fit core.priors.indoor_fill.ELEVATION_GAIN on the `dev` panoramas (never test/control).

    python -m bench.indoor_fill [--hdri-dir DIR] [--average arithmetic|geometric]  # fit, print the table
    python -m bench.indoor_fill --ablation [--split dev]       # the prior's fill/clip variants
    python -m bench.indoor_fill --leave-one-out [--average ...]  # each dev panorama with the others' profile

Per panorama (area-downsampled to GAIN_ROWS rows, +y up as stored): each row's mean luminance
over the mean luminance within +-HORIZON_BAND_DEG of the horizon; averaged over the dev
panoramas (arithmetically, the default: the expected radiance, which is what a diffuse
render integrates; `geometric`: the mean of the logs, the first fit, which a few bright
sources barely move) and smoothed in log over rows. Prints the tuple to paste into
core/priors/indoor_fill.py.
"""
from __future__ import annotations

import argparse
import math
from contextlib import contextmanager
from pathlib import Path

import torch


AVERAGES = ("arithmetic", "geometric")


def row_profile(pano: torch.Tensor, rows: int, band_deg: float) -> torch.Tensor:
    """Each row's mean luminance over the horizon band's (linear ratios)."""
    from core.conventions import equirect_pixel_centres
    from core.envmap import resize_envmap
    from core.exposure import luminance

    y = luminance(resize_envmap(pano.double(), rows)).mean(1)
    theta, _ = equirect_pixel_centres(rows, dtype=torch.float64)  # polar angle from up (+y)
    band = (90.0 - torch.rad2deg(theta[:, 0])).abs() <= band_deg
    return y.clamp_min(1e-12) / y[band].mean()


def mean_log_profile(profiles: torch.Tensor, average: str) -> torch.Tensor:
    """The log of the panoramas' profiles [P, rows] averaged as `average` says."""
    if average == "arithmetic":
        return profiles.mean(0).log()
    if average == "geometric":
        return profiles.log().mean(0)
    raise ValueError(f"average must be one of {AVERAGES}, got {average!r}")


def smooth(log_gain: torch.Tensor, sigma_rows: float) -> torch.Tensor:
    """Gaussian smoothing over rows (reflected at the poles): a gradient, not 24 free steps
    (steps would read as structure the photo never showed, and overfit 13 panoramas)."""
    if sigma_rows <= 0:
        return log_gain
    r = int(math.ceil(3 * sigma_rows))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float64) / sigma_rows) ** 2)
    padded = torch.nn.functional.pad(log_gain[None, None], (r, r), mode="reflect")[0, 0]
    return torch.nn.functional.conv1d(padded[None, None], (k / k.sum())[None, None])[0, 0]


def panorama_profiles(paths: list[Path]) -> torch.Tensor:
    from bench.real_panoramas import load_panorama
    from core.priors.indoor_fill import GAIN_ROWS, HORIZON_BAND_DEG

    return torch.stack([row_profile(load_panorama(p), GAIN_ROWS, HORIZON_BAND_DEG) for p in paths])


def gain_from_profiles(profiles: torch.Tensor, average: str = "arithmetic", sigma_rows: float | None = None) -> list[float]:
    from core.priors.indoor_fill import GAIN_SMOOTHING_ROWS

    mean = smooth(mean_log_profile(profiles, average), GAIN_SMOOTHING_ROWS if sigma_rows is None else sigma_rows)
    return [round(math.exp(v), 3) for v in mean.tolist()]


def fit_gain(paths: list[Path], sigma_rows: float | None = None, average: str = "arithmetic") -> list[float]:
    return gain_from_profiles(panorama_profiles(paths), average, sigma_rows)


ABLATION = {
    "pull-push, fixed 8x": {"unseen_fill": "push-pull", "clip_rule": "fixed"},
    "pull-push, clip rule": {"unseen_fill": "push-pull"},
    "indoor fill, fixed 8x": {"clip_rule": "fixed"},
    "indoor fill, clip rule, no source cap": {"fill_source_cap": None},
    "indoor fill, clip rule, source cap 1x": {"fill_source_cap": 1.0},
    "indoor fill, clip rule, source cap 2x (default)": {},
    "indoor fill, clip rule, source cap 4x": {"fill_source_cap": 4.0},
    "indoor fill, clip rule, source cap 8x": {"fill_source_cap": 8.0},
}


@contextmanager
def elevation_gain_as(gain: tuple[float, ...] | None):
    """core.priors.indoor_fill.ELEVATION_GAIN replaced while the block runs (None: as it is)."""
    import core.priors.indoor_fill as fill

    kept = fill.ELEVATION_GAIN
    fill.ELEVATION_GAIN = kept if gain is None else tuple(gain)
    try:
        yield
    finally:
        fill.ELEVATION_GAIN = kept


def ablation(hdri: Path, split: str, variants: dict | None = None, gains: dict | None = None, views: int = 1) -> list[str]:
    """The reprojection prior alone at the camera centre, draft settings (24-row maps, frames
    at 72 rows), per fill/clip variant (`variants`, default ABLATION), on the panorama protocol:
    mean ratios to the constant map (diffuse si-RMSE and angle, matte si-RMSE). `gains` maps a
    panorama's file name to the elevation gain its prior uses (leave-one-out); else the module's.
    `views` photos per panorama (bench.real_panoramas.view_for)."""
    import bench.real_panoramas as rp
    from bench.suite.evaluation import score_probe
    from core.camera import Camera
    from core.conventions import inverse_tonemap
    from core.engine.presets import preset
    from core.envmap import resize_envmap, rotate_envmap
    from core.metrics import observed_region_correlation
    from core.priors.reprojection import ReprojectionPrior

    cfg = preset(rp.PRESET)
    base = dict(cfg.priors.get("reprojection", {}))
    variants = ABLATION if variants is None else variants
    acc: dict = {k: [] for k in [*variants, "mean-colour"]}
    names = set()
    for photo in rp.protocol_photos(hdri, split, views, cfg.distill.work_height):
        names.add(photo["name"])
        R, ldr = photo["rotation"], photo["ldr"]
        preds = {}
        with elevation_gain_as((gains or {}).get(photo["name"])):
            for name, settings in variants.items():
                prior = ReprojectionPrior(**{**base, **settings})
                prior.bind(photo["work"])
                preds[name] = prior.envmaps(torch.zeros(1, 3), 0.0, rp.GT_HEIGHT)[0]
        preds["mean-colour"] = rp.estimate_mean_colour(ldr)
        scores = score_probe(preds, rotate_envmap(resize_envmap(photo["pano"], rp.GT_HEIGHT), R.T), 64)
        rays = Camera(photo["intrinsics"], torch.eye(4, dtype=torch.float64)).pixel_rays(dtype=torch.float64)[1]
        for name, env in preds.items():
            acc[name].append((scores[name]["diffuse"]["si_rmse_rel"], scores[name]["diffuse"]["angular_deg"],
                              observed_region_correlation(env, inverse_tonemap(ldr), rays),
                              scores[name]["matte"]["si_rmse_rel"]))
    const = acc["mean-colour"]
    mean = lambda rows, i: sum(r[i] for r in rows) / len(rows)  # noqa: E731
    lines = [f"{split}, {len(names)} panoramas x {views} view(s), prior at the camera (shortcut, not the product):", "",
             "| variant | diffuse si-RMSE vs const | diffuse ang vs const | matte si-RMSE vs const | observed corr. |",
             "|---|---|---|---|---|"]
    for name, rows in acc.items():
        lines.append(f"| {name} | {mean(rows, 0) / mean(const, 0):.3f} | {mean(rows, 1) / mean(const, 1):.3f} "
                     f"| {mean(rows, 3) / mean(const, 3):.3f} | {mean(rows, 2):.3f} |")
    return lines


def main(argv=None) -> int:
    from bench.real_panoramas import read_manifest
    from bench.run import DEFAULT_HDRI_DIR

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hdri-dir", default=str(DEFAULT_HDRI_DIR))
    p.add_argument("--ablation", action="store_true", help="score the prior's fill/clip variants instead of fitting")
    p.add_argument("--split", default="dev", help="split for --ablation (tune on dev only)")
    p.add_argument("--views", type=int, default=1, help="photos per panorama for --ablation (bench.real_panoramas.view_for)")
    p.add_argument("--average", choices=AVERAGES, default="arithmetic", help="how the panoramas' profiles are averaged")
    p.add_argument("--leave-one-out", action="store_true",
                   help="score the default fill on each dev panorama with the profile fitted on the others")
    args = p.parse_args(argv)
    hdri = Path(args.hdri_dir)
    torch.set_num_threads(1)
    if args.ablation:
        print("\n".join(ablation(hdri, args.split, views=max(1, args.views))))
        return 0
    dev = sorted(hdri / r["filename"] for r in read_manifest(hdri) if r.get("split") == "dev" and (hdri / r["filename"]).is_file())
    if args.leave_one_out:
        profiles = panorama_profiles(dev)
        gains = {p.name: gain_from_profiles(torch.cat([profiles[:i], profiles[i + 1:]]), args.average) for i, p in enumerate(dev)}
        lines = ablation(hdri, "dev", {f"indoor fill, {args.average} profile of the other dev panoramas": {}}, gains)
        print("\n".join(lines))
        return 0
    gain = fit_gain(dev, average=args.average)
    print(f"# {len(dev)} dev panoramas, {args.average} mean\nELEVATION_GAIN = {tuple(gain)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
