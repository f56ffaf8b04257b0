"""The distillation loop recovers known fields, is reproducible and resumable, cancels
promptly and stays finite on hard inputs."""
import json

import pytest
import torch

from core.capture.load import capture_from_arrays
from core.chrome_ball import place_probe
from core.conventions import equirect_directions
from core.engine import run_job, trainer as trainer_module
from core.engine.distill import distill
from core.engine.params import JobParams
from core.engine.presets import preset
from core.engine.probes import sample_probes
from core.engine.progress import Cancelled, Reporter
from core.priors.known import KnownRadiancePrior
from core.priors.reprojection import ReprojectionPrior

H, W = 36, 48
LAMP = torch.tensor([1.2, 1.0, -2.5])  # inside the assumed box room (upper right, in front)
LAMP_RGB = torch.tensor([1.0, 0.9, 0.7])


def lamp_field(x, t, d, on=None):
    """Sky-ish gradient + a small lamp whose direction AND brightness depend on x
    (a lobe towards LAMP with inverse-square falloff)."""
    v = LAMP - x
    dist = v.norm(dim=-1, keepdim=True)
    lobe = torch.exp(((d * (v / dist)).sum(-1, keepdim=True) - 1) / 0.05)
    lamp = 30 * lobe / dist**2 * LAMP_RGB
    if on is not None:
        lamp = lamp * on(t)[:, None]
    return 0.2 + 0.1 * (d[:, 1:2] + 1) + lamp


def tiny(**kw):
    base = dict(work_height=H, checkpoint_every=1000, warmup_steps=5, fallback=False)  # the loop's mechanics
    base.update(kw)
    return preset("draft").with_overrides({"distill": base})


def held_out_probes(capture, cfg, frame=0, seed=123, rounds=3):
    g = torch.Generator().manual_seed(seed)
    xs = []
    for _ in range(rounds):
        px, dp = sample_probes(capture, frame, cfg.distill, g)
        xs += [place_probe(capture.camera(frame), px[n], float(dp[n]))[0] for n in range(px.shape[0])]
    return torch.stack(xs)


def log_rmse_facing_camera(pred, gt, xs, dirs):
    """log-radiance RMSE over directions on the camera's side of each probe: the directions
    a chrome ball shows well (the cone behind the ball is never observed)."""
    to_cam = -xs / xs.norm(dim=-1, keepdim=True)
    mask = (dirs[None] * to_cam[:, None]).sum(-1) > 0
    return float((((pred.log() - gt.log()) ** 2).mean(-1)[mask]).mean().sqrt())


def test_known_spatial_field_is_recovered_and_beats_a_constant():
    cap = capture_from_arrays(torch.full((1, H, W, 3), 0.4))
    cfg = tiny(iterations=200)
    res = distill(cap, KnownRadiancePrior(lamp_field), cfg, uses_time=False, seed=0)
    xs = held_out_probes(cap, cfg)
    h = 16
    dirs = equirect_directions(h).reshape(-1, 3)
    with torch.no_grad():
        pred = res.field.envmaps(xs, None, h).reshape(len(xs), -1, 3)
    gt = torch.stack([lamp_field(x.expand(dirs.shape[0], 3), None, dirs) for x in xs])
    err = log_rmse_facing_camera(pred, gt, xs, dirs)
    # the best spatially constant estimate (per-direction mean log radiance over the probes)
    const = gt.log().mean(0, keepdim=True).exp().expand_as(gt)
    err_const = log_rmse_facing_camera(const, gt, xs, dirs)
    assert err < 0.5, err  # stated error: log-RMSE < 0.5 over a ~2-decade range (0.39 measured)
    assert err < 0.75 * err_const, (err, err_const)


def test_light_switch_off_is_recovered_in_time():
    """A lamp that switches off between two frames. 400 steps: with the draft's time gain the
    codes take longer to learn a local switch (one run, on / off 1.5 at 200 steps, 8.6 at 400;
    8.0 at 200 without the gain): early on the gain takes part of the lamp's change for the
    whole room's (docs/engine.md, "Time gain")."""
    cap = capture_from_arrays(torch.full((2, H, W, 3), 0.4), fps=1.0)  # t = 0 s, 1 s

    def switch(x, t, d):
        return lamp_field(x, t, d, on=lambda t: (t < 0.5).float())

    res = distill(cap, KnownRadiancePrior(switch), tiny(iterations=400), uses_time=True, seed=0)
    x = torch.tensor([[0.0, 0.0, -1.5]])
    d = (LAMP - x[0]) / (LAMP - x[0]).norm()
    with torch.no_grad():
        on = res.field(x, torch.tensor([0.0]), d[None])[0, 0]
        off = res.field(x, torch.tensor([1.0]), d[None])[0, 0]
    true_on = switch(x, torch.tensor([0.0]), d[None])[0, 0]
    true_off = switch(x, torch.tensor([1.0]), d[None])[0, 0]
    assert true_on / true_off > 10
    assert on / off > 4, (float(on), float(off))


