"""Radiance supervision (core.engine.radiance): a field distilled from a prior that answers HDR
env maps keeps what the prior knows, extrapolates smoothly where nothing was observed, and
follows a light switching off out of view while static stretches stay flat.

Small scenes and budgets (seconds each); the suite-scale numbers are bench/accuracy_probe.py's."""
import json

import pytest
import torch

from core.capture.load import capture_from_arrays
from core.capture.prepare import load_prepared_capture
from core.conventions import inverse_tonemap
from core.engine.distill import distill, view_rays, with_view_detail
from core.engine.extrapolation import log_total_variation, observed_directions, ring_ratio
from core.engine.presets import preset
from core.engine.radiance import bright_directions, radiance_loss, supervision_probes
from core.envmap import integrate, resize_envmap
from core.exposure import luminance
from core.metrics import observed_region_correlation, three_sphere_metrics
from core.priors.known import KnownRadiancePrior
from core.priors.reprojection import ReprojectionPrior
from core.sim.capture import write_capture
from core.sim.render import render_envmap
from core.sim.suites import spatial


def small(supervision="envmaps", iterations=300, work_height=48, **distill_overrides):
    d = {"iterations": iterations, "work_height": work_height, "supervision": supervision, "envmap_height": 16,
         "checkpoint_every": 1000, **distill_overrides}
    return preset("draft").with_overrides({"distill": d})


def simulated_scene(spec, resolution, tmp_dir):
    """(spec at `resolution`, its capture written to tmp_dir and loaded)."""
    spec = spec.model_copy(update={"resolution": resolution})
    write_capture(spec, tmp_dir, envmap_height=16, video=False)
    return spec, load_prepared_capture(tmp_dir)


@pytest.fixture(scope="module")
def spatial_scene(tmp_path_factory):
    """The simulator's `spatial` suite (two near lamps, shadows) as a 64x48 photo with depth."""
    return simulated_scene(spatial(), (64, 48), tmp_path_factory.mktemp("spatial"))


def _bound_prior(capture):
    prior = ReprojectionPrior(env_height=16)
    prior.bind(capture, lighting_changes=False)
    return prior


def test_field_keeps_what_the_prior_knows_on_a_simulated_room(spatial_scene):
    spec, capture = spatial_scene
    prior = _bound_prior(capture)
    field = distill(capture, prior, small(), uses_time=False, seed=0).field
    field_scores, prior_scores = [], []
    for probe in spec.probes:  # held out: the loop never placed a probe there
        x = torch.tensor([probe.x])
        truth = render_envmap(spec, probe.x, 0.0, 16)
        with torch.no_grad():
            field_scores.append(three_sphere_metrics(field.envmaps(x, None, 16)[0], truth, 32))
        prior_scores.append(three_sphere_metrics(prior.envmaps(x, 0.0, 16)[0], truth, 32))

    def mean(scores, material):
        return sum(s[material]["si_rmse"] for s in scores) / len(scores)

    for material in ("diffuse", "matte", "mirror"):
        # measured 1.02 / 1.02 / 1.01 of the prior (bench/accuracy_probe.py for the suites)
        assert mean(field_scores, material) <= 1.05 * mean(prior_scores, material), material


