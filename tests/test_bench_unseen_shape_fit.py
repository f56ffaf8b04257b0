"""bench.unseen_shape_fit: the SH fit over a region, the ridge, and leave-one-panorama-out."""
from __future__ import annotations

import pytest
import torch

from bench.unseen_shape_fit import ShapeBasis, leave_one_out, ridge


def test_the_region_fit_recovers_a_band_2_map_from_part_of_the_sphere():
    basis = ShapeBasis(16)
    coeffs = torch.tensor([1.0, 0.3, -0.2, 0.1, 0.05, 0.0, -0.1, 0.02, 0.04], dtype=torch.float64)
    lum = basis.Y @ coeffs
    region = torch.zeros(16, 32, dtype=torch.bool)
    region[:, 8:] = True  # three quarters of the columns: the unseen part of a photo's sphere
    assert torch.allclose(basis.fit(lum, region), coeffs, atol=1e-9)
    # the mean is solid-angle weighted: a map bright only near a pole is not counted per row
    assert float(basis.mean(torch.ones(16, 32, dtype=torch.float64), region)) == pytest.approx(1.0)


def test_a_ridge_this_strong_is_the_intercept_alone():
    X = torch.randn(40, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    T = torch.randn(40, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    W = ridge(X, T, 1e12)
    assert torch.allclose(W[:-1], torch.zeros(3, 2, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(W[-1], T.mean(0), atol=1e-9)
    # no penalty: ordinary least squares, which fits a linear target exactly
    B = torch.tensor([[1.0], [-2.0], [0.5]], dtype=torch.float64)
    assert torch.allclose(ridge(X, X @ B + 3.0, 0.0)[:-1], B, atol=1e-9)


def test_a_panorama_is_never_predicted_from_its_own_photos():
    train = [{"name": n} for n in ("a", "a", "b", "b", "c", "c")]
    evaluate = [{"name": "a"}, {"name": "b"}]
    Xtr = torch.zeros(6, 1, dtype=torch.float64)
    Ttr = torch.tensor([[100.0], [100.0], [1.0], [1.0], [3.0], [3.0]], dtype=torch.float64)
    pred = leave_one_out(train, evaluate, Xtr, Ttr, torch.zeros(2, 1, dtype=torch.float64), 1.0)
    assert pred[:, 0].tolist() == pytest.approx([2.0, 51.5])  # a: mean of b and c; b: of a and c


def test_fewer_bands_leave_the_higher_coefficients_zero():
    basis = ShapeBasis(16)
    dipole = torch.tensor([1.0, 0.4, -0.3, 0.2, 0, 0, 0, 0, 0], dtype=torch.float64)
    region = torch.ones(16, 32, dtype=torch.bool)
    region[:, :6] = False
    c = basis.fit(basis.Y @ dipole, region, bands=2)
    assert torch.allclose(c, dipole, atol=1e-9)
    assert basis.fit(basis.Y @ dipole, region, bands=1)[1:].abs().max() == 0