def test_a_time_fields_lattice_stays_frozen_until_its_start_step():
    """The room lattice of a field with a time input trains only from `time_lattice_start` of
    the steps on: started after the last step it is still zero; started halfway it moved."""
    cap = capture_from_arrays(torch.rand(2, H, W, 3, generator=torch.Generator().manual_seed(2)))
    moved = {}
    for start in (0.95, 0.5):
        prior = ReprojectionPrior(env_height=8)
        prior.bind(cap)
        field = distill(cap, prior, tiny(iterations=10, time_lattice_start=start), uses_time=True, seed=0).field
        moved[start] = float(field.room_lattice.maps.detach().abs().max())
    assert moved[0.95] == 0.0 and moved[0.5] > 0.0, moved


def _weights(field):
    return {k: v.clone() for k, v in field.state_dict().items()}


def test_same_seed_same_weights_and_other_seed_differs():
    cap = capture_from_arrays(torch.rand(2, H, W, 3, generator=torch.Generator().manual_seed(0)))
    runs = []
    for seed in (7, 7, 8):
        prior = ReprojectionPrior(env_height=8)
        prior.bind(cap)
        runs.append(_weights(distill(cap, prior, tiny(iterations=6), uses_time=True, seed=seed).field))
    assert all(torch.equal(runs[0][k], runs[1][k]) for k in runs[0])
    assert not all(torch.equal(runs[0][k], runs[2][k]) for k in runs[0])


def test_resume_from_checkpoint_equals_uninterrupted_run(tmp_path):
    cap = capture_from_arrays(torch.rand(2, H, W, 3, generator=torch.Generator().manual_seed(1)))
    cfg = tiny(iterations=10, checkpoint_every=4)

    def run(ckpt, cancel_after=None):
        prior = ReprojectionPrior(env_height=8)
        prior.bind(cap)
        done = []
        rep = Reporter(
            lambda p: done.append(p.iteration),
            (lambda: bool(done) and done[-1] >= cancel_after) if cancel_after else None,
        )
        return distill(cap, prior, cfg, uses_time=True, seed=3, reporter=rep, checkpoint_dir=ckpt)

    full = run(None)
    with pytest.raises(Cancelled):
        run(tmp_path, cancel_after=6)  # checkpoint written at step 4, killed at 6
    assert json.loads((tmp_path / "checkpoint.json").read_text())["step"] == 4
    resumed = run(tmp_path)
    assert resumed.resumed_from == 4
    a, b = _weights(full.field), _weights(resumed.field)
    assert all(torch.equal(a[k], b[k]) for k in a)  # bit-identical on CPU
    assert resumed.losses == pytest.approx(full.losses)


def test_mismatched_checkpoint_is_ignored(tmp_path):
    cap = capture_from_arrays(torch.rand(1, H, W, 3))
    prior = ReprojectionPrior(env_height=8)
    prior.bind(cap)
    distill(cap, prior, tiny(iterations=4, checkpoint_every=2), uses_time=False, seed=0, checkpoint_dir=tmp_path)
    res = distill(cap, prior, tiny(iterations=4, checkpoint_every=2), uses_time=False, seed=1, checkpoint_dir=tmp_path)
    assert res.resumed_from == 0


def test_cancel_raises_promptly():
    cap = capture_from_arrays(torch.rand(1, H, W, 3))
    prior = ReprojectionPrior(env_height=8)
    prior.bind(cap)
    steps = []
    rep = Reporter(lambda p: steps.append(p.iteration), lambda: len(steps) >= 2)
    with pytest.raises(Cancelled):
        distill(cap, prior, tiny(iterations=500), uses_time=False, reporter=rep)
    assert len(steps) == 2  # checked after every step


def _finite_field(res):
    x = torch.tensor([[0.0, 0.0, -1.0]])
    with torch.no_grad():
        env = res.field.envmaps(x, torch.zeros(1) if res.field.uses_time else None, 8)
    assert all(torch.isfinite(v).all() for v in res.field.state_dict().values())
    assert torch.isfinite(env).all() and (env > 0).all()
    assert all(torch.isfinite(torch.tensor(l)) for l in res.losses)


