"""Three-sphere protocol and image metrics: analytic cases and degenerate inputs."""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings, strategies as st

from core.envmap import envmap_from_function
from core.metrics import (
    MetricsError,
    angular_error_deg,
    normalized_rmse,
    render_probe_sphere,
    si_rmse,
    sphere_normals,
    temporal_flicker,
    three_sphere_metrics,
)


def textured_env(height=32):
    return envmap_from_function(
        lambda d: torch.stack((1.0 + d[..., 0] ** 2, 0.5 + 0.4 * d[..., 1], 2.0 + torch.sin(3 * d[..., 2])), -1)
        + 20.0 * torch.exp(40.0 * (d[..., 1:2] - 1.0)),  # a soft "sun" overhead
        height,
    )


# ---------------------------------------------------------------------------------------
# Sphere renders
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("material,scale", [("diffuse", 0.8), ("matte", 0.8), ("mirror", 1.0)])
def test_uniform_environment_gives_uniform_sphere(material, scale):
    env = torch.full((16, 32, 3), 1.5)
    image, mask = render_probe_sphere(env, material, size=48)
    assert torch.allclose(image[mask], torch.full_like(image[mask], 1.5 * scale), rtol=1e-4)
    assert float(image[~mask].abs().max()) == 0.0
    # the mask is the unit disc
    assert float(mask.float().mean()) == pytest.approx(math.pi / 4, abs=0.02)


def test_diffuse_sphere_under_upper_hemisphere_sky_matches_analytic_irradiance():
    # L = 1 for d_y > 0: E(n) = pi (1 + n_y) / 2, radiance = albedo E / pi
    env = envmap_from_function(lambda d: (d[..., 1:2] > 0).float().expand(*d.shape[:-1], 3), 64)
    image, mask = render_probe_sphere(env, "diffuse", size=48)
    n, _ = sphere_normals(48)
    expected = 0.8 * (1.0 + n[..., 1]) / 2.0
    assert torch.allclose(image[..., 0][mask], expected[mask].float(), atol=0.02)


def test_mirror_sphere_reflects_by_the_reflection_law():
    env = textured_env(128)
    image, mask = render_probe_sphere(env, "mirror", size=64)
    n, _ = sphere_normals(64)
    # independent: reflect the view ray (0, 0, -1) about n by hand, evaluate the function
    d = torch.stack((2 * n[..., 2] * n[..., 0], 2 * n[..., 2] * n[..., 1], -1 + 2 * n[..., 2] ** 2), -1)
    truth = torch.stack((1.0 + d[..., 0] ** 2, 0.5 + 0.4 * d[..., 1], 2.0 + torch.sin(3 * d[..., 2])), -1)
    truth = truth + 20.0 * torch.exp(40.0 * (d[..., 1:2] - 1.0))
    inner = mask & (n[..., 2] > 0.3)  # away from the rim, where the map is compressed
    assert torch.allclose(image[inner], truth[inner].float(), rtol=0.05, atol=0.05)
    # the overhead sun shows where n bisects +y and the view direction +z: n_y = sin 45 deg
    row, col = divmod(int(image[..., 1].argmax()), 64)
    assert abs(col - 31.5) <= 1.0 and abs(row + 0.5 - 32 * (1 - math.sqrt(0.5))) <= 1.0


def test_matte_is_between_mirror_and_diffuse_in_contrast():
    env = textured_env(64)
    contrast = {}
    for material in ("diffuse", "matte", "mirror"):
        image, mask = render_probe_sphere(env, material, size=48)
        y = image[mask].sum(-1)
        contrast[material] = float(y.max() / y.min())
    assert contrast["diffuse"] < contrast["matte"] < contrast["mirror"]


def test_render_rejects_unknown_material():
    with pytest.raises(MetricsError, match="material"):
        render_probe_sphere(torch.ones(8, 16, 3), "glass")


# ---------------------------------------------------------------------------------------
# Image metrics
# ---------------------------------------------------------------------------------------
def test_metrics_are_zero_for_identical_maps_and_si_rmse_is_scale_invariant():
    env = textured_env(32)
    same = three_sphere_metrics(env, env, size=32)
    for material, values in same.items():
        for name, value in values.items():
            assert value == pytest.approx(0.0, abs=1e-4), (material, name)
    scaled = three_sphere_metrics(env * 7.5, env, size=32)
    for material in scaled:
        assert scaled[material]["si_rmse"] == pytest.approx(0.0, abs=1e-4)
        assert scaled[material]["angular_deg"] == pytest.approx(0.0, abs=1e-3)


