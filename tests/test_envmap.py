"""Env map geometry: solid angles, sampling at poles and seams, resizing, rotation."""
import math

import pytest
import torch
from hypothesis import given, settings, strategies as st

from core.conventions import equirect_directions, theta_phi_to_direction
from core.envmap import (
    EnvmapError,
    envmap_from_function,
    integrate,
    irradiance,
    mirror_envmap,
    resize_envmap,
    rotate_envmap,
    sample_envmap,
    solid_angles,
)


def smooth_map(height, dtype=torch.float32):
    """A smooth, non-symmetric positive test map."""

    def fn(d):
        x, y, z = d.unbind(-1)
        return torch.stack((1.0 + 0.5 * x + 0.2 * y * z, 1.0 + 0.3 * y, 1.2 - 0.4 * z + 0.1 * x * x), dim=-1)

    return envmap_from_function(fn, height, dtype=dtype)


@pytest.mark.parametrize("height", [1, 2, 3, 7, 64, 512])
def test_solid_angles_sum_to_4pi(height):
    w = solid_angles(height, dtype=torch.float64)
    assert w.shape == (height, 2 * height)
    assert float(w.sum()) == pytest.approx(4 * math.pi, rel=1e-12)
    assert (w > 0).all()


def test_solid_angles_match_a_band_area():
    """The rows of the top quarter of the sphere (theta < pi/4 for H = 4) cover 2 pi (1 - cos(pi/4))."""
    w = solid_angles(4, dtype=torch.float64)
    assert float(w[0].sum()) == pytest.approx(2 * math.pi * (1 - math.cos(math.pi / 4)), rel=1e-12)


def test_integrate_constant_and_cosine():
    c = torch.full((16, 32, 3), 2.0, dtype=torch.float64)
    assert torch.allclose(integrate(c), torch.full((3,), 8 * math.pi, dtype=torch.float64))
    # integral of max(0, y) over the sphere is pi; the midpoint rule converges as 1/H^2
    up = envmap_from_function(lambda d: d[..., 1].clamp_min(0), 256, dtype=torch.float64)
    assert float(integrate(up)[0]) == pytest.approx(math.pi, rel=1e-4)


def test_irradiance_of_uniform_map_is_pi_L():
    c = torch.full((32, 64, 3), 0.5, dtype=torch.float64)
    n = torch.tensor([[0.0, 1.0, 0.0], [0.6, 0.0, -0.8]], dtype=torch.float64)
    # kink at the horizon: midpoint rule
    assert torch.allclose(irradiance(c, n), torch.full((2, 3), 0.5 * math.pi, dtype=torch.float64), rtol=3e-3)


def test_sample_at_pixel_centres_returns_the_pixels():
    e = torch.rand(8, 16, 3, dtype=torch.float64)
    d = equirect_directions(8, dtype=torch.float64)
    assert torch.allclose(sample_envmap(e, d), e, atol=1e-9)


def test_single_bright_texel_is_sampled_back_where_it_is():
    h = 32
    e = torch.zeros(h, 2 * h, 3)
    i, j = 9, 45
    e[i, j] = torch.tensor([1e6, 2e6, 3e6])
    d = equirect_directions(h)
    s = sample_envmap(e, d)
    assert torch.equal(s.sum(-1).flatten().argmax(), torch.tensor(i * 2 * h + j))
    assert torch.allclose(s[i, j], e[i, j])
    # half a pixel to the right, half the energy
    theta = math.pi * (i + 0.5) / h
    phi = 2 * math.pi * (j + 1.0) / (2 * h) - math.pi
    half = sample_envmap(e, theta_phi_to_direction(torch.tensor(theta), torch.tensor(phi)))
    assert torch.allclose(half, e[i, j] / 2, rtol=1e-4)


def test_sampling_wraps_across_the_seam():
    h = 8
    e = torch.zeros(h, 2 * h, 3, dtype=torch.float64)
    e[4, 0] = 1.0  # first column, just right of phi = -pi
    e[4, -1] = 3.0  # last column, just left of phi = +pi
    theta = torch.tensor(math.pi * 4.5 / h, dtype=torch.float64)
    on_seam = sample_envmap(e, theta_phi_to_direction(theta, torch.tensor(math.pi, dtype=torch.float64)))
    assert torch.allclose(on_seam, torch.full((3,), 2.0, dtype=torch.float64))


