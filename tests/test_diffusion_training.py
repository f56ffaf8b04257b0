"""Fine-tuning the prior on the tiny model: data format, masked loss, overfitting, resume."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from core.priors.diffusion.loading import load_components
from core.training.diffusion.data import BallDataset, StepOrder, TrainingDataError, read_dataset_info
from core.training.diffusion.train import (
    TrainConfig,
    TrainConfigError,
    masked_noise_loss,
    prepare_batch,
    sample_draws,
    train_prior,
    training_loss,
)

RES = (24, 40)  # dataset resolution (H, W); the tiny model works at 32 x 32 pixels' worth

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/diffusion_fixtures.py


def write_samples(root: Path, count: int = 3, res=RES, seed: int = 0) -> Path:
    """A few samples in the lightfield-balls format: a graded room with one or two balls."""
    from core.io.depth import write_depth_npz
    from core.io.exr import write_exr
    from core.io.images import write_png

    g = np.random.default_rng(seed)
    h, w = res
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    for i in range(count):
        d = root / "samples" / f"{i:06d}"
        d.mkdir(parents=True)
        background = (g.uniform(0.05, 0.6, size=3) * (0.5 + yy[..., None] / h)).astype(np.float32)
        mask = np.zeros((h, w), bool)
        balls = []
        for _ in range(1 + i % 2):
            cy, cx, r = g.uniform(6, h - 6), g.uniform(6, w - 6), g.uniform(3, 5)
            mask |= (yy - cy) ** 2 + (xx - cx) ** 2 < r * r
            balls.append({"center": [0.0, 0.0, -2.0], "radius": 0.1, "pixel": [cx, cy]})
        image = background.copy()
        image[mask] = g.uniform(0.0, 50.0, size=(int(mask.sum()), 3))  # bright HDR reflections
        depth = np.full((h, w), 3.0, np.float32)
        depth[mask] = 2.0
        write_exr(d / "image_with_balls.exr", image)
        write_exr(d / "background.exr", background)
        write_png(d / "ball_mask.png", mask.astype(np.uint8) * 255)
        write_depth_npz(d / "depth_with_balls.npz", depth)
        (d / "meta.json").write_text(json.dumps({"balls": balls, "intrinsics": {}, "c2w": np.eye(4).ravel().tolist()}))
    (root / "dataset.json").write_text(
        json.dumps({"format": "lightfield-balls", "version": 1, "count": count, "resolution": list(res)})
    )
    return root


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return write_samples(tmp_path_factory.mktemp("balls"))


# -- data -----------------------------------------------------------------------------------
def test_dataset_reads_the_format(data_dir):
    ds = BallDataset(data_dir, (32, 48))
    item = ds[1]
    assert item["hdr"].shape == (3, 32, 48) and item["background"].shape == (3, 32, 48)
    assert item["coverage"].shape == (1, 32, 48) and item["control"].shape == (3, 32, 48)
    assert item["hdr"].max() > 1.0  # HDR survives reading and resizing
    covered = item["coverage"][0] > 0.5
    assert covered.any() and not covered.all()
    assert item["control"][0][covered].mean() > item["control"][0][~covered].mean()  # balls are nearer


def test_dataset_errors_name_the_problem(data_dir, tmp_path):
    with pytest.raises(TrainingDataError, match="dataset.json"):
        read_dataset_info(tmp_path)
    (tmp_path / "dataset.json").write_text(
        json.dumps({"format": "other", "version": 1, "count": 1, "resolution": [4, 4]})
    )
    with pytest.raises(TrainingDataError, match="format"):
        read_dataset_info(tmp_path)
    (tmp_path / "dataset.json").write_text(
        json.dumps({"format": "lightfield-balls", "version": 1, "count": 1, "resolution": [4, 4]})
    )
    with pytest.raises(TrainingDataError, match="000000: missing image_with_balls.exr"):
        read_dataset_info(tmp_path)


def test_step_order_is_a_pure_function_of_position():
    a = StepOrder(5, seed=3)
    first = [i for _, i in zip(range(12), iter(a))]
    assert sorted(first[:5]) == list(range(5)) and sorted(first[5:10]) == list(range(5))  # epochs are permutations
    resumed = StepOrder(5, seed=3, start=7)
    assert [i for _, i in zip(range(5), iter(resumed))] == first[7:12]
    ranks = [StepOrder(5, seed=3, rank=r, world=2) for r in (0, 1)]
    interleaved = [ranks[k % 2].index_at(k) for k in range(10)]
    assert interleaved == first[:10]


def test_batch_arithmetic_is_checked():
    assert TrainConfig(batch=16, micro_batch=2).accumulation(processes=2) == 4
    with pytest.raises(TrainConfigError, match="batch=16"):
        TrainConfig(batch=16, micro_batch=3).accumulation(processes=1)
    with pytest.raises(TrainConfigError, match="grad_accum=3"):
        TrainConfig(batch=16, micro_batch=2, grad_accum=3).accumulation(processes=1)


# -- the loss -------------------------------------------------------------------------------
def test_masked_loss_has_zero_gradient_outside_the_mask():
    g = torch.Generator().manual_seed(0)
    pred = torch.randn(2, 4, 6, 6, generator=g, requires_grad=True)
    target = torch.randn(2, 4, 6, 6, generator=g)
    mask = torch.zeros(2, 1, 6, 6)
    mask[0, :, 1:3, 2:5] = 1
    mask[1, :, 4:, :2] = 1
    loss = masked_noise_loss(pred, target, mask)
    loss.backward()
    outside = (mask == 0).expand_as(pred)
    assert torch.equal(pred.grad[outside], torch.zeros_like(pred.grad[outside]))
    assert (pred.grad[~outside].abs() > 0).all()
    # the value ignores outside cells too: changing them (even to huge values) changes nothing
    wild = pred.detach().clone()
    wild[outside] = 1e6
    assert torch.equal(masked_noise_loss(wild, target, mask), loss.detach())
    # and it is the mean over masked cells
    expected = ((pred.detach() - target) ** 2)[~outside].mean()
    torch.testing.assert_close(loss.detach(), expected)


def test_end_to_end_loss_gradient_ignores_background_latents(tiny_dir, data_dir):
    """Through the real UNet: the loss's gradient w.r.t. the prediction is 0 on background cells."""
    comps = load_components(tiny_dir)
    from core.priors.diffusion.exposure import ExposureConditioner
    from core.priors.diffusion.network import InpaintNetwork

    cond = ExposureConditioner(comps.text_encoder, comps.tokenizer, "a", "b", comps.card.ev_min)
    net = InpaintNetwork(comps.unet, comps.controlnet).requires_grad_(True)
    batch = torch.utils.data.default_collate([BallDataset(data_dir, (32, 48))[i] for i in range(2)])
    draws = sample_draws(torch.Generator().manual_seed(0), 2, (4, 4, 6), -5.0, 1000, 0.1)
    prepared = prepare_batch(comps, batch, draws)
    grads = []

    def capture_grad(module, args, out):
        out[0].register_hook(grads.append)

    handle = comps.unet.register_forward_hook(capture_grad)
    try:
        training_loss(net, comps, cond, prepared, draws).backward()
    finally:
        handle.remove()
    outside = (prepared.mask == 0).expand_as(grads[0])
    assert outside.any() and (~outside).any()
    assert torch.equal(grads[0][outside], torch.zeros_like(grads[0][outside]))
    assert grads[0][~outside].abs().sum() > 0


