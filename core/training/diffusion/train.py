"""Fine-tuning the prior (paper §3.1, "Diffusion Model" + implementation details).

Full fine-tuning of the UNet and the depth ControlNet (no LoRA); the VAE and text encoder
stay frozen. Per sample: ev ~ U[ev_min, 0] exposes the HDR target before the tone map
(core.conventions.tonemap); the UNet input is the noisy target latent + the ball mask +
the latent of the background with the balls blanked (what inference sees); the text
condition is zeta(ev), replaced by the null (empty-prompt) embedding with p = 0.1 so CFG
works; the loss is the noise-prediction MSE over ball cells of the latent only.

Every random draw of a step comes from a generator seeded by (seed, step, micro-batch,
rank) and the data order is a pure function of the sample position, so a resumed run
repeats an uninterrupted one exactly. Multi-GPU: launch with `accelerate launch`.
"""
from __future__ import annotations

import contextlib
import json
import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch.utils.data import DataLoader

from core.conventions import tonemap
from core.priors.diffusion.card import ModelCard
from core.priors.diffusion.conditioning import latent_mask, model_size, to_signed
from core.priors.diffusion.exposure import ExposureConditioner
from core.priors.diffusion.loading import PriorComponents, load_components
from core.priors.diffusion.network import InpaintNetwork
from core.training.diffusion.checkpoint import list_checkpoints, load_checkpoint, save_checkpoint
from core.training.diffusion.data import BallDataset, StepOrder, read_dataset_info

log = logging.getLogger("lightfield.train_prior")

FROZEN_SUBFOLDERS = ("vae", "text_encoder", "tokenizer", "scheduler")
LOG_FILE = "train_log.jsonl"


class TrainConfigError(ValueError):
    """Inconsistent fine-tuning settings (named field and value in the message)."""


class TrainConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    iterations: int = Field(15_000, ge=1, description="optimizer steps")
    lr: float = Field(1e-5, gt=0)
    batch: int = Field(16, ge=1, description="effective batch = micro_batch x grad_accum x processes")
    micro_batch: int = Field(1, ge=1, description="samples per forward pass and process")
    grad_accum: int | None = Field(None, ge=1, description="default: batch / (micro_batch x processes)")
    exposure_dropout: float = Field(0.1, ge=0.0, le=1.0)
    weight_decay: float = Field(1e-2, ge=0.0)
    max_grad_norm: float = Field(1.0, gt=0.0)
    checkpoint_every: int = Field(500, ge=1)
    keep_checkpoints: int = Field(2, ge=1)
    log_every: int = Field(10, ge=1)
    seed: int = 0
    mixed_precision: Literal["no", "fp16", "bf16"] = "no"
    gradient_checkpointing: bool = False
    num_workers: int = Field(0, ge=0, description="DataLoader worker processes")

    def accumulation(self, processes: int) -> int:
        if self.grad_accum is not None:
            if self.micro_batch * self.grad_accum * processes != self.batch:
                raise TrainConfigError(
                    f"batch={self.batch} != micro_batch={self.micro_batch} x grad_accum={self.grad_accum} "
                    f"x processes={processes}"
                )
            return self.grad_accum
        per_step = self.micro_batch * processes
        if self.batch % per_step:
            raise TrainConfigError(f"batch={self.batch} is not a multiple of micro_batch x processes = {per_step}")
        return self.batch // per_step


# -- one step's randomness ------------------------------------------------------------------
@dataclass
class StepDraws:
    ev: torch.Tensor  # [B] exposure applied to the HDR target
    timesteps: torch.Tensor  # [B] long
    noise: torch.Tensor  # [B, C, h, w] diffusion noise
    latent_eps: torch.Tensor  # [B, C, h, w] reparameterisation noise of the VAE posterior
    drop: torch.Tensor  # [B] bool: use the null embedding (CFG dropout)


def sample_draws(gen: torch.Generator, batch: int, latent_shape: tuple[int, int, int], ev_min: float,
                 num_timesteps: int, dropout: float) -> StepDraws:
    return StepDraws(
        ev=ev_min * torch.rand(batch, generator=gen),
        timesteps=torch.randint(0, num_timesteps, (batch,), generator=gen),
        noise=torch.randn(batch, *latent_shape, generator=gen),
        latent_eps=torch.randn(batch, *latent_shape, generator=gen),
        drop=torch.rand(batch, generator=gen) < dropout,
    )


def step_generator(seed: int, step: int, micro: int, rank: int) -> torch.Generator:
    return torch.Generator().manual_seed(((seed * 1_000_003 + step) * 1_009 + micro) * 131 + rank)


