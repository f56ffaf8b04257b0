"""bench.calibration.indoor_fill: the elevation profile's fit (arithmetic vs geometric mean over panoramas)."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from bench.calibration.indoor_fill import gain_from_profiles, mean_log_profile, row_profile
from bench.panoramas import DEFAULT_HDRI_DIR


def test_arithmetic_mean_keeps_the_energy_a_few_bright_panoramas_carry():
    # two panoramas: one flat, one with a band 9x the horizon's (a row of lamps)
    profiles = torch.tensor([[1.0, 1.0], [9.0, 1.0]], dtype=torch.float64)
    arithmetic = mean_log_profile(profiles, "arithmetic").exp()
    geometric = mean_log_profile(profiles, "geometric").exp()
    assert arithmetic.tolist() == pytest.approx([5.0, 1.0])
    assert geometric.tolist() == pytest.approx([3.0, 1.0])
    with pytest.raises(ValueError, match="average"):
        mean_log_profile(profiles, "median")


def test_gain_from_profiles_without_smoothing_is_the_mean():
    profiles = torch.tensor([[2.0, 1.0, 0.5], [4.0, 1.0, 0.5]], dtype=torch.float64)
    assert gain_from_profiles(profiles, "arithmetic", sigma_rows=0) == pytest.approx([3.0, 1.0, 0.5])
    assert gain_from_profiles(profiles, "geometric", sigma_rows=0) == pytest.approx(
        [math.sqrt(8.0), 1.0, 0.5], abs=1e-3
    )


def test_row_profile_is_relative_to_the_horizon_band():
    h = 24
    pano = torch.ones(h, 2 * h, 3, dtype=torch.float64)
    assert torch.allclose(row_profile(pano, h, 25.0), torch.ones(h, dtype=torch.float64))
    pano[:2] = 10.0  # a bright ceiling band (rows 0-1 = up, well outside +-25 deg)
    prof = row_profile(pano, h, 25.0)
    assert float(prof[0]) == pytest.approx(10.0) and float(prof[h // 2]) == pytest.approx(1.0)


DEV = Path(DEFAULT_HDRI_DIR)


@pytest.mark.skipif(
    not (DEV / "MANIFEST.tsv").is_file(), reason="the dev panoramas (../shared/hdri) are not on this machine"
)
def test_the_stored_gain_is_the_fit_on_every_indoor_room():
    from bench.calibration.indoor_fill import fit_gain
    from bench.panoramas import indoor_rooms, read_manifest
    from core.priors.indoor_fill import ELEVATION_GAIN

    rooms = indoor_rooms(DEV)
    split = {r["filename"]: r["split"] for r in read_manifest(DEV)}
    assert len(rooms) == 24 and {split[p.name] for p in rooms} == {"dev", "test", "extra"}
    assert tuple(fit_gain(rooms)) == pytest.approx(ELEVATION_GAIN, abs=2e-3)