def test_a_few_steps_overfit_a_fixed_batch(tiny_dir, data_dir):
    """Fixed data, noise, timesteps and EVs: 40 Adam steps cut the loss at least 5x."""
    torch.manual_seed(0)
    comps = load_components(tiny_dir)
    from core.priors.diffusion.exposure import ExposureConditioner
    from core.priors.diffusion.network import InpaintNetwork

    cond = ExposureConditioner(
        comps.text_encoder, comps.tokenizer, comps.card.prompts.max, comps.card.prompts.min, comps.card.ev_min
    )
    net = InpaintNetwork(comps.unet, comps.controlnet).requires_grad_(True).train()
    batch = torch.utils.data.default_collate([BallDataset(data_dir, (32, 48))[i] for i in range(2)])
    draws = sample_draws(torch.Generator().manual_seed(1), 2, (4, 4, 6), -5.0, 1000, 0.1)
    prepared = prepare_batch(comps, batch, draws)
    opt = torch.optim.Adam(net.parameters(), lr=2e-3)
    losses = []
    for _ in range(40):
        loss = training_loss(net, comps, cond, prepared, draws)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < losses[0] / 5, losses


# -- the trainer ----------------------------------------------------------------------------
def _weights(model_dir: Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    out = {}
    for sub in ("unet", "controlnet"):
        for k, v in load_file(str(model_dir / sub / "diffusion_pytorch_model.safetensors")).items():
            out[f"{sub}.{k}"] = v
    return out


def test_resume_gives_identical_weights(tiny_dir, data_dir, tmp_path):
    cfg = dict(lr=1e-3, batch=2, micro_batch=1, checkpoint_every=2, log_every=1, seed=5)
    straight = train_prior(data_dir, tiny_dir, tmp_path / "straight", TrainConfig(iterations=4, **cfg))
    assert straight.start_step == 0 and len(straight.losses) == 4 and all(np.isfinite(straight.losses))
    train_prior(data_dir, tiny_dir, tmp_path / "split", TrainConfig(iterations=2, **cfg))
    resumed = train_prior(data_dir, tiny_dir, tmp_path / "split", TrainConfig(iterations=4, **cfg), resume=True)
    assert resumed.start_step == 2 and len(resumed.losses) == 2
    assert resumed.losses == straight.losses[2:]
    a, b = _weights(tmp_path / "straight"), _weights(tmp_path / "split")
    base = _weights(tiny_dir)
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert any(not torch.equal(a[k], base[k]) for k in a)  # training changed the weights
    # the output is a complete model directory the prior loads, with a card that records the run
    from core.priors.diffusion import DiffusionPrior

    prior = DiffusionPrior.from_pretrained(tmp_path / "split")
    assert prior.describe()["card"]["fine_tuning"]["iterations"] == 4
    log_lines = (tmp_path / "straight" / "train_log.jsonl").read_text().splitlines()
    assert [json.loads(line)["step"] for line in log_lines] == [1, 2, 3, 4]


def test_trainer_runs_on_simulator_export(tiny_dir, tmp_path):
    """End to end on what `lightfield simulate --training-export` writes (small, 2 views)."""
    from core.sim.suites import suite
    from core.sim.training import write_training_export

    scene = suite("static").model_copy(update={"resolution": (48, 36)})
    write_training_export(scene, tmp_path / "export", 2)
    result = train_prior(tmp_path / "export", tiny_dir, tmp_path / "out",
                         TrainConfig(iterations=2, batch=2, micro_batch=1, lr=1e-4, checkpoint_every=1))
    assert len(result.losses) == 2 and all(np.isfinite(result.losses)) and result.losses[0] > 0
    assert [p.name for p in sorted((tmp_path / "out" / "checkpoints").glob("step-*"))] == ["step-000001", "step-000002"]


def test_exposure_dropout_replaces_zeta_by_the_null_embedding(tiny_dir, data_dir):
    """With dropout the loss no longer depends on ev's embedding; without, it does."""
    from dataclasses import replace

    from core.priors.diffusion.exposure import ExposureConditioner
    from core.priors.diffusion.network import InpaintNetwork

    comps = load_components(tiny_dir)
    card = comps.card
    cond = ExposureConditioner(comps.text_encoder, comps.tokenizer, card.prompts.max, card.prompts.min, card.ev_min)
    net = InpaintNetwork(comps.unet, comps.controlnet)
    batch = torch.utils.data.default_collate([BallDataset(data_dir, (32, 48))[0]])
    draws = sample_draws(torch.Generator().manual_seed(2), 1, (4, 4, 6), card.ev_min, 1000, 0.0)
    prepared = prepare_batch(comps, batch, draws)  # the target's exposure is fixed here

    def loss(ev, drop):
        d = replace(draws, ev=torch.tensor([ev]), drop=torch.tensor([drop]))
        with torch.no_grad():
            return float(training_loss(net, comps, cond, prepared, d))

    assert loss(0.0, True) == loss(card.ev_min, True)
    assert loss(0.0, False) != loss(card.ev_min, False)
