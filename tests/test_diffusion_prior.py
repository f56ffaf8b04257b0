"""The diffusion prior as a distillation target, on the tiny random model (CPU).

The tiny model is loaded through the same local loader as real weights; its outputs are
noise-like, so these tests check the plumbing: exposure embedding, guidance, schedule,
masking, determinism and error handling.
"""
from __future__ import annotations

import math
import socket

import pytest
import torch

from core.camera import Camera, Intrinsics, identity_pose
from core.priors.base import PriorError, PriorRequest, ProbeGeometry
from core.priors.diffusion import DiffusionPrior, ModelCard, build_tiny_model
from core.priors.diffusion.conditioning import depth_to_control, model_size
from core.priors.diffusion.tiny import TinyConfig

H, W = 40, 56  # deliberately not the model's 32 x 32 nor a multiple of 16

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/diffusion_fixtures.py


@pytest.fixture(scope="module")
def single_ball_prior(tmp_path_factory):
    d = build_tiny_model(tmp_path_factory.mktemp("tiny_single"), TinyConfig(resolution=(32, 32), multi_ball=False))
    return DiffusionPrior.from_pretrained(d)


def disc(cy, cx, r):
    """Anti-aliased disc coverage (4x4 supersampled) so mask edges are soft like the engine's."""
    s = 4
    yy, xx = torch.meshgrid(
        (torch.arange(H * s) + 0.5) / s, (torch.arange(W * s) + 0.5) / s, indexing="ij"
    )
    inside = (((yy - cy) ** 2 + (xx - cx) ** 2) < r * r).float()
    return inside.view(H, s, W, s).mean(dim=(1, 3))


def make_request(tau=0.5, ev=-1.0, guidance=3.0, seed=0, steps=None, image=None, depth=None, masks=None):
    g = torch.Generator().manual_seed(0)
    image = torch.rand(3, H, W, generator=g) if image is None else image
    masks = torch.stack([disc(12, 14, 6.5), disc(26, 40, 8.0)]) if masks is None else masks
    depth = torch.linspace(1.0, 4.0, H)[:, None].expand(H, W).clone() if depth is None else depth
    cam = Camera(Intrinsics.from_hfov(W, H), identity_pose())
    n = masks.shape[0]
    probes = ProbeGeometry(torch.zeros(n, 3), torch.ones(n), torch.zeros(n, 2), cam, 0, 0.0)
    return PriorRequest(
        image=image, ball_masks=masks, depth=depth, ev=ev, tau=tau,
        steps=math.ceil(10 * tau) if steps is None else steps, guidance_scale=guidance, probes=probes,
        generator=torch.Generator().manual_seed(seed),
    )


# -- exposure conditioning -------------------------------------------------------------------
def test_exposure_embedding_hits_both_anchors_and_clamps(prior):
    cond = prior.conditioner
    ev_min = prior.components.card.ev_min
    z0, zmin, zmid = cond(0.0), cond(ev_min), cond(ev_min / 2)
    assert not torch.allclose(cond.max.tokens, cond.min.tokens)  # the prompts differ, so the test can fail
    torch.testing.assert_close(z0.tokens, cond.max.tokens, rtol=0, atol=0)
    torch.testing.assert_close(zmin.tokens, cond.min.tokens, rtol=1e-6, atol=1e-6)
    assert cond.max.pooled is not None  # CLIPTextModel has a pooled output: it must follow too
    torch.testing.assert_close(z0.pooled, cond.max.pooled, rtol=0, atol=0)
    torch.testing.assert_close(zmin.pooled, cond.min.pooled, rtol=1e-6, atol=1e-6)
    # linear in ev: the midpoint is the average of the anchors
    torch.testing.assert_close(zmid.tokens, 0.5 * (cond.max.tokens + cond.min.tokens), rtol=1e-5, atol=1e-6)
    # outside [ev_min, 0]: clamped, never extrapolated
    torch.testing.assert_close(cond(3.0).tokens, z0.tokens)
    torch.testing.assert_close(cond(ev_min - 7.0).tokens, zmin.tokens)
    # a batch of EVs gives one embedding per EV
    batch = cond([0.0, ev_min])
    assert batch.tokens.shape[0] == 2
    torch.testing.assert_close(batch.tokens[1:], zmin.tokens)


def test_null_embedding_is_the_empty_prompt_and_differs_from_zeta(prior):
    cond = prior.conditioner
    assert not torch.allclose(cond.null_embedding().tokens, cond(0.0).tokens)
    assert cond.null_embedding(3).tokens.shape[0] == 3