@pytest.mark.parametrize("case", ["tiny_bright_light", "all_dark", "saturated", "depth_holes", "one_frame_video"])
def test_hard_cases_stay_finite(case):
    frames = torch.full((2, H, W, 3), 0.4)
    depth = None
    prior = ReprojectionPrior(env_height=8)
    if case == "tiny_bright_light":
        def fn(x, t, d):  # 1e4 x the room in a ~1 degree lobe
            return (
                0.1 + 1e3 * torch.exp(((d * torch.tensor([0.0, 1.0, 0.0])).sum(-1, keepdim=True) - 1) / 1e-4)
            ).expand(-1, 3)

        prior = KnownRadiancePrior(fn)
    elif case == "all_dark":
        frames = torch.zeros(2, H, W, 3)
    elif case == "saturated":
        frames = torch.ones(2, H, W, 3)
    elif case == "depth_holes":
        depth = torch.full((2, H, W), 3.0)
        depth[:, ::2] = float("nan")
        depth[:, :, :10] = 0.0
    elif case == "one_frame_video":
        frames = frames[:1]
    cap = capture_from_arrays(frames, depth)
    prior.bind(cap)
    res = distill(cap, prior, tiny(iterations=8, ev_sweep_fraction=0.5), uses_time=cap.num_frames > 1)
    _finite_field(res)


def test_probes_at_the_image_border(monkeypatch):
    cap = capture_from_arrays(torch.full((1, H, W, 3), 0.5))
    corners = torch.tensor([[0.5, 0.5], [W - 0.5, 0.5], [0.5, H - 0.5], [W - 0.5, H - 0.5]], dtype=torch.float64)

    def border(capture, frame, cfg, gen):
        return corners[: cfg.n_probes], torch.full((cfg.n_probes,), 2.0, dtype=torch.float64)

    monkeypatch.setattr(trainer_module, "sample_probes", border)
    prior = ReprojectionPrior(env_height=8)
    prior.bind(cap)
    res = distill(cap, prior, tiny(iterations=4, n_probes=4), uses_time=False)
    _finite_field(res)
    assert res.losses[0] > 0  # the clipped balls still produced a loss


