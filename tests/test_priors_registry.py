"""Priors plug in by registration with typed settings, and declare what they offer beyond the
call (PriorCapabilities): the env-map capability answers what the balls show."""

import pytest
import torch

from core.capture.load import capture_from_arrays
from core.conventions import equirect_directions
from core.envmap import resize_envmap, sample_envmap
from core.priors import (
    KnownRadiancePrior,
    Prior,
    PriorCapabilities,
    PriorConfig,
    PriorError,
    ReprojectionPrior,
    build_prior,
    job_prior_names,
    prior_names,
    register_prior,
)
from core.priors.registry import LAZY_PRIORS, PRIORS, prior_class


def sky(x, t, d):
    """Smooth radiance that depends on position, time and direction."""
    return (1.0 + 0.5 * d[:, 1:2] + 0.1 * x[:, 0:1] + 0.2 * t[:, None]).clamp_min(0.05).expand(-1, 3) * torch.tensor(
        [1.0, 0.8, 0.6]
    )


def test_names_come_from_the_registry():
    assert {"reprojection", "known", "diffusion"} <= set(prior_names())
    assert set(job_prior_names()) == {"reprojection", "diffusion"}  # known/oracle need Python objects
    assert prior_class("diffusion").for_jobs  # the lazily registered prior declares what LAZY_PRIORS assumes
    assert set(LAZY_PRIORS) <= set(PRIORS)


def test_capabilities_are_declared_by_each_prior():
    from core.sim.oracle import OracleSimPrior

    assert ReprojectionPrior.capabilities == PriorCapabilities(
        frame_geometry=True, envmaps=True, envmaps_anywhere=True, view_radiance=True
    )
    assert not KnownRadiancePrior.capabilities.view_radiance
    assert KnownRadiancePrior.capabilities.envmaps and not KnownRadiancePrior.capabilities.frame_geometry
    assert OracleSimPrior.capabilities.envmaps and prior_class("oracle") is OracleSimPrior
    assert prior_class("diffusion").capabilities == PriorCapabilities()
    assert ReprojectionPrior().device == torch.device("cpu")


def test_known_prior_env_maps_are_its_radiance_in_every_direction():
    prior = KnownRadiancePrior(sky)
    centers = torch.tensor([[0.5, 0.0, -1.0], [-1.0, 0.3, -2.0]])
    env = prior.envmaps(centers, 1.5, 8)
    assert env.shape == (2, 8, 16, 3)
    dirs = equirect_directions(8).reshape(-1, 3)
    for n in range(2):
        expected = sky(centers[n].expand(dirs.shape[0], 3), torch.full((dirs.shape[0],), 1.5), dirs)
        torch.testing.assert_close(env[n].reshape(-1, 3), expected)


def test_oracle_env_maps_are_the_simulators_truth_and_match_its_ball_radiance():
    import core.sim.oracle  # noqa: F401  (registers the oracle)
    from core.sim.render import radiance_fn, render_envmap
    from core.sim.suites import suite

    scene = suite("spatial")
    prior = build_prior("oracle", {"scene": scene})
    probe = scene.probes[0]
    x = torch.tensor([probe.x], dtype=torch.float32)
    env = prior.envmaps(x, probe.t, 16)[0]
    torch.testing.assert_close(env, render_envmap(scene, x[0], probe.t, 16))
    # away from the lamps (which the truth integrates per pixel), the map is the radiance the balls show
    dirs = equirect_directions(16).reshape(-1, 3)
    direct = radiance_fn(scene)(x.expand(dirs.shape[0], 3), torch.full((dirs.shape[0],), probe.t), dirs)
    same = torch.isclose(env.reshape(-1, 3), direct, rtol=1e-3, atol=1e-6).all(-1)
    assert float(same.float().mean()) > 0.95