def test_angular_error_of_colour_shift_matches_analytic_angle():
    grey = envmap_from_function(lambda d: (1.5 + d[..., 1:2]).expand(*d.shape[:-1], 3), 32)
    tint = torch.tensor([1.0, 0.5, 0.25])
    expected = math.degrees(math.acos(float(tint.sum() / (tint.norm() * math.sqrt(3.0)))))
    metrics = three_sphere_metrics(grey * tint, grey, size=32)
    for material in metrics:
        assert metrics[material]["angular_deg"] == pytest.approx(expected, rel=1e-4)


@settings(max_examples=30, deadline=None)
@given(scale=st.floats(1e-6, 1e6), seed=st.integers(0, 1000))
def test_si_rmse_invariant_to_prediction_scale(scale, seed):
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(10, 10, 3, generator=g)
    pred = gt + 0.1 * torch.rand(10, 10, 3, generator=g)
    assert si_rmse(pred * scale, gt) == pytest.approx(si_rmse(pred, gt), rel=1e-6, abs=1e-9)


def test_si_rmse_closed_form_against_brute_force_scale_search():
    g = torch.Generator().manual_seed(3)
    gt, pred = torch.rand(6, 6, 3, generator=g), torch.rand(6, 6, 3, generator=g)
    alphas = torch.linspace(0.0, 3.0, 30001, dtype=torch.float64)
    errs = ((alphas[:, None] * pred.double().reshape(1, -1) - gt.double().reshape(1, -1)) ** 2).sum(-1) / 36
    assert si_rmse(pred, gt) == pytest.approx(float(errs.min().sqrt()), rel=1e-6)


def test_metrics_on_all_zero_prediction_and_constant_images():
    gt = torch.rand(8, 8, 3) + 0.1
    zero = torch.zeros(8, 8, 3)
    # best alpha is 0: the error is the RMS of gt
    assert si_rmse(zero, gt) == pytest.approx(float(gt.double().pow(2).sum(-1).mean().sqrt()), rel=1e-6)
    assert angular_error_deg(zero, gt) == pytest.approx(90.0)
    assert angular_error_deg(zero, zero) == 0.0
    assert math.isfinite(normalized_rmse(zero, gt))
    const = torch.full((8, 8, 3), 3.0)
    assert normalized_rmse(const, const * 2) == 0.0
    assert si_rmse(const, const * 2) == pytest.approx(0.0, abs=1e-12)
    env_metrics = three_sphere_metrics(torch.zeros(16, 32, 3), torch.ones(16, 32, 3), size=24)
    assert all(math.isfinite(v) for m in env_metrics.values() for v in m.values())


def test_normalized_rmse_ignores_affine_changes_and_respects_mask():
    g = torch.Generator().manual_seed(4)
    gt = torch.rand(16, 16, 3, generator=g)
    assert normalized_rmse(3.0 * gt + 0.5, gt) == pytest.approx(0.0, abs=1e-6)
    mask = torch.zeros(16, 16, dtype=torch.bool)
    mask[:8] = True
    pred = gt.clone()
    pred[8:] = 100.0  # outside the mask: must not matter
    assert normalized_rmse(pred, gt, mask) == pytest.approx(0.0, abs=1e-6)


def test_metric_input_errors():
    with pytest.raises(MetricsError, match="shape"):
        si_rmse(torch.ones(4, 4, 3), torch.ones(4, 5, 3))
    with pytest.raises(MetricsError, match="no pixels"):
        si_rmse(torch.ones(4, 4, 3), torch.ones(4, 4, 3), torch.zeros(4, 4, dtype=torch.bool))
    with pytest.raises(MetricsError, match="pred"):
        angular_error_deg(torch.full((4, 4, 3), float("nan")), torch.ones(4, 4, 3))