def test_single_photo_is_reproduced_where_seen_without_rings_where_not(spatial_scene):
    """A photo without depth (the assumed room), map at the camera. Where the photo looked, the
    field reproduces it (pixel rays fitted to the prior's view radiance through the direction
    grids): log-luminance correlation with the linearised photo well above the prior's 16-row
    map. Where nothing was seen (~95 % of directions) it has no more structure than the prior's
    push-pull fill (the ball loop, measured: 2.3x the prior's unobserved TV, ratio 0.38)."""
    _, with_depth = spatial_scene
    capture = capture_from_arrays(with_depth.frames)
    prior = _bound_prior(capture)
    field = distill(capture, prior, small(), uses_time=False, seed=0).field
    cam = capture.camera(0)
    at_camera = cam.position[None].float()
    observed = observed_directions(cam, 32)
    with torch.no_grad():
        env = field.envmaps(at_camera, None, 32)[0]
        fine = field.envmaps(at_camera, None, 64)[0]
    ours = ring_ratio(env, observed)
    reference = ring_ratio(prior.envmaps(at_camera, 0.0, 32)[0], observed)
    assert ours["tv_unobserved"] <= 1.5 * reference["tv_unobserved"], (ours, reference)  # measured 1.25x
    assert ours["ratio"] <= 0.25, ours  # measured 0.10
    rays, photo = cam.pixel_rays(dtype=torch.float64)[1], inverse_tonemap(capture.frames[0])
    corr = observed_region_correlation(fine, photo, rays)
    prior_corr = observed_region_correlation(prior.envmaps(at_camera, 0.0, 64)[0], photo, rays)
    # measured 0.91 vs 0.70 (0.69 without view supervision)
    assert corr >= 0.85 and corr >= prior_corr + 0.1, (corr, prior_corr)


def test_view_supervision_only_with_a_prior_that_gives_view_radiance(spatial_scene):
    _, capture = spatial_scene
    cfg = small().distill
    rays = view_rays(capture, cfg, _bound_prior(capture))
    assert rays.shape == (capture.height * capture.width, 3)
    assert torch.allclose(rays.norm(dim=-1), torch.ones(1), atol=1e-5)
    world = capture.camera(0).pixel_rays()[1].reshape(-1, 3)  # what the trainer makes of them
    assert torch.allclose(rays @ capture.poses[0, :3, :3].T.float(), world, atol=1e-6)
    assert view_rays(capture, cfg, KnownRadiancePrior(lambda x, t, d: torch.ones_like(d))) is None
    assert view_rays(capture, cfg.model_copy(update={"envmap_view_directions": 0}), _bound_prior(capture)) is None
    assert view_rays(capture, cfg.model_copy(update={"envmap_camera_probe": False}), _bound_prior(capture)) is None