# -- guidance ----------------------------------------------------------------------------------
def test_guidance_one_is_the_conditional_branch_alone(prior, monkeypatch):
    """At g = 1 the null (CFG) embedding plays no part; at g = 3 it does (so the test can fail)."""
    from core.priors.diffusion.exposure import ExposureEmbedding

    cond = prior.conditioner
    garbage = ExposureEmbedding(torch.randn_like(cond.null.tokens) * 5, torch.randn_like(cond.null.pooled))
    for g, null_matters in ((1.0, False), (3.0, True)):
        base = prior(make_request(guidance=g))
        with monkeypatch.context() as m:
            m.setattr(cond, "null", garbage)
            swapped = prior(make_request(guidance=g))
        assert bool((base - swapped).abs().max() > 1e-4) == null_matters


def test_batched_cfg_equals_separate_branches(prior):
    """uncond + g (cond - uncond) computed in one batched call equals two separate calls."""
    req = make_request()
    coverage = req.ball_masks.sum(0).clamp(max=1)[None]
    c, latents = prior.condition(req.image, coverage, req.depth, req.ev)
    den = prior.denoiser
    scheduler, timesteps = den.schedule(0.5, 5)
    t = timesteps[0]
    x = torch.randn(latents.shape, generator=torch.Generator().manual_seed(0))
    guided = den.predict_noise(scheduler, x, t, c, 2.5)
    text = den.predict_noise(scheduler, x, t, c, 1.0)
    from dataclasses import replace

    uncond = den.predict_noise(scheduler, x, t, replace(c, embedding=c.null_embedding), 1.0)
    torch.testing.assert_close(guided, uncond + 2.5 * (text - uncond), rtol=1e-4, atol=1e-5)


# -- schedule ----------------------------------------------------------------------------------
@pytest.mark.parametrize("tau", [0.05, 0.31, 0.7, 1.0])
def test_denoising_steps_follow_ceil_10_tau(prior, tau):
    from core.engine.config import DistillConfig

    steps = DistillConfig.steps_for_tau(tau)
    assert steps == math.ceil(10 * tau)
    seen = []
    handle = prior.components.unet.register_forward_pre_hook(lambda m, args: seen.append(int(args[1])))
    try:
        prior(make_request(tau=tau, steps=steps, guidance=3.0))
    finally:
        handle.remove()
    assert len(seen) == steps  # one UNet call per step: both CFG branches share a batch
    total = prior.components.scheduler.config.num_train_timesteps
    assert abs(seen[0] - tau * total) <= total / (steps / tau) + 1  # starts at ~ tau * T
    assert all(a > b for a, b in zip(seen, seen[1:]))  # strictly decreasing
    assert seen[-1] <= total / (steps / tau) + 1  # ends near t = 0


# -- masking -----------------------------------------------------------------------------------
@pytest.mark.parametrize("which", ["multi", "single"])
def test_pixels_outside_the_masks_are_unchanged(prior, single_ball_prior, which):
    p = prior if which == "multi" else single_ball_prior
    req = make_request(tau=0.6)
    out = p(req)
    outside = req.ball_masks.sum(0) == 0
    assert out.shape == req.image.shape and out.dtype == torch.float32
    assert torch.equal(out[:, outside], req.image[:, outside])
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    inside = req.ball_masks.sum(0) > 0.99
    assert (out[:, inside] - req.image[:, inside]).abs().mean() > 1e-3  # the balls were repainted


def test_no_balls_or_zero_tau_returns_the_input(prior):
    req = make_request(masks=torch.zeros(2, H, W))
    assert torch.equal(prior(req), req.image)
    req = make_request(tau=0.0, steps=0)
    assert torch.equal(prior(req), req.image)


def test_hard_inputs_stay_finite(prior):
    depth = torch.full((H, W), float("nan"))
    depth[5:9, 5:9] = 1e-9
    depth[20:, :] = float("inf")
    image = torch.ones(3, H, W)
    req = make_request(image=image, depth=depth, masks=disc(20, 28, 0.6)[None], ev=-40.0, tau=1.0)
    out = prior(req)
    assert torch.isfinite(out).all()
    assert torch.equal(out[:, req.ball_masks[0] == 0], image[:, req.ball_masks[0] == 0])


def test_same_seed_same_output_different_seed_different(prior):
    a = prior(make_request(seed=7))
    b = prior(make_request(seed=7))
    c = prior(make_request(seed=8))
    assert torch.equal(a, b)
    assert (a - c).abs().max() > 1e-4


def test_bad_request_shapes_raise_prior_error(prior):
    req = make_request()
    req.depth = torch.ones(H + 1, W)
    with pytest.raises(PriorError, match="request.depth"):
        prior(req)
    req = make_request(tau=1.5)
    with pytest.raises(PriorError, match="tau"):
        prior(req)