# -- the loss -----------------------------------------------------------------------------------
def masked_noise_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error over masked latent cells only ([B, C, h, w] vs mask [B, 1, h, w]).

    Cells outside the mask are multiplied by exactly 0 before the sum, so they contribute
    neither value nor gradient; an all-background batch gives loss 0.
    """
    m = mask.to(pred.dtype)
    sq = torch.where(m > 0, (pred.float() - target.float()) ** 2, torch.zeros((), device=pred.device))
    denom = (m.sum() * pred.shape[1]).clamp(min=1.0)
    return sq.sum() / denom


@dataclass
class PreparedBatch:
    latents: torch.Tensor  # [B, C, h, w] clean target latent (scaled)
    masked_image_latents: torch.Tensor
    mask: torch.Tensor  # [B, 1, h, w] latent-resolution ball mask
    control: torch.Tensor


@torch.no_grad()
def prepare_batch(comps: PriorComponents, batch: dict[str, torch.Tensor], draws: StepDraws) -> PreparedBatch:
    """Expose + tone map, mask, and encode one micro-batch (frozen VAE, fp32)."""
    dev = comps.device
    ev = draws.ev.to(dev)[:, None, None, None]
    target = tonemap(batch["hdr"].to(dev), ev)
    background = tonemap(batch["background"].to(dev), ev)
    mask = (batch["coverage"].to(dev) > 0).float()
    vae, scale = comps.vae, float(comps.vae.config.scaling_factor)
    posterior = vae.encode(to_signed(target).to(vae.dtype)).latent_dist
    latents = (posterior.mean + posterior.std * draws.latent_eps.to(dev, posterior.mean.dtype)).float() * scale
    masked = vae.encode((to_signed(background) * (1.0 - mask)).to(vae.dtype)).latent_dist.mode().float() * scale
    return PreparedBatch(latents, masked, latent_mask(mask, comps.vae_scale_factor), batch["control"].to(dev))


def training_loss(network, comps: PriorComponents, conditioner: ExposureConditioner, prepared: PreparedBatch,
                  draws: StepDraws) -> torch.Tensor:
    scheduler = comps.scheduler
    dev = prepared.latents.device
    t = draws.timesteps.to(dev)
    noise = draws.noise.to(dev)
    noisy = scheduler.add_noise(prepared.latents, noise, t)
    tokens = torch.where(draws.drop.to(dev)[:, None, None], conditioner.null.tokens, conditioner(draws.ev).tokens)
    if scheduler.config.prediction_type == "v_prediction":
        target = scheduler.get_velocity(prepared.latents, noise, t)
    else:
        target = noise
    pred = network(noisy, t, tokens, prepared.mask, prepared.masked_image_latents, prepared.control)
    return masked_noise_loss(pred, target, prepared.mask)


# -- the loop ---------------------------------------------------------------------------------
@dataclass
class TrainResult:
    out_dir: Path
    start_step: int
    final_step: int
    losses: list[float]  # per optimizer step, averaged over processes
    seconds: float
    main_process: bool = True


def train_prior(data_dir: str | Path, base_dir: str | Path, out_dir: str | Path, cfg: TrainConfig,
                resume: bool = False) -> TrainResult:
    """Fine-tune `base_dir` on `data_dir`; write checkpoints and the final model directory to `out_dir`."""
    from accelerate import Accelerator  # noqa: PLC0415 — accelerate is heavy: imported when used

    accelerator = Accelerator(mixed_precision=cfg.mixed_precision)
    world, rank = accelerator.num_processes, accelerator.process_index
    accum = cfg.accumulation(world)
    out = Path(out_dir)
    info = read_dataset_info(data_dir)

    comps = load_components(base_dir, device=accelerator.device, dtype=torch.float32)
    card = comps.card
    size = model_size(*info.resolution, card.resolution, comps.size_multiple)
    conditioner = ExposureConditioner(
        comps.text_encoder, comps.tokenizer, card.prompts.max, card.prompts.min, card.ev_min
    )
    network = InpaintNetwork(comps.unet, comps.controlnet, card.controlnet_conditioning_scale)
    network.requires_grad_(True).train()
    if cfg.gradient_checkpointing:
        comps.unet.enable_gradient_checkpointing()
        comps.controlnet.enable_gradient_checkpointing()
    optimizer = torch.optim.AdamW(network.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)

    start = 0
    if resume and list_checkpoints(out):
        ckpt = list_checkpoints(out)[-1]
        start = int(load_checkpoint(ckpt, network, optimizer)["step"])
        log.info("resumed from %s (step %d)", ckpt, start)
    network, optimizer = accelerator.prepare(network, optimizer)

    dataset = BallDataset(data_dir, size)
    order = StepOrder(len(dataset), cfg.seed, start=start * accum * cfg.micro_batch, rank=rank, world=world)
    batches = iter(DataLoader(dataset, batch_size=cfg.micro_batch, sampler=order, num_workers=cfg.num_workers))
    latent_shape = (
        comps.vae.config.latent_channels,
        size[0] // comps.vae_scale_factor,
        size[1] // comps.vae_scale_factor,
    )
    log_path = out / LOG_FILE
    if accelerator.is_main_process:
        out.mkdir(parents=True, exist_ok=True)
        log.info("fine-tuning %s on %d samples at %s: batch %d = %d x %d x %d processes, %d iterations from %d",
                 base_dir, len(dataset), size, cfg.batch, cfg.micro_batch, accum, world, cfg.iterations, start)

    losses: list[float] = []
    t0 = time.perf_counter()
    for step in range(start, cfg.iterations):
        step_loss = 0.0
        for micro in range(accum):
            batch = next(batches)
            draws = sample_draws(step_generator(cfg.seed, step, micro, rank), batch["hdr"].shape[0], latent_shape,
                                 card.ev_min, comps.scheduler.config.num_train_timesteps, cfg.exposure_dropout)
            prepared = prepare_batch(comps, batch, draws)
            sync = contextlib.nullcontext() if micro == accum - 1 else accelerator.no_sync(network)
            with sync:
                loss = training_loss(network, comps, conditioner, prepared, draws)
                accelerator.backward(loss / accum)
            step_loss += float(loss.detach()) / accum
        accelerator.clip_grad_norm_(network.parameters(), cfg.max_grad_norm)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        if world > 1:  # log the loss of the whole batch, not of this rank's share
            step_loss = float(accelerator.reduce(torch.tensor(step_loss, device=accelerator.device), "mean"))
        losses.append(step_loss)
        done = step + 1
        if accelerator.is_main_process and (done % cfg.log_every == 0 or done == cfg.iterations):
            elapsed = time.perf_counter() - t0
            record = {"step": done, "loss": step_loss, "lr": cfg.lr, "seconds": round(elapsed, 3),
                      "samples_per_s": round((done - start) * cfg.batch / max(elapsed, 1e-9), 3)}
            with log_path.open("a") as f:
                f.write(json.dumps(record) + "\n")
            log.info("step %d/%d loss %.5f (%.2f samples/s)", done, cfg.iterations, step_loss, record["samples_per_s"])
        if done % cfg.checkpoint_every == 0 and done < cfg.iterations:
            accelerator.wait_for_everyone()
            if accelerator.is_main_process:
                save_checkpoint(out, done, accelerator.unwrap_model(network), optimizer,
                                {"config": cfg.model_dump(), "base": str(base_dir), "data": str(data_dir)},
                                keep=cfg.keep_checkpoints)

    accelerator.wait_for_everyone()
    if accelerator.is_main_process:
        save_checkpoint(out, cfg.iterations, accelerator.unwrap_model(network), optimizer,
                        {"config": cfg.model_dump(), "base": str(base_dir), "data": str(data_dir)},
                        keep=cfg.keep_checkpoints)
        export_model(accelerator.unwrap_model(network), comps, out, cfg, data_dir)
    return TrainResult(out, start, cfg.iterations, losses, time.perf_counter() - t0, accelerator.is_main_process)


def export_model(network: InpaintNetwork, comps: PriorComponents, out: Path, cfg: TrainConfig, data_dir) -> None:
    """Write `out` as a complete model directory (`--prior-weights OUT` works directly)."""
    for sub in FROZEN_SUBFOLDERS:
        shutil.copytree(comps.model_dir / sub, out / sub, dirs_exist_ok=True)
    network.unet.save_pretrained(out / "unet", safe_serialization=True)
    network.controlnet.save_pretrained(out / "controlnet", safe_serialization=True)
    card = ModelCard.model_validate({
        **comps.card.model_dump(mode="json"),
        "base": f"fine-tuned from {comps.model_dir}",
        "fine_tuning": {"data": str(data_dir), "iterations": cfg.iterations, "lr": cfg.lr, "batch": cfg.batch,
                        "exposure_dropout": cfg.exposure_dropout, "seed": cfg.seed},
    })
    card.save(out)  # written last: a directory with a card is complete