def test_tv_statistic_sees_rings_and_ignores_smooth_gradients():
    h = 32
    theta = (torch.arange(h) + 0.5) / h * torch.pi
    smooth = torch.exp(torch.cos(theta))[:, None, None].expand(h, 2 * h, 3)
    rings = smooth * (1.0 + 0.5 * torch.sin(12 * theta))[:, None, None]
    top = torch.zeros(h, 2 * h, dtype=torch.bool)
    top[: h // 2] = True
    assert log_total_variation(smooth, ~top) < 0.2 * log_total_variation(rings, ~top)
    assert ring_ratio(rings, top)["tv_unobserved"] > ring_ratio(smooth, top)["tv_unobserved"]
    assert torch.isnan(torch.tensor(log_total_variation(smooth, torch.zeros_like(top))))


LAMP = torch.tensor([0.0, 1.0, 2.0])  # behind the camera (it looks along -z): never in view
SWITCH_FRAME, FRAMES, FPS = 4, 8, 8.0


def _lamp_switching_off(x, t, d):
    v = LAMP - x
    dist = v.norm(dim=-1, keepdim=True)
    lobe = torch.exp(((d * (v / dist)).sum(-1, keepdim=True) - 1) / 0.05)
    on = (t < (SWITCH_FRAME - 0.5) / FPS).float()[:, None]
    return (0.2 + 0.1 * (d[:, 1:2] + 1) + 30 * lobe / dist**2 * on) * torch.tensor([1.0, 0.9, 0.7])


def test_out_of_view_switch_is_followed_and_static_stretches_stay_flat():
    cap = capture_from_arrays(torch.full((FRAMES, 36, 48, 3), 0.4), fps=FPS)  # the frames never show the lamp
    prior = KnownRadiancePrior(_lamp_switching_off)
    field = distill(cap, prior, small(work_height=36), uses_time=True, seed=0).field
    x = torch.zeros(1, 3)

    def brightness(env):
        return float(luminance(integrate(env.double())))

    with torch.no_grad():
        ours = [brightness(field.envmaps(x, torch.tensor([float(t)]), 16)[0]) for t in cap.times]
    truth = [brightness(prior.envmaps(x, float(t), 16)[0]) for t in cap.times]
    before, after = ours[:SWITCH_FRAME], ours[SWITCH_FRAME:]
    ratio = (sum(after) / len(after)) / (sum(before) / len(before))
    true_ratio = (sum(truth[SWITCH_FRAME:]) / len(after)) / (sum(truth[:SWITCH_FRAME]) / len(before))
    assert abs(ratio - true_ratio) <= 0.1, (ratio, true_ratio)  # measured 0.670 vs 0.667 (TV weight 0.1: 0.97)
    for stretch in (before, after):
        mean = sum(stretch) / len(stretch)
        assert max(abs(b / mean - 1) for b in stretch) <= 0.03, stretch  # measured 0.2 % and 0.1 %


def test_supervision_probes_are_in_front_of_the_scene_and_include_the_camera():
    cap = capture_from_arrays(torch.full((1, 36, 48, 3), 0.5))
    # the ones off the rays: tests/test_free_space.py
    cfg = small().distill.model_copy(update={"envmap_free_probes": 0})
    centers = supervision_probes(cap, 0, cfg, torch.Generator().manual_seed(0))
    assert centers.shape == (cfg.envmap_probe_count, 3)
    cam = cap.camera(0)
    assert torch.allclose(centers[-1], cam.position.float())
    u, v, z = cam.project(centers[:-1].double())
    depth = cap.depth[0][v.long().clamp(0, 35), u.long().clamp(0, 47)]
    assert bool((z > 0).all()) and bool((z < depth).all())


def test_bright_directions_find_a_one_pixel_source():
    maps = torch.full((2, 8, 16, 3), 0.1)
    maps[:, 3, 5] = 1e4  # one pixel holds ~99 % of the energy
    d = bright_directions(maps, 200, torch.Generator().manual_seed(0))
    from core.conventions import direction_to_equirect_pixel

    row, col = direction_to_equirect_pixel(d, 8)
    hit = (row.round() == 3) & (col.round() == 5)
    assert float(hit.float().mean()) > 0.9


def test_radiance_loss_is_finite_on_black_and_huge_targets_and_keeps_energy():
    pred = torch.tensor([[1e-6, 1e-6, 1e-6], [1e5, 1e5, 1e5]], requires_grad=True)
    target = torch.tensor([[0.0, 0.0, 0.0], [1e6, 1e6, 1e6]])
    loss = radiance_loss(pred, target, floor=1e-3, linear_weight=0.1)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(pred.grad).all()
    assert float(pred.grad[1].sum()) < 0  # the too-dim source is pushed up


def test_chroma_weight_penalises_colour_errors_only():
    target = torch.tensor([[1.0, 0.5, 0.25], [10.0, 10.0, 10.0]])
    grey = target * 2.0  # right colour, wrong brightness
    tinted = target * torch.tensor([2.0, 1.0, 1.0])  # wrong colour
    for pred in (grey, tinted):
        base = radiance_loss(pred, target, floor=1e-6, linear_weight=0.0)
        extra = radiance_loss(pred, target, floor=1e-6, linear_weight=0.0, chroma_weight=4.0) - base
        if pred is grey:
            assert abs(float(extra)) < 1e-6
        else:
            assert float(extra) > 0.5 * float(base)


def test_envmaps_supervision_needs_a_prior_that_answers_envmaps():
    from core.priors.base import Prior

    class BallsOnly(Prior):
        name = "balls-only"

        def __call__(self, request):
            return request.image

        def describe(self):
            return {"name": self.name}

    cap = capture_from_arrays(torch.full((1, 36, 48, 3), 0.5))
    with pytest.raises(ValueError, match="answers env maps"):
        distill(cap, BallsOnly(), small(iterations=1), uses_time=False)
    res = distill(cap, BallsOnly(), small(supervision="auto", iterations=2), uses_time=False)
    assert res.stats["supervision"] == "balls"
    res = distill(
        cap,
        KnownRadiancePrior(lambda x, t, d: torch.ones_like(d)),
        small(supervision="auto", iterations=2),
        uses_time=False,
    )
    assert res.stats["supervision"] == "envmaps"
    assert json.dumps(res.stats["field_config"])  # recorded in the artefact


def test_view_detail_is_bound_to_the_cameras_and_to_the_frames(spatial_scene):
    """Anchors at the camera centres; with a time input, one detail time knot per frame, or no
    detail at all with `view_detail_time_rank` 0 (a static detail would hold the frames'
    average fine structure where the lighting changes)."""
    _, capture = spatial_scene
    field = preset("draft").field
    assert field.view_detail_heights and field.view_detail_time_rank > 0
    static = with_view_detail(field.with_time(False), capture)
    assert static.view_detail_heights == field.view_detail_heights
    assert static.view_anchors == (tuple(capture.poses[0, :3, 3].double().tolist()),)
    video = capture_from_arrays(capture.frames.expand(5, -1, -1, -1))
    changing = with_view_detail(field.with_time(True), video)
    assert changing.view_detail_heights == field.view_detail_heights and changing.view_detail_time_knots == 5
    assert len(changing.view_anchors) == 1
    no_time_part = with_view_detail(field.with_time(True).model_copy(update={"view_detail_time_rank": 0}), video)
    assert no_time_part.view_detail_heights == () and no_time_part.view_anchors == ()


def _patch_switching_off():
    """8 frames of a static camera: a 6x8-pixel patch clipped white in frames 0-3, dark after."""
    frames = torch.full((FRAMES, 36, 48, 3), 0.4)
    patch = torch.zeros(36, 48, dtype=torch.bool)
    patch[12:18, 20:28] = True
    frames[:SWITCH_FRAME, patch] = 1.0
    frames[SWITCH_FRAME:, patch] = 0.1
    return capture_from_arrays(frames, fps=FPS), patch


def _at_patch_centre(field, cap, patch, frame):
    """Median over the patch's inner pixel rays of field / linearised frame at the camera."""
    from core.envmap import sample_envmap

    inner = patch.clone()
    inner[12] = inner[17] = inner[:, 20] = inner[:, 27] = False  # the edge blends with the walls
    cam = cap.camera(0)
    with torch.no_grad():
        env = field.envmaps(cam.position[None].float(), torch.tensor([float(cap.times[frame])]), 64)[0]
    pred = luminance(sample_envmap(env, cam.pixel_rays()[1][inner]))
    return float((pred / luminance(inverse_tonemap(cap.frames[frame])[inner])).median())


def test_a_light_switching_off_in_view_is_followed_at_the_camera():
    """The view detail's time part (rank maps x per-frame coefficients) lets the photographed
    region change with the frames: after the patch goes dark the field at the camera follows
    it; without the time part (rank 0: no detail for a field with a time input) it stays
    brighter."""
    cap, patch = _patch_switching_off()
    prior = ReprojectionPrior(env_height=16)
    prior.bind(cap, lighting_changes=True)
    ratios = {}
    for rank in (4, 0):
        # the property is the camera fit's, measured with the probe mix these thresholds were set
        # on (2 surface probes, none off the camera rays); at this budget the draft's mix blurs it
        # (seed 0: 1.94 vs 2.10 without the time part); at the draft's 600 steps
        # `python -m bench.in_view_switch` measures 2.33 vs 3.59 (median ray 1.32 vs 2.59)
        cfg = small(work_height=36, envmap_free_probes=0, envmap_surface_probes=2).with_overrides(
            {"field": {"view_detail_time_rank": rank}})
        field = distill(cap, prior, cfg, uses_time=True, seed=0).field
        ratios[rank] = [_at_patch_centre(field, cap, patch, f) for f in (1, 2, 6)]
    (before, steady, after), (_, _, after_without) = ratios[4], ratios[0]
    # after / frame at these 300 steps, seed 0: 3.15 vs 19.0 without the time part (seeds 1 / 2,
    # one-off runs: 2.61 / 1.71); with the log-averaged indoor fill before the energy profile 2.18 /
    # 2.04 / 1.92 vs 4.28 / 4.95 / 2.35: the unseen directions' level moves this short run's
    # convergence, while the draft's `bench.in_view_switch` stayed at 2.38x (median ray 1.35x;
    # with a static view detail it read 8.4x). Before the switch the field sits at the prior's clip-estimated radiance,
    # 12-14x
    # the clipped frame (5.5x without the time part). With the fill's source cap (core.priors.indoor_fill)
    # 3.52 / 2.09 / 2.75 (seeds 0 / 1 / 2) vs 19.0 without the time part; the draft's bench 2.29x (median ray 1.32x)
    assert after <= 4.0, ratios
    assert after <= 0.5 * after_without, ratios  # seed 0: 0.17 (seeds 1, 2: 0.14, 0.09)
    # a static stretch stays flat: 4.4 % with the draft's time gain (seed 0; 2.2 % without it; 5.6 %
    # before the gain shared the codes' TV penalty: docs/engine.md, "Time gain")
    assert abs(before / steady - 1) <= 0.05, ratios


@pytest.fixture(scope="module")
def temporal_scene(tmp_path_factory):
    """The simulator's `temporal` suite (a lamp in view dims; the ceiling panel switches off) at 128x96."""
    from core.sim.suites import temporal

    return simulated_scene(temporal(), (128, 96), tmp_path_factory.mktemp("temporal"))


def test_a_lamp_in_view_stays_a_lamp_at_held_out_probes(temporal_scene):
    """With emitters (the draft's) the lamp is found where it is and a held-out probe 1.3 m away
    after the panel switched off (the lamp lights it) sees it: matte / mirror nRMSE against the
    truth well below the field without emitters, the draft's observed surfaces on in both (which
    show the lamp where it stands but not its energy: seed 0 read 0.12 / 0.08 with emitters, 0.35 /
    0.19 without, maps asked at 32 rows; at 16, 0.14 / 0.12 against 0.30 / 0.12). The draft's full
    bench: bench.accuracy_probe."""
    spec, capture = temporal_scene
    prior = ReprojectionPrior(env_height=16)
    prior.bind(capture, lighting_changes=True)
    x, t = (4.568, 1.857, 1.862), 1.7264
    truth = render_envmap(spec, x, t, 16)
    scores, found = {}, None
    for emitters in (4, 0):
        result = distill(capture, prior, small(work_height=72, emitters=emitters), uses_time=True, seed=0)
        found = found or result.stats["emitters"]
        with torch.no_grad():  # asked at 32 rows, as a user would (at 16 the surfaces' splat is as sharp as a lobe)
            env = result.field.envmaps(torch.tensor([x]), torch.tensor([t]), 32)[0]
        scores[emitters] = three_sphere_metrics(resize_envmap(env, 16), truth, 32)
    lamp = next(e for e in spec.emitters if e.name == "lamp")
    assert len(found) == 1 and torch.allclose(torch.tensor(found[0]["centre"]), torch.tensor(lamp.center), atol=0.1), (
        found
    )
    assert scores[4]["matte"]["nrmse"] <= 0.6 * scores[0]["matte"]["nrmse"], scores
    assert scores[4]["mirror"]["nrmse"] <= 0.5 * scores[0]["mirror"]["nrmse"], scores