@settings(max_examples=150, deadline=None)
@given(st.floats(0.0, math.pi), st.floats(-1e-3, 1e-3), st.integers(1, 12))
def test_sampling_is_continuous_across_the_seam(theta, dphi, height):
    e = smooth_map(height, dtype=torch.float64) * torch.linspace(1, 2, 2 * height, dtype=torch.float64)[None, :, None]
    t = torch.tensor(theta, dtype=torch.float64)
    a = sample_envmap(e, theta_phi_to_direction(t, torch.tensor(math.pi - abs(dphi), dtype=torch.float64)))
    b = sample_envmap(e, theta_phi_to_direction(t, torch.tensor(-math.pi + abs(dphi), dtype=torch.float64)))
    assert torch.isfinite(a).all() and torch.isfinite(b).all()
    # |dphi| <= 1e-3 rad is < 1e-3 W / 2pi pixels from the seam on either side
    step = float(e.abs().max()) * 2 * (1e-3 * 2 * height / (2 * math.pi) + 1e-9)
    assert torch.allclose(a, b, atol=step)


@settings(max_examples=150, deadline=None)
@given(
    st.floats(-math.pi, math.pi), st.floats(-math.pi, math.pi), st.sampled_from([0.0, 1e-12, 1e-7]), st.integers(1, 12)
)
def test_sampling_at_and_near_poles_is_finite_and_phi_independent(phi_a, phi_b, eps, height):
    e = torch.rand(height, 2 * height, 3, dtype=torch.float64) + 0.1
    for pole_theta in (0.0, math.pi):
        theta = torch.tensor(abs(pole_theta - eps), dtype=torch.float64)
        a = sample_envmap(e, theta_phi_to_direction(theta, torch.tensor(phi_a, dtype=torch.float64)))
        b = sample_envmap(e, theta_phi_to_direction(theta, torch.tensor(phi_b, dtype=torch.float64)))
        assert torch.isfinite(a).all()
        # the pole value is the mean of the nearest row; within eps of it the phi dependence is O(eps)
        row = e[0] if pole_theta == 0.0 else e[-1]
        assert torch.allclose(a, b, atol=1e-5)
        assert torch.allclose(a, row.mean(0), atol=1e-5)


def test_exact_pole_vectors_and_degenerate_directions():
    e = torch.rand(4, 8, 3)
    d = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 0.0], [-0.0, 1.0, -0.0], [float("nan"), 0.0, 1.0]])
    s = sample_envmap(e, d)
    assert torch.isfinite(s[:4]).all()
    assert torch.allclose(s[0], e[0].mean(0)) and torch.allclose(s[1], e[-1].mean(0))
    assert torch.isnan(s[4]).all()


def test_sampling_is_differentiable_in_map_and_direction():
    e = torch.rand(8, 16, 3, dtype=torch.float64, requires_grad=True)
    d = torch.tensor([[0.3, 0.2, -0.9]], dtype=torch.float64, requires_grad=True)
    sample_envmap(e, d).sum().backward()
    assert e.grad is not None and float(e.grad.sum()) == pytest.approx(3.0)  # bilinear weights sum to 1 per channel
    assert d.grad is not None and torch.isfinite(d.grad).all()


@pytest.mark.parametrize("src,dst", [(64, 32), (64, 16), (60, 7), (33, 1), (12, 5)])
def test_downsampling_preserves_integral_over_huge_dynamic_range(src, dst):
    g = torch.Generator().manual_seed(src * 100 + dst)
    # log-uniform radiance spanning 1e-6 .. 1e6
    e = torch.pow(10.0, torch.rand(src, 2 * src, 3, generator=g) * 12 - 6)
    small = resize_envmap(e, dst)
    assert small.shape == (dst, 2 * dst, 3) and small.dtype == torch.float32
    assert torch.allclose(integrate(small).double(), integrate(e.double()), rtol=1e-5)
    assert float(small.min()) >= float(e.min()) * (1 - 1e-6)


