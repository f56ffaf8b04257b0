"""Fit core.priors.indoor_fill.ELEVATION_GAIN on every indoor panorama (dev, test and extra of
MANIFEST.tsv; never `control`): what a user gets.

    python -m bench.calibration.indoor_fill [--hdri-dir DIR] [--average arithmetic|geometric]  # fit, print the tuple

Per panorama (area-downsampled to GAIN_ROWS rows, +y up as stored): each row's mean luminance
over the mean luminance within +-HORIZON_BAND_DEG of the horizon; averaged over the panoramas
(arithmetically, the default: the expected radiance, which is what a diffuse render
integrates; `geometric`: the mean of the logs, which a few bright sources barely move) and
smoothed in log over rows. Prints the tuple to paste into core/priors/indoor_fill.py. How well
it does on rooms it was not fitted on is measured by leave-one-room-out
(`python -m bench.real_panoramas --cv`, which refits it per fold with gain_from_profiles).
"""
from __future__ import annotations

import argparse
import math
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
    from bench.panoramas import load_panorama
    from core.priors.indoor_fill import GAIN_ROWS, HORIZON_BAND_DEG

    return torch.stack([row_profile(load_panorama(p), GAIN_ROWS, HORIZON_BAND_DEG) for p in paths])


def gain_from_profiles(
    profiles: torch.Tensor, average: str = "arithmetic", sigma_rows: float | None = None
) -> list[float]:
    from core.priors.indoor_fill import GAIN_SMOOTHING_ROWS

    mean = smooth(mean_log_profile(profiles, average), GAIN_SMOOTHING_ROWS if sigma_rows is None else sigma_rows)
    return [round(math.exp(v), 3) for v in mean.tolist()]


def fit_gain(paths: list[Path], sigma_rows: float | None = None, average: str = "arithmetic") -> list[float]:
    return gain_from_profiles(panorama_profiles(paths), average, sigma_rows)


def main(argv=None) -> int:
    from bench.panoramas import DEFAULT_HDRI_DIR, indoor_rooms

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hdri-dir", default=str(DEFAULT_HDRI_DIR))
    p.add_argument("--average", choices=AVERAGES, default="arithmetic", help="how the panoramas' profiles are averaged")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    rooms = indoor_rooms(Path(args.hdri_dir))
    gain = fit_gain(rooms, average=args.average)
    print(f"# {len(rooms)} indoor panoramas (dev, test, extra), {args.average} mean\nELEVATION_GAIN = {tuple(gain)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