# -- conditioning helpers ------------------------------------------------------------------------
def test_depth_control_is_normalised_inverse_depth():
    depth = torch.tensor([[1.0, 2.0, 4.0, float("nan")], [0.0, -1.0, float("inf"), 8.0]])
    ctl = depth_to_control(depth)
    assert ctl.shape == (3, 2, 4) and torch.equal(ctl[0], ctl[2])
    c = ctl[0]
    assert c[0, 0] > c[0, 1] > c[0, 2] > c[1, 3]  # near is bright
    assert c.max() <= 1 and c.min() >= 0
    assert torch.equal(c[0, 3], torch.tensor(0.0)) and torch.equal(c[1, :3], torch.zeros(3))  # invalid -> far
    assert torch.allclose(depth_to_control(torch.full((3, 3), 2.0)), torch.full((3, 3, 3), 0.5))
    assert torch.equal(depth_to_control(torch.full((3, 3), float("nan"))), torch.zeros(3, 3, 3))
    wide = torch.logspace(-6, 6, 100).reshape(10, 10)
    assert torch.isfinite(depth_to_control(wide)).all()


@pytest.mark.parametrize("hw", [(480, 640), (1080, 1920), (1000, 300), (17, 5)])
def test_model_size_keeps_aspect_and_pixel_count(hw):
    h, w = hw
    mh, mw = model_size(h, w, (512, 512), 64)
    assert mh % 64 == 0 and mw % 64 == 0 and mh >= 64 and mw >= 64
    if min(h, w) / max(h, w) > 0.25:
        assert abs(mh * mw / 512**2 - 1) < 0.3
        assert abs((mw / mh) / (w / h) - 1) < 0.2


# -- loading -------------------------------------------------------------------------------------
@pytest.fixture()
def no_network(monkeypatch):
    def refuse(*a, **k):
        raise AssertionError("network access attempted")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)


def test_hub_id_is_refused_without_network(no_network):
    with pytest.raises(PriorError, match="not an existing local directory.*hub id"):
        DiffusionPrior.from_pretrained("stabilityai/stable-diffusion-2-inpainting")


def test_missing_sub_model_or_card_is_named(tiny_dir, tmp_path, no_network):
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(tiny_dir, broken)
    shutil.rmtree(broken / "controlnet")
    with pytest.raises(PriorError, match="controlnet/config.json"):
        DiffusionPrior.from_pretrained(broken)
    shutil.copytree(tiny_dir / "controlnet", broken / "controlnet")
    (broken / "lightfield_prior.json").unlink()
    with pytest.raises(PriorError, match="lightfield_prior.json"):
        DiffusionPrior.from_pretrained(broken)
    ModelCard(ev_min=-5.0).save(broken)
    card = (broken / "lightfield_prior.json").read_text().replace("-5.0", "2.0")
    (broken / "lightfield_prior.json").write_text(card)
    with pytest.raises(PriorError, match="ev_min"):
        DiffusionPrior.from_pretrained(broken)
    with pytest.raises(PriorError, match="dtype"):
        DiffusionPrior.from_pretrained(tiny_dir, dtype="float8")
    with pytest.raises(PriorError, match="float16 is not supported on CPU"):
        DiffusionPrior.from_pretrained(tiny_dir, device="cpu", dtype="fp16")


def test_pickled_weights_are_refused(tiny_dir, tmp_path, no_network):
    import shutil

    pickled = tmp_path / "pickled"
    shutil.copytree(tiny_dir, pickled)
    (pickled / "unet" / "diffusion_pytorch_model.safetensors").rename(pickled / "unet" / "diffusion_pytorch_model.bin")
    with pytest.raises(PriorError, match="cannot load prior weights"):
        DiffusionPrior.from_pretrained(pickled)


def test_registry_builds_the_diffusion_prior(tiny_dir):
    from core.priors.registry import build_prior

    p = build_prior("diffusion", {"weights": str(tiny_dir)})
    assert isinstance(p, DiffusionPrior)
    d = p.describe()
    assert d["name"] == "diffusion" and d["card"]["multi_ball"] is True and d["dtype"] == "float32"
    with pytest.raises(PriorError, match="prior-weights"):
        build_prior("diffusion")


def test_registry_passes_the_profile_and_the_worker_keeps_one_prior_per_profile(tiny_dir):
    from core.priors.registry import build_prior
    from worker.prior_cache import cached_prior

    assert (
        build_prior("diffusion", {"weights": str(tiny_dir), "profile": "diffusionlight"}).profile.name
        == "diffusionlight"
    )
    assert build_prior("diffusion", {"weights": str(tiny_dir)}).profile.name == "paper"  # the card's
    with pytest.raises(PriorError, match="profile"):
        build_prior("diffusion", {"weights": str(tiny_dir), "profile": "authors"})
    paper = cached_prior("diffusion", {"weights": str(tiny_dir), "profile": "paper"})
    assert cached_prior("diffusion", {"weights": str(tiny_dir), "profile": "paper"}) is paper
    seed = cached_prior("diffusion", {"weights": str(tiny_dir), "profile": "seed"})
    assert seed is not paper and seed.profile.name == "seed"
