"""Direct sampling (bracketed inpainting -> unwrapped, merged HDR env maps) and a full
distillation run with the tiny diffusion prior."""
from __future__ import annotations

import json
import warnings

import pytest
import torch

from core.camera import Camera, Intrinsics, identity_pose
from core.chrome_ball import place_probe, render_balls
from core.priors.base import PriorError, ProbeGeometry
from core.priors.diffusion import DiffusionPrior

H, W = 40, 56
EVS = (0.0, -5.0)

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/diffusion_fixtures.py


@pytest.fixture(scope="module")
def scene():
    """Two balls placed by core.chrome_ball in front of a wall 3 m away."""
    cam = Camera(Intrinsics.from_hfov(W, H, 60.0), identity_pose())
    placed = [place_probe(cam, (16.0, 20.0), 2.0, 0.35), place_probe(cam, (40.0, 22.0), 2.5, 0.3)]
    centers = torch.stack([c for c, _ in placed])
    radii = torch.tensor([r for _, r in placed], dtype=torch.float32)
    layer = render_balls(cam, centers, radii, lambda d, i: torch.full((d.shape[0], 3), 0.5))
    image = torch.rand(3, H, W, generator=torch.Generator().manual_seed(3))
    probes = ProbeGeometry(centers, radii, torch.zeros(2, 2), cam, 0, 0.0)
    return image, layer.coverage.float(), torch.full((H, W), 3.0), probes


def test_sampling_returns_finite_hdr_envmaps_and_keeps_the_background(prior, scene):
    image, masks, depth, probes = scene
    out = prior.sample_balls(image, masks, depth, probes, evs=EVS, seed=1, steps=2, env_height=8)
    assert out.envmaps.shape == (2, 8, 16, 3) and out.valid.shape == (2, 8, 16)
    assert torch.isfinite(out.envmaps).all() and (out.envmaps >= 0).all()
    assert out.valid.any(dim=(1, 2)).all()  # every ball shows some directions
    assert torch.equal(out.envmaps[~out.valid], torch.zeros_like(out.envmaps[~out.valid]))
    outside = masks.sum(0) == 0
    assert sorted(out.images) == sorted(EVS)
    for ldr in out.images.values():
        assert torch.equal(ldr[:, outside], image[:, outside])
    assert out.images[0.0][:, masks.sum(0) > 0.99].sub(image[:, masks.sum(0) > 0.99]).abs().mean() > 1e-3
    assert out.inpaintings == len(EVS) and out.seconds > 0


def test_sampling_median_is_the_per_pixel_median_of_seeds(prior, scene):
    image, masks, depth, probes = scene
    kw = dict(evs=(-2.5,), steps=2, env_height=8)
    runs = [prior.sample_balls(image, masks, depth, probes, seed=s, **kw).images[-2.5] for s in (4, 5, 6)]
    assert not torch.equal(runs[0], runs[1])  # seeds differ, so the median can fail
    med = prior.sample_balls(image, masks, depth, probes, seed=4, median_over=3, **kw)
    torch.testing.assert_close(med.images[-2.5], torch.stack(runs).median(0).values, rtol=0, atol=1e-6)
    assert med.inpaintings == 3 and med.settings["median_over"] == 3
    again = prior.sample_balls(image, masks, depth, probes, seed=4, median_over=3, **kw)
    assert torch.equal(again.images[-2.5], med.images[-2.5])  # same seed, same output


def test_sampling_rejects_bad_settings(prior, scene):
    image, masks, depth, probes = scene
    with pytest.raises(PriorError, match="median_over"):
        prior.sample_balls(image, masks, depth, probes, median_over=0)
    with pytest.raises(PriorError, match="N = 2 probes"):
        prior.sample_balls(image, masks[:1], depth, probes)


def test_distillation_with_the_tiny_prior_completes_and_stays_finite(tiny_dir, tmp_path):
    from core.engine import run_job
    from core.engine.config import DistillConfig, EngineConfig
    from core.engine.params import JobParams
    from core.fields.stored.artefact import LightFieldArtefact
    from core.io import write_png

    write_png(tmp_path / "in.png", torch.rand(24, 32, 3, generator=torch.Generator().manual_seed(0)).numpy())
    prior = DiffusionPrior.from_pretrained(tiny_dir)
    calls = []
    handle = prior.components.unet.register_forward_pre_hook(lambda m, a: calls.append(1))
    cfg = EngineConfig(distill=DistillConfig(iterations=3, n_probes=3, work_height=24, warmup_steps=1,
                                             checkpoint_every=1000, guidance_scale=3.0, perceptual_weight=0.0))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "depth assumed" for a bare image
            out = run_job(tmp_path / "in.png", None, JobParams(seed=2), tmp_path / "art", prior=prior, config=cfg).path
    finally:
        handle.remove()
    assert len(calls) >= 3  # the prior ran at every step (>= 1 denoising step each)
    meta = json.loads((out / "lightfield.json").read_text())
    assert meta["prior"]["name"] == "diffusion"
    curve = meta["training"]["loss_curve"]
    assert len(curve) == 3 and all(map(lambda v: v == v and abs(v) < float("inf"), curve))
    env, _ = LightFieldArtefact.load(out).envmap(torch.tensor([0.0, 0.0, -1.0]), None, 8)
    assert torch.isfinite(env).all()