def test_sample_probes_are_spread_and_in_front_of_the_surface():
    cap = capture_from_arrays(torch.full((1, H, W, 3), 0.5))
    cfg = tiny()
    px, dp = sample_probes(cap, 0, cfg.distill, torch.Generator().manual_seed(0))
    assert px.shape == (9, 2)
    # stratified: one probe per cell of a 4 x 3 grid, so no two share a cell
    cells = {(int(u // (W / 4)), int(v // (H / 3))) for u, v in px.tolist()}
    assert len(cells) == 9
    scene = cap.depth[0, px[:, 1].long(), px[:, 0].long()].double()
    assert (dp >= 0.5 * scene - 1e-9).all() and (dp < 0.95 * scene).all()
    for n in range(9):  # the ball's far side stays in front of the surface
        c, r = place_probe(cap.camera(0), px[n], float(dp[n]))
        assert float(-c[2]) + r <= float(scene[n]) * (1 + 1e-6)


def test_run_job_writes_a_loadable_artefact(tmp_path):
    from core.fields.stored.artefact import LightFieldArtefact
    from core.io import write_png

    img = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(0)).numpy()
    write_png(tmp_path / "in.png", img)
    events = []
    with pytest.warns(UserWarning):
        out = run_job(tmp_path / "in.png", None, JobParams(seed=1), tmp_path / "art", progress=events.append,
                      config=tiny(iterations=5)).path
    art = LightFieldArtefact.load(out)
    env, flags = art.envmap(torch.tensor([0.0, 0.0, -1.0]), None, 8)
    assert torch.isfinite(env).all()
    meta = json.loads((out / "lightfield.json").read_text())
    assert meta["temporal"]["uses_time"] is False and not art.uses_time
    assert meta["capture"]["depth_source"].startswith("assumed")
    assert meta["training"]["perceptual"]["kind"] == "ssim"
    assert meta["prior"]["name"] == "reprojection" and meta["simulated"]["point_cloud_builds"] == 1
    assert len(meta["training"]["loss_curve"]) == 5
    assert meta["training"]["surfaces"] == {"points": H * W, "knots": 1}  # every pixel: fewer than the draft's 16384
    assert meta["training"]["device"] == ("cuda" if torch.cuda.is_available() else "cpu")
    assert {"loading", "prior", "field_render", "optimisation"} <= set(meta["training"]["stage_timings"])
    stages = [e.stage for e in events]
    assert stages[0] == "loading" and stages[-1] == "done"
    assert all(a.fraction <= b.fraction + 1e-9 for a, b in zip(events, events[1:]))


@pytest.mark.slow  # importing diffusers/transformers dominates
def test_run_job_with_the_tiny_diffusion_prior(tmp_path):
    """The diffusion prior plugs in unchanged (a tiny random local model: contract, not quality)."""
    from core.io import write_png
    from core.priors.diffusion import build_tiny_model

    weights = build_tiny_model(tmp_path / "tiny")
    write_png(tmp_path / "in.png", torch.rand(H, W, 3, generator=torch.Generator().manual_seed(0)).numpy())
    with pytest.warns(UserWarning):
        out = run_job(tmp_path / "in.png", None, JobParams(prior="diffusion", prior_weights=str(weights)),
                      tmp_path / "art", config=tiny(iterations=2)).path
    meta = json.loads((out / "lightfield.json").read_text())
    assert meta["prior"]["name"] == "diffusion" and len(meta["training"]["loss_curve"]) == 2
    assert all(torch.isfinite(torch.tensor(meta["training"]["loss_curve"])))


# ---------------------------------------------------------------------------------------
# Device
# ---------------------------------------------------------------------------------------
def test_explicit_cpu_device_equals_the_default_here(monkeypatch):
    from core.device import resolve_device

    monkeypatch.delenv("LIGHTFIELD_DEVICE", raising=False)
    if torch.cuda.is_available():
        pytest.skip("'auto' is CUDA on this machine")
    assert resolve_device("auto") == torch.device("cpu")
    cap = capture_from_arrays(torch.rand(2, H, W, 3, generator=torch.Generator().manual_seed(4)))
    runs = []
    for device in ("auto", "cpu"):
        prior = ReprojectionPrior(env_height=8)
        prior.bind(cap)
        result = distill(cap, prior, tiny(iterations=6, device=device), uses_time=True, seed=5)
        assert result.stats["device"] == "cpu"
        runs.append(_weights(result.field))
    assert all(torch.equal(runs[0][k], runs[1][k]) for k in runs[0])


def test_cuda_without_cuda_is_a_clear_error(monkeypatch, tmp_path):
    from core.device import DeviceError, resolve_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.delenv("LIGHTFIELD_DEVICE", raising=False)
    with pytest.raises(DeviceError, match=r"DistillConfig\.device='cuda'.*CUDA is not available"):
        resolve_device("cuda")
    monkeypatch.setenv("LIGHTFIELD_DEVICE", "cuda:1")  # the environment overrides the config
    with pytest.raises(DeviceError, match=r"LIGHTFIELD_DEVICE='cuda:1'"):
        resolve_device("cpu")
    monkeypatch.setenv("LIGHTFIELD_DEVICE", "tpu")
    with pytest.raises(DeviceError, match=r"LIGHTFIELD_DEVICE='tpu'"):
        resolve_device("auto")
    monkeypatch.setenv("LIGHTFIELD_DEVICE", "cpu")
    assert resolve_device("cuda") == torch.device("cpu")
    # run_job refuses before reading its input (the input does not even exist)
    monkeypatch.delenv("LIGHTFIELD_DEVICE")
    with pytest.raises(DeviceError, match="device"):
        run_job(tmp_path / "missing.png", None, JobParams(), tmp_path / "art", config=tiny(iterations=2, device="cuda"))
    with pytest.raises(ValueError, match="device"):  # malformed values are refused by the schema too
        tiny(device="gpu")


def test_away_from_the_camera_the_field_shows_what_its_prior_saw_with_parallax():
    """A photo of a red / blue wall 2 m away: after even 5 steps the field at probes 1.3 m or more
    from the camera (beyond the view detail's reach) answers every direction its prior saw as the prior does (the
    observed
    surfaces, core.fields.components.surfaces), and the red-blue edge moves with the probe."""
    frame = torch.zeros(H, W, 3)
    frame[:, : W // 2] = torch.tensor([0.8, 0.1, 0.1])
    frame[:, W // 2:] = torch.tensor([0.1, 0.1, 0.8])
    cap = capture_from_arrays(frame, torch.full((H, W), 2.0))
    cfg = tiny(iterations=5)
    prior = ReprojectionPrior(env_height=cfg.distill.envmap_height)
    prior.bind(cap, lighting_changes=False)
    field = distill(cap, prior, cfg, uses_time=False, seed=0).field
    h = cfg.distill.envmap_height
    edges = []
    for x in ([-1.0, 0.0, -0.9], [1.0, 0.0, -0.9], [0.0, 0.8, -1.1]):
        xs = torch.tensor([x])
        with torch.no_grad():
            got = field.envmaps(xs, None, h)[0]
        want, seen = prior.observed_envmaps(xs, 0.0)
        assert int(seen.sum()) > 50
        # the same points, in float32 here (float64 in the prior): a point on a pixel border may swap pixels
        assert torch.allclose(got[seen[0]], want[0][seen[0]], rtol=2e-3), x
        edges.append(float(torch.nonzero((got[h // 2, :, 2] > got[h // 2, :, 0]) & seen[0, h // 2]).min()))
    assert edges[0] != edges[1]  # the edge is at another column from another probe


def test_run_job_records_a_lamp_in_the_photo_as_an_emitter(tmp_path):
    """A dim photo with a small clipped spot: the job finds one emitter, records it in the
    artefact's metadata, and the saved field's map at the camera is brightest towards it."""
    from core.capture.load import load_capture
    from core.conventions import equirect_directions
    from core.exposure import luminance
    from core.fields.stored.artefact import LightFieldArtefact
    from core.io import write_png

    img = torch.full((H, W, 3), 0.15)
    img[10:12, 30:32] = 1.0
    write_png(tmp_path / "lamp.png", img.numpy())
    with pytest.warns(UserWarning):
        out = run_job(tmp_path / "lamp.png", None, JobParams(seed=0), tmp_path / "art", config=tiny(iterations=5)).path
    meta = json.loads((out / "lightfield.json").read_text())
    assert len(meta["training"]["emitters"]) == 1, meta["training"]["emitters"]
    art = LightFieldArtefact.load(out)
    env, _ = art.envmap(torch.zeros(3), None, 32)
    peak = equirect_directions(32).reshape(-1, 3)[luminance(env).flatten().argmax()]
    cap = load_capture(tmp_path / "lamp.png", None, JobParams(seed=0))
    spot = cap.camera(0).pixel_rays()[1][10:12, 30:32].reshape(-1, 3).mean(0)
    assert float(peak @ (spot / spot.norm())) > 0.95


def test_a_room_wide_dimming_is_followed_everywhere_with_the_time_gain():
    """A light that dims the whole room (a dimmer, daylight fading) is one number per frame for
    the time gain: every held-out probe dims as the truth, alike (without the gain, one run:
    0.26-0.34 for the truth's 0.30, the codes' change differing from place to place, a 31 %
    spread; with it, 0.302-0.312 on one machine, 4.02 % from the truth at worst, where the
    machine it was written on stayed under 4 %: the bound leaves room for CPU kernels, not for
    the codes' scatter)."""
    cap = capture_from_arrays(torch.full((4, H, W, 3), 0.4), fps=1.0)  # t = 0, 1, 2, 3 s
    scale = torch.tensor([1.0, 0.7, 0.45, 0.3])

    def dimming(x, t, d):
        return lamp_field(x, t, d) * scale[t.round().long().clamp(0, 3)][:, None]

    cfg = tiny(iterations=200)
    res = distill(cap, KnownRadiancePrior(dimming), cfg, uses_time=True, seed=0)
    assert res.field.time_gain is not None
    xs = held_out_probes(cap, cfg)
    with torch.no_grad():
        first = res.field.envmaps(xs, torch.zeros(len(xs)), 16).mean((1, 2, 3))
        last = res.field.envmaps(xs, torch.full((len(xs),), 3.0), 16).mean((1, 2, 3))
    ratio = last / first
    assert float((ratio / 0.3 - 1.0).abs().max()) < 0.06, ratio.tolist()
    assert float(ratio.max() / ratio.min() - 1.0) < 0.06, ratio.tolist()


def test_the_ball_loop_keeps_its_field_without_a_time_gain():
    """The time gain is the radiance loop's: the paper's ball loop is left as it was."""
    cap = capture_from_arrays(torch.full((2, H, W, 3), 0.4), fps=1.0)
    cfg = tiny(iterations=2, supervision="balls")
    assert cfg.distill.time_gain
    res = distill(cap, KnownRadiancePrior(lamp_field), cfg, uses_time=True, seed=0)
    assert res.field.time_gain is None and res.stats["field_config"]["time_gain_knots"] == 0