# ---------------------------------------------------------------------------------------
# Temporal flicker
# ---------------------------------------------------------------------------------------
def test_flicker_zero_for_static_and_single_frame_sequences():
    frame = torch.rand(8, 8, 3)
    assert temporal_flicker(frame.expand(5, -1, -1, -1)) == 0.0
    assert temporal_flicker(frame[None]) == 0.0
    assert temporal_flicker(torch.zeros(4, 8, 8, 3)) == 0.0


def test_flicker_measures_relative_change_and_ignores_global_scale():
    frame = torch.rand(8, 8, 3) + 0.5
    factors = torch.tensor([1.0, 1.1, 1.0, 1.1])
    seq = frame[None] * factors[:, None, None, None]
    # each step changes log-luminance by ~log(1.1) (eps is 1e-3 of the mean)
    assert temporal_flicker(seq) == pytest.approx(math.log(1.1), rel=0.01)
    assert temporal_flicker(seq * 1000.0) == pytest.approx(temporal_flicker(seq), rel=1e-5)
    smooth = frame[None] * torch.linspace(1.0, 1.03, 4)[:, None, None, None]
    assert temporal_flicker(smooth) < temporal_flicker(seq)


def test_flicker_rejects_non_finite():
    seq = torch.ones(3, 4, 4, 3)
    seq[1, 0, 0, 0] = float("inf")
    with pytest.raises(MetricsError, match="non-finite"):
        temporal_flicker(seq)


# ---------------------------------------------------------------------------------------
# Observed-region correlation
# ---------------------------------------------------------------------------------------
def _camera_rays(yaw_deg: float, pitch_deg: float, hfov: float = 60.0, size=(48, 36)) -> torch.Tensor:
    from core.camera import Camera, Intrinsics
    from core.sim.state import pose_from_yaw_pitch

    c2w = pose_from_yaw_pitch((0.0, 0.0, 0.0), yaw_deg, pitch_deg)
    return Camera(Intrinsics.from_hfov(size[0], size[1], hfov), c2w).pixel_rays(dtype=torch.float64)[1]


def _textured_map(h: int = 64, seed: int = 0) -> torch.Tensor:
    """Smooth random HDR texture over 4 stops plus a bright 'lamp'."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.randn(1, 3, h // 8, h // 4, generator=g, dtype=torch.float64)
    log_y = torch.nn.functional.interpolate(coarse, size=(h, 2 * h), mode="bicubic", align_corners=False)[0].permute(
        1, 2, 0
    )
    env = torch.exp(1.4 * log_y)
    env[h // 3 : h // 3 + 3, 10:13] = 500.0
    return env


@pytest.mark.parametrize("yaw,pitch", [(0.0, 0.0), (180.0, 5.0), (-179.0, -10.0), (30.0, 88.0), (0.0, -89.0)])
def test_observed_correlation_of_the_true_map_is_one_across_seam_and_poles(yaw, pitch):
    from core.envmap import sample_envmap
    from core.metrics import observed_region_correlation

    env = _textured_map()
    rays = _camera_rays(yaw, pitch)
    photo = sample_envmap(env, rays) * 0.01  # the photo's exposure does not matter
    assert observed_region_correlation(env, photo, rays) > 0.999


def test_observed_correlation_constant_map_is_zero_and_wrong_view_is_low():
    from core.envmap import sample_envmap
    from core.metrics import observed_region_correlation

    env = _textured_map()
    rays = _camera_rays(20.0, 0.0)
    photo = sample_envmap(env, rays)
    assert observed_region_correlation(torch.ones_like(env), photo, rays) == 0.0
    assert observed_region_correlation(torch.zeros_like(env), photo, rays) == 0.0
    # the same map looked up behind the camera does not reproduce the photo
    assert observed_region_correlation(env, photo, _camera_rays(200.0, 0.0)) < 0.5
    # a blurred map (lower resolution) still correlates, less than perfectly
    from core.envmap import resize_envmap

    blurred = resize_envmap(resize_envmap(env, 8), 64)
    assert 0.3 < observed_region_correlation(blurred, photo, rays) < 0.999


def test_observed_correlation_rejects_mismatched_shapes():
    from core.metrics import MetricsError, observed_region_correlation

    with pytest.raises(MetricsError):
        observed_region_correlation(torch.ones(8, 16, 3), torch.ones(4, 5, 3), torch.ones(4, 6, 3))
