"""The conventions of core.conventions, checked against their documented meaning."""
import math

import pytest
import torch
from hypothesis import given, settings, strategies as st

from core.conventions import (
    direction_to_equirect_pixel,
    direction_to_theta_phi,
    equirect_directions,
    inverse_tonemap,
    theta_phi_to_direction,
    tonemap,
    valid_depth_mask,
)


@pytest.mark.parametrize("height", [1, 2, 3, 8, 33])
def test_every_pixel_centre_round_trips_to_its_pixel(height):
    d = equirect_directions(height, dtype=torch.float64)
    row, col = direction_to_equirect_pixel(d, height)
    rows = torch.arange(height, dtype=torch.float64)[:, None].expand_as(row)
    cols = torch.arange(2 * height, dtype=torch.float64)[None, :].expand_as(col)
    assert torch.allclose(row, rows, atol=1e-9)
    assert torch.allclose(col, cols, atol=1e-9)


def test_directions_are_unit():
    d = equirect_directions(16, dtype=torch.float64)
    assert torch.allclose(d.norm(dim=-1), torch.ones(16, 32, dtype=torch.float64))


def test_image_centre_is_forward_right_is_plus_x_top_is_up():
    h = 64
    # The exact image centre lies on a pixel corner: the direction there is -z.
    row, col = direction_to_equirect_pixel(torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64), h)
    assert float(row) == pytest.approx((h - 1) / 2) and float(col) == pytest.approx((2 * h - 1) / 2)
    d = equirect_directions(h, dtype=torch.float64)
    # three quarters across the width (right of centre) looks along +x at the horizon
    right = d[h // 2 - 1 : h // 2 + 1, 3 * h // 2 - 1 : 3 * h // 2 + 1].mean(dim=(0, 1))
    assert torch.allclose(right / right.norm(), torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), atol=1e-9)
    # the top row points up, the bottom row down, within half a pixel of the pole
    assert (d[0, :, 1] > math.cos(math.pi / h)).all()
    assert (d[-1, :, 1] < -math.cos(math.pi / h)).all()
    # left edge / right edge are +z (behind), the seam
    assert (d[h // 2, 0, 2] > 0.99) and (d[h // 2, -1, 2] > 0.99)


@settings(max_examples=200, deadline=None)
@given(st.floats(0.0, math.pi), st.floats(-math.pi, math.pi, exclude_min=True))
def test_theta_phi_round_trip(theta, phi):
    d = theta_phi_to_direction(torch.tensor(theta, dtype=torch.float64), torch.tensor(phi, dtype=torch.float64))
    t2, p2 = direction_to_theta_phi(d)
    assert float(t2) == pytest.approx(theta, abs=1e-9)
    if 1e-6 < theta < math.pi - 1e-6:  # phi is arbitrary at the poles
        dphi = (float(p2) - phi + math.pi) % (2 * math.pi) - math.pi
        assert abs(dphi) < 1e-7


@settings(max_examples=200, deadline=None)
@given(st.floats(1e-4, 1.0), st.floats(-10.0, 5.0))
def test_tonemap_inverse_round_trip_unclipped(ldr, ev):
    """For any unclipped LDR value and ev in [-10, 5], inverse then forward is the identity."""
    ldr_t = torch.tensor(ldr, dtype=torch.float64)
    radiance = inverse_tonemap(ldr_t, ev)
    assert float(tonemap(radiance, ev)) == pytest.approx(ldr, rel=1e-9)
    # and the documented formula
    assert float(radiance) == pytest.approx(ldr**2.4 / 2.0**ev, rel=1e-9)


@pytest.mark.parametrize("ev", [-10.0, -2.5, 0.0, 5.0])
def test_tonemap_extremes_are_finite_and_clipped(ev):
    x = torch.tensor([1e-6, 1e6, 0.0, -1.0, float("inf"), float("nan")])
    y = tonemap(x, ev)
    assert torch.isfinite(y).all()
    assert ((y >= 0) & (y <= 1)).all()
    assert float(y[1]) == 1.0 or ev < -19  # 1e6 saturates for every ev here
    assert float(y[0]) == pytest.approx((1e-6 * 2.0**ev) ** (1 / 2.4), rel=1e-4)
    assert float(y[2]) == 0.0 and float(y[3]) == 0.0


def test_tonemap_is_monotonic():
    x = torch.logspace(-6, 6, 1000, dtype=torch.float64)
    y = tonemap(x, -2.0)
    assert (y[1:] >= y[:-1]).all()


def test_valid_depth_mask():
    depth = torch.tensor([0.0, float("nan"), float("inf"), -float("inf"), -1.0, 1e-6, 2.5])
    assert valid_depth_mask(depth).tolist() == [False, False, False, False, False, True, True]


def test_poles_have_phi_zero_and_finite_gradients():
    d = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 2.0, -0.0], [0.0, 0.0, 0.0]], requires_grad=True)
    theta, phi = direction_to_theta_phi(d)
    assert phi.tolist() == [0.0, 0.0, 0.0, 0.0]
    assert theta.tolist() == pytest.approx([0.0, math.pi, 0.0, 0.0])
    (theta.sum() + phi.sum()).backward()
    assert torch.isfinite(d.grad).all()
