"""Fit core.priors.indoor_fill.ELEVATION_GAIN on the `dev` panoramas (never test/control).

    python -m bench.indoor_fill [--hdri-dir DIR]

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


def fit_gain(paths: list[Path]) -> list[float]:
    from bench.real_panoramas import load_panorama
    from core.priors.indoor_fill import GAIN_ROWS, HORIZON_BAND_DEG

    logs = torch.stack([row_profile(load_panorama(p), GAIN_ROWS, HORIZON_BAND_DEG) for p in paths])
    return [round(math.exp(v), 3) for v in logs.mean(0).tolist()]


def main(argv=None) -> int:
    from bench.real_panoramas import read_manifest
    from bench.run import DEFAULT_HDRI_DIR

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hdri-dir", default=str(DEFAULT_HDRI_DIR))
    args = p.parse_args(argv)
    hdri = Path(args.hdri_dir)
    dev = [hdri / r["filename"] for r in read_manifest(hdri) if r.get("split") == "dev" and (hdri / r["filename"]).is_file()]
    gain = fit_gain(sorted(dev))
    print(f"# {len(dev)} dev panoramas\nELEVATION_GAIN = {tuple(gain)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