def test_reprojection_env_maps_follow_time_and_height():
    frames = torch.stack([torch.full((24, 32, 3), 0.2), torch.full((24, 32, 3), 0.7)])
    cap = capture_from_arrays(frames, torch.full((2, 24, 32), 3.0), fps=1.0)  # t = 0 s, 1 s
    # smooth maps: resizing is the subject
    prior = build_prior("reprojection", {"env_height": 8, "unseen_fill": "push-pull"})
    prior.bind(cap)
    c = torch.tensor([[0.0, 0.0, -1.0]])
    torch.testing.assert_close(prior.envmaps(c, 0.2, 8), prior.envmaps_at_frame(c, 0))
    torch.testing.assert_close(prior.envmaps(c, 0.8, 8), prior.envmaps_at_frame(c, 1))
    big = prior.envmaps(c, 0.8, 16)
    assert big.shape == (1, 16, 32, 3)
    torch.testing.assert_close(resize_envmap(big[0], 8), prior.envmaps_at_frame(c, 1)[0], rtol=0.05, atol=0.02)


def test_reprojection_pools_views_only_for_static_lighting_and_a_moving_camera():
    poses = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    poses[1, 0, 3] = 0.5
    moving = capture_from_arrays(torch.rand(2, 24, 32, 3), torch.full((2, 24, 32), 3.0), poses=poses)
    static = capture_from_arrays(torch.rand(2, 24, 32, 3), torch.full((2, 24, 32), 3.0))
    for cap, changes, merged in ((moving, False, 2), (moving, True, 1), (static, False, 1)):
        prior = ReprojectionPrior(env_height=8)
        prior.bind(cap, lighting_changes=changes)
        assert prior.describe()["merge_views"] == merged  # still light, moving camera: every frame
        assert (prior.describe()["merged_cloud_points"] is not None) == (merged > 1)
    prior = ReprojectionPrior(env_height=8, merge_views=2)
    prior.bind(moving, lighting_changes=True)
    assert prior.merge_views == 2  # an explicit setting wins


def test_a_prior_without_the_capability_refuses_env_maps():
    class Flat(Prior):
        def __call__(self, request):
            return request.image

        def describe(self):
            return {"name": "flat"}

    Flat.name = "flat"
    with pytest.raises(PriorError, match="cannot answer env maps"):
        Flat().envmaps(torch.zeros(1, 3), 0.0, 8)


def test_a_new_prior_is_one_class_and_its_registration():
    class GreySettings(PriorConfig):
        level: float = 0.5

    @register_prior("grey-test", for_jobs=True)
    class GreyPrior(Prior):
        Config = GreySettings
        capabilities = PriorCapabilities(envmaps=True)

        def __init__(self, level: float):
            self.level = level

        def __call__(self, request):
            return request.image

        def envmaps(self, centers, time, height):
            return torch.full((centers.shape[0], height, 2 * height, 3), self.level)

        def describe(self):
            return {"name": self.name, "level": self.level}

    try:
        assert "grey-test" in job_prior_names()
        prior = build_prior("grey-test", {"level": 0.25})
        assert prior.describe() == {"name": "grey-test", "level": 0.25}
        assert (
            float(sample_envmap(prior.envmaps(torch.zeros(1, 3), 0.0, 4)[0], torch.tensor([[0.0, 1.0, 0.0]]))[0, 0])
            == 0.25
        )
        with pytest.raises(PriorError, match="levle"):
            build_prior("grey-test", {"levle": 1})
        with pytest.raises(ValueError, match="already registered"):
            register_prior("reprojection")(GreyPrior)
    finally:
        PRIORS.pop("grey-test", None)


def test_reprojection_view_radiance_is_what_it_splats_and_its_camera_map_is_cached_exactly():
    from core.capture.load import capture_from_arrays

    frames = torch.rand(2, 12, 16, 3, generator=torch.Generator().manual_seed(0))
    capture = capture_from_arrays(frames)
    prior = ReprojectionPrior(env_height=8)
    prior.bind(capture)
    assert prior.view_radiance(1).shape == (12, 16, 3) and torch.equal(prior.view_radiance(1), prior._colors[1])
    cam = capture.poses[1, :3, 3].float()
    centers = torch.stack((cam + torch.tensor([0.1, 0.0, -0.2]), cam))
    first, again = prior.envmaps_at_frame(centers, 1), prior.envmaps_at_frame(centers.flip(0), 1)
    assert torch.equal(first, prior._splat(centers, 1)) and torch.equal(again, first.flip(0))
