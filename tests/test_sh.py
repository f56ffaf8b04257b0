"""Real SH up to band 2: analytic projections, irradiance, ARCore layout."""
import math

import pytest
import torch
from hypothesis import given, settings, strategies as st

from core.envmap import envmap_from_function, irradiance
from core.export.sh_layouts import from_arcore_27, to_arcore_27
from core.sh import (
    COSINE_LOBE_BY_BAND,
    SH_BANDS,
    SHError,
    eval_sh,
    project_sh,
    sh_basis,
    sh_irradiance,
    sh_to_envmap,
)

unit_vectors = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(
    lambda v: sum(c * c for c in v) > 1e-4
)


def test_basis_constants_and_axes():
    """Band 1 is (y, z, x) in OUR frame; the documented 6-digit constants."""
    y_up = sh_basis(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    z_back = sh_basis(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    x_right = sh_basis(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    assert float(y_up[0]) == pytest.approx(0.282095, abs=1e-6)
    assert float(y_up[1]) == pytest.approx(0.488603, abs=1e-6) and float(y_up[2]) == 0 and float(y_up[3]) == 0
    assert float(z_back[2]) == pytest.approx(0.488603, abs=1e-6)
    assert float(x_right[3]) == pytest.approx(0.488603, abs=1e-6)
    assert float(z_back[6]) == pytest.approx(2 * 0.315392, abs=1e-6)  # 3z^2 - 1 = 2
    assert float(x_right[8]) == pytest.approx(0.546274, abs=1e-6)
    d = torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64) / math.sqrt(2)
    assert float(sh_basis(d)[4]) == pytest.approx(1.092548 / 2, abs=1e-6)


@settings(max_examples=200, deadline=None)
@given(unit_vectors)
def test_addition_theorem(v):
    """sum_m Y_lm(d)^2 = (2l + 1) / 4 pi for every band and direction (checks every constant)."""
    y = sh_basis(torch.tensor(v, dtype=torch.float64))
    for band, (lo, hi) in enumerate(((0, 1), (1, 4), (4, 9))):
        assert float((y[lo:hi] ** 2).sum()) == pytest.approx((2 * band + 1) / (4 * math.pi), rel=1e-9)


def test_basis_of_zero_direction_is_finite():
    y = sh_basis(torch.zeros(3))
    assert torch.isfinite(y).all() and float(y[1:].abs().sum()) == 0.0


@pytest.mark.parametrize("height", [1, 2, 4, 64])
def test_constant_map_has_only_band_0_exactly(height):
    """c_0 = L sqrt(4 pi) and nothing else, at any resolution (per-cell exact projection)."""
    c = torch.tensor([0.5, 2.0, 1e-6], dtype=torch.float64)
    coeffs = project_sh(c.expand(height, 2 * height, 3).contiguous())
    assert torch.allclose(coeffs[0], c * math.sqrt(4 * math.pi), rtol=1e-12)
    assert coeffs[1:].abs().max() < 1e-12 * float(c.max())


def test_projection_is_orthonormal():
    """Projecting each basis function gives the unit vector of its index."""
    h = 96
    for k in range(9):
        e = envmap_from_function(lambda d: sh_basis(d)[..., k], h, dtype=torch.float64)
        coeffs = project_sh(e)[:, 0]
        expected = torch.zeros(9, dtype=torch.float64)
        expected[k] = 1.0
        assert torch.allclose(coeffs, expected, atol=1e-3), k


def test_clamped_cosine_lobe_matches_analytic_coefficients():
    """max(0, n.d) is zonal about n with coefficients A_l Y_lm(n) (Ramamoorthi & Hanrahan)."""
    n = torch.tensor([0.3, 0.8, -0.5], dtype=torch.float64)
    n = n / n.norm()
    e = envmap_from_function(lambda d: (d @ n).clamp_min(0), 256, dtype=torch.float64)
    coeffs = project_sh(e)[:, 0]
    a = torch.tensor([COSINE_LOBE_BY_BAND[l] for l in SH_BANDS], dtype=torch.float64)
    assert torch.allclose(coeffs, a * sh_basis(n), atol=2e-4)
    assert COSINE_LOBE_BY_BAND == pytest.approx((math.pi, 2 * math.pi / 3, math.pi / 4))


def test_eval_of_projection_reproduces_band_limited_function():
    g = torch.Generator().manual_seed(0)
    coeffs = torch.randn(9, 3, generator=g, dtype=torch.float64)
    e = sh_to_envmap(coeffs, 64)
    back = project_sh(e)
    assert torch.allclose(back, coeffs, atol=2e-3)
    assert (sh_to_envmap(back, 64) - e).abs().max() < 5e-3


def test_sh_irradiance_matches_brute_force_for_band_limited_radiance():
    g = torch.Generator().manual_seed(1)
    coeffs = torch.randn(9, 3, generator=g, dtype=torch.float64) * 0.2
    coeffs[0] += 3.0
    e = sh_to_envmap(coeffs, 64)
    normals = torch.nn.functional.normalize(torch.randn(20, 3, generator=g, dtype=torch.float64), dim=-1)
    assert torch.allclose(sh_irradiance(coeffs, normals), irradiance(e, normals), atol=1e-2)


def test_irradiance_of_analytic_cases():
    const = torch.zeros(9, 1, dtype=torch.float64)
    const[0] = math.sqrt(4 * math.pi)  # L = 1 everywhere
    n = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    assert torch.allclose(sh_irradiance(const, n), torch.full((2, 1), math.pi, dtype=torch.float64))
    # L = y  =>  E(n) = (2 pi / 3) n_y
    lin = torch.zeros(9, 1, dtype=torch.float64)
    lin[1] = 1.0 / 0.4886025119029199
    assert torch.allclose(sh_irradiance(lin, n)[:, 0], torch.tensor([2 * math.pi / 3, 0.0], dtype=torch.float64))


def test_arcore_layout_round_trip_and_interleaving():
    g = torch.Generator().manual_seed(2)
    coeffs = torch.randn(9, 3, generator=g)
    flat = to_arcore_27(coeffs)
    assert isinstance(flat, list) and len(flat) == 27
    assert flat[3 * 4 + 1] == pytest.approx(float(coeffs[4, 1]))  # coefficient-major, RGB interleaved
    assert flat[3 * 1 + 2] == pytest.approx(-float(coeffs[1, 2]))  # odd m carries the Condon-Shortley sign
    assert torch.allclose(from_arcore_27(flat), coeffs)


def test_arcore_coefficients_light_a_surface_like_the_arcore_sample():
    """ARCore's sample shader: irradiance/pi = sum_k sh[k] f_k P_k(n) with its published factors."""
    factors = torch.tensor(
        [0.282095, -0.325735, 0.325735, -0.325735, 0.273137, -0.273137, 0.078848, -0.273137, 0.136569],
        dtype=torch.float64,
    )

    def arcore_shader(sh27, n):
        x, y, z = n
        poly = torch.stack((torch.ones(()), y, z, x, y * x, y * z, 3 * z * z - 1, z * x, x * x - y * y)).double()
        return ((torch.tensor(sh27, dtype=torch.float64).reshape(9, 3) * (factors * poly)[:, None]).sum(0))

    g = torch.Generator().manual_seed(3)
    coeffs = torch.randn(9, 3, generator=g, dtype=torch.float64)
    for n in torch.nn.functional.normalize(torch.randn(10, 3, generator=g, dtype=torch.float64), dim=-1):
        assert torch.allclose(arcore_shader(to_arcore_27(coeffs), n), sh_irradiance(coeffs, n) / math.pi, atol=1e-5)


@pytest.mark.parametrize("bad", [[0.0] * 26, [0.0] * 28, [float("nan")] * 27])
def test_bad_arcore_arrays_raise(bad):
    with pytest.raises(SHError, match="27|finite"):
        from_arcore_27(bad)


def test_eval_sh_rejects_wrong_coefficient_count():
    with pytest.raises(SHError, match="9"):
        eval_sh(torch.zeros(4, 3), torch.tensor([0.0, 1.0, 0.0]))