def test_downsampling_keeps_a_single_bright_texel():
    e = torch.zeros(64, 128, 3)
    e[20, 77] = 1e6
    small = resize_envmap(e, 8)
    assert float(integrate(small)[0]) == pytest.approx(float(integrate(e)[0]), rel=1e-5)
    assert small[..., 0].argmax() == (20 // 8) * 16 + 77 // 8


def test_upsampling_is_bilinear_and_exact_on_constants():
    c = torch.full((4, 8, 3), 7.0)
    assert torch.allclose(resize_envmap(c, 16), torch.full((16, 32, 3), 7.0))
    e = smooth_map(16, dtype=torch.float64)
    up = resize_envmap(e, 64)
    assert (up - smooth_map(64, dtype=torch.float64)).abs().max() < 0.02


def test_rotation_by_90_degrees_about_y_moves_forward_content_to_minus_x():
    """R = Ry(+90): R(-z) = -x. result(d) = envmap(R^T d), so the light from -z now arrives from -x."""
    h = 32
    c, s = 0.0, 1.0
    R = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
    assert torch.allclose(
        R @ torch.tensor([0, 0, -1.0], dtype=torch.float64), torch.tensor([-1.0, 0, 0], dtype=torch.float64)
    )
    e = envmap_from_function(lambda d: (-d[..., 2]).clamp_min(0) ** 8, h, dtype=torch.float64)  # lobe at -z
    rotated = rotate_envmap(e, R)
    expected = envmap_from_function(lambda d: (-d[..., 0]).clamp_min(0) ** 8, h, dtype=torch.float64)  # lobe at -x
    assert (rotated - expected).abs().max() < 0.05
    # a quarter turn about y is an exact column shift by W/4 (no resampling error)
    assert torch.allclose(rotated, torch.roll(e, shifts=-h // 2, dims=1), atol=1e-9)


def test_rotation_preserves_integral_and_inverts():
    e = smooth_map(32, dtype=torch.float64)
    a = 0.7
    R = torch.tensor([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]], dtype=torch.float64)
    r = rotate_envmap(e, R)
    assert torch.allclose(integrate(r), integrate(e), rtol=1e-2)
    back = rotate_envmap(r, R.T)
    assert (back - e).abs().max() < 0.05


def test_rotation_rejects_non_rotations():
    with pytest.raises(EnvmapError, match="R"):
        rotate_envmap(torch.ones(4, 8, 3), torch.eye(3) * 2)


@pytest.mark.parametrize("axis,flip", [("x", (-1, 1, 1)), ("y", (1, -1, 1)), ("z", (1, 1, -1))])
def test_mirror_envmap_negates_one_axis(axis, flip):
    e = smooth_map(8, dtype=torch.float64)
    f = torch.tensor(flip, dtype=torch.float64)
    expected = envmap_from_function(lambda d: sample_envmap(e, d * f), 8, dtype=torch.float64)
    assert torch.allclose(mirror_envmap(e, axis), expected, atol=1e-9)


@pytest.mark.parametrize("shape", [(4, 4, 3), (4, 8), (4, 8, 4), (0, 0, 3)])
def test_malformed_maps_raise(shape):
    with pytest.raises(EnvmapError, match="envmap"):
        integrate(torch.zeros(shape))


def test_bad_height_raises():
    with pytest.raises(EnvmapError, match="height"):
        solid_angles(0)
    with pytest.raises(EnvmapError, match="height"):
        resize_envmap(torch.ones(4, 8, 3), 2.5)


def test_splat_keeps_the_nearest_surface_skips_points_at_the_centre_and_treats_centres_apart():
    """splat_points' rules: per pixel only points within SPLAT_Z_TOLERANCE of the nearest one are
    averaged (a wall behind a table does not bleed through); a point at the centre itself lands
    nowhere; a centre's maps do not depend on the other centres; unseen pixels are 0."""
    from core.envmap import SPLAT_MIN_DISTANCE, splat_points

    forward = torch.tensor([0.0, 0.0, -1.0])
    pts = torch.stack([1.0 * forward, 1.05 * forward, 3.0 * forward, torch.zeros(3)])  # near, near, far, at the centre
    col = torch.tensor([[1.0, 1.0, 1.0], [3.0, 3.0, 3.0], [100.0, 100.0, 100.0], [7.0, 7.0, 7.0]])
    env, seen = splat_points(pts, col, torch.zeros(1, 3), 8)
    assert int(seen.sum()) == 1 and torch.isfinite(env).all()
    assert torch.allclose(env[seen], torch.full((1, 3), 2.0))  # (1 + 3) / 2: the far point and the centre's are out
    assert float(env[~seen].abs().max()) == 0.0
    # the centre's point is only skipped within SPLAT_MIN_DISTANCE
    near = splat_points(torch.tensor([[0.0, 2 * SPLAT_MIN_DISTANCE, 0.0]]), col[:1], torch.zeros(1, 3), 8)[1]
    assert int(near.sum()) == 1
    # two centres at once answer as each alone
    centres = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, -2.0]])
    both, both_seen = splat_points(pts, col, centres, 8)
    for k in range(2):
        alone, alone_seen = splat_points(pts, col, centres[k:k + 1], 8)
        assert torch.equal(both[k], alone[0]) and torch.equal(both_seen[k], alone_seen[0])
