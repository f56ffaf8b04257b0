"""The `seed` profile computes what the authors' released code computes (tiny random model).

tests/authors_reference.py re-derives their denoising step and conditioning from reading
ORionTMT/Sig25_4DLighting; here both run on the same inputs and generator and must agree
tensor by tensor (ControlNet input, CFG-rescaled output of every sub-step, latents of every
sub-step, the decoded target) to float tolerance. The frame is already at the model size,
so the canvas is the identity and nothing is resampled on either side.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from authors_reference import reference_control, reference_pipeline, reference_prompts, reference_target
from core.camera import Camera, Intrinsics, identity_pose
from core.conventions import tonemap
from core.priors.base import PriorRequest, ProbeGeometry
from core.priors.diffusion.loading import load_components
from core.priors.diffusion.prior import DiffusionPrior, control_inputs
from core.priors.diffusion.seed import SeedTrace, authors_substeps

pytestmark = pytest.mark.usefixtures("one_thread")
S = 32  # tiny model resolution = frame size


@pytest.fixture(scope="module")
def seed_prior(tiny_dir):
    return DiffusionPrior(load_components(tiny_dir), profile="seed")


def _scene():
    cam = Camera(Intrinsics.from_hfov(S, S, 60.0), identity_pose())
    g = torch.Generator().manual_seed(3)
    linear = torch.rand(S, S, 3, generator=g) * 1.5
    # balls stay behind the nearest scene point: their z = U(1, 1/disparity) >= 1 guarantees it there
    # (nearer, their uint8 conversion would wrap around; ours clamps to white)
    background = torch.linspace(1.5, 5.0, S)[:, None].expand(S, S).clone()
    background[:6, :6] = float("nan")  # invalid depth -> far, as the engine's captures may have
    pix = [(9.5, 10.5), (22.5, 20.5)]
    depths = [1.8, 2.6]
    centres, radii, masks = [], [], []
    yy, xx = torch.meshgrid(torch.arange(S) + 0.5, torch.arange(S) + 0.5, indexing="ij")
    for (u, v), d in zip(pix, depths):
        from core.chrome_ball import place_probe

        c, r = place_probe(cam, torch.tensor([u, v], dtype=torch.float64), d, 0.25)
        centres.append(c)
        radii.append(r)
        masks.append(((xx - u) ** 2 + (yy - v) ** 2 < 3.6 ** 2).float())
    masks = torch.stack(masks)
    masks[1] = masks[1] * (1 - masks[0])  # mutual occlusion: coverages partition
    probes = ProbeGeometry(torch.stack(centres).float(), torch.tensor(radii, dtype=torch.float32),
                           torch.tensor(pix, dtype=torch.float32), cam, 0, 0.0)
    return cam, linear, background, masks, probes


def _request(tau, ev, guidance, seed):
    cam, linear, background, masks, probes = _scene()
    balls = torch.rand(3, S, S, generator=torch.Generator().manual_seed(5))
    frame = tonemap(linear, ev).permute(2, 0, 1)
    cover = masks.sum(0).clamp(max=1)
    image = (1 - cover) * frame + cover * balls
    depth = torch.where(cover > 0, torch.full_like(background, 1.9), background)
    return PriorRequest(image=image, ball_masks=masks, depth=depth, ev=ev, tau=tau, steps=math.ceil(10 * tau),
                        guidance_scale=guidance, probes=probes, generator=torch.Generator().manual_seed(seed),
                        extras={"frame_linear": linear, "depth_background": background})


@pytest.mark.parametrize("tau,guidance", [(0.45, 12.5), (0.08, 12.5), (0.73, 1.0)])
def test_seed_profile_matches_the_authors_step(seed_prior, tau, guidance):
    ev = -1.5
    req = _request(tau, ev, guidance, seed=11)
    image = req.image.float()
    masks = req.ball_masks
    coverage = masks.sum(0).clamp(max=1)
    canvas = seed_prior.canvas(S, S)
    assert canvas.size == (S, S) and canvas.full
    trace = SeedTrace()
    ours = seed_prior._seed_target(req, image, coverage[None], coverage, canvas,
                                   control_inputs(req, req.depth, masks), trace=trace)

    # -- the reference, on the same inputs -------------------------------------------------
    c = seed_prior.components
    pipe = reference_pipeline(c)
    card = c.card
    bg = req.extras["depth_background"]
    disparity = torch.where(torch.isfinite(bg) & (bg > 0), 1.0 / bg, torch.zeros_like(bg))  # DPT stand-in
    lo, hi = disparity.min(), disparity.max()
    ball_depth = req.probes.camera.project(req.probes.centers.double())[2].float()
    ball_z = [float(1.0 / ((1.0 / d - lo) / (hi - lo))) for d in ball_depth]  # their units: 1 / normalised disparity
    ball_masks = [(m > 0).numpy() for m in masks]
    control = reference_control(pipe, disparity, ball_masks, ball_z)
    prompt, negative = reference_prompts(pipe, card.prompts.max, card.prompts.min, ev, card.ev_min)
    mask = (coverage > 0).float()[None]
    clean = tonemap(req.extras["frame_linear"], ev).permute(2, 0, 1)[None] * 2 - 1
    ref, log = reference_target(pipe, image[None] * 2 - 1, mask, clean, control, prompt, negative, tau, guidance,
                                card.controlnet_conditioning_scale, torch.Generator().manual_seed(11))

    # -- tensor by tensor --------------------------------------------------------------------
    t0, k = authors_substeps(tau, 1000)
    assert trace.timesteps == log["timesteps"] and len(trace.timesteps) == k + 1 and trace.timesteps[-1] == 0
    if tau < 0.15:
        assert k == 5  # their `if not multistep > 1: multistep = 5`
    torch.testing.assert_close(trace.control, control, rtol=0, atol=1e-6)  # the ControlNet input
    reps = 2 if guidance > 1 else 1
    for step in log["controlnet_input"]:
        torch.testing.assert_close(trace.control.repeat(reps, 1, 1, 1), step, rtol=0, atol=1e-6)
    assert len(trace.guided) == len(log["noise_pred"]) == k
    for a, b in zip(trace.guided, log["noise_pred"]):  # CFG (+ rescale) output
        torch.testing.assert_close(a, b, rtol=1e-4, atol=2e-5)
    for a, b in zip(trace.latents, log["latents"]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=2e-5)
    ours_signed = ours * 2 - 1
    ref01 = ((ref[0] + 1) / 2).clamp(0, 1)
    torch.testing.assert_close(ours, ref01, rtol=1e-4, atol=5e-5)
    # outside the balls the target is the request's image exactly
    assert torch.equal(ours[:, coverage == 0], image[:, coverage == 0])
    assert ours_signed.shape == (3, S, S)


def test_seed_profile_differs_from_paper_and_is_recorded(tiny_dir, seed_prior):
    paper = DiffusionPrior(load_components(tiny_dir))
    req_a, req_b = _request(0.5, 0.0, 12.5, 2), _request(0.5, 0.0, 12.5, 2)
    a, b = paper(req_a), seed_prior(req_b)
    assert float((a - b).abs().max()) > 1e-3
    assert seed_prior.describe()["profile"]["name"] == "seed" and paper.describe()["profile"]["name"] == "paper"
    assert seed_prior.describe()["control_encoding"] == "authors_disparity"


def test_authors_substeps_rule():
    assert authors_substeps(0.45, 1000) == (450, 4)  # round(4.5) = 4 (Python rounds half to even)
    assert authors_substeps(0.1, 1000) == (100, 5)  # round(1.0) = 1 -> 5
    assert authors_substeps(0.98, 1000) == (980, 10)
    assert authors_substeps(0.003, 1000) == (3, 3)  # clamped to t0 where their code would assert
    assert authors_substeps(0.0, 1000) == (0, 0)


def test_seed_control_quantises_and_fills_balls(seed_prior):
    from core.priors.diffusion.control import control_image

    req = _request(0.5, 0.0, 12.5, 0)
    canvas = seed_prior.canvas(S, S)
    ctrl = control_image("authors_disparity", control_inputs(req, req.depth, req.ball_masks), canvas, "cpu")
    assert torch.equal(ctrl, torch.floor(ctrl * 255) / 255)  # 8-bit levels
    inside = [ctrl[0][m > 0] for m in req.ball_masks]
    assert all(float(v.max() - v.min()) == 0.0 for v in inside)  # one value per ball
    assert float(inside[0][0]) > float(inside[1][0])  # the nearer ball is brighter
    assert np.isfinite(ctrl.numpy()).all()
