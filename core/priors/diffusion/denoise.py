"""The distillation target: partial DDIM denoising of an inpainting latent (SDEdit-style).

Start from the composite's latent noised to t0 ~ tau * T, run k DDIM steps down to 0 with
classifier-free guidance, and after every step put the background back from the input
latent noised to the next timestep (masked latent blending), so only ball cells evolve.

Timesteps: the scheduler is set to n = round(k / tau) steps with "trailing" spacing and the
last k are used, so the first timestep is ~ tau * T - 1 and the steps are evenly spaced
down to ~T/n. This is diffusers' img2img `strength` recipe, with trailing spacing so small
tau still starts at ~tau * T rather than at 1.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from core.priors.base import PriorError
from core.priors.diffusion.exposure import ExposureEmbedding
from core.priors.diffusion.loading import PriorComponents
from core.priors.diffusion.network import inpaint_forward


@dataclass
class InpaintCondition:
    """Everything the UNet and ControlNet see besides the noisy latent (batch B)."""

    mask: torch.Tensor  # [B, 1, h, w] latent-resolution binary ball mask
    # [B, C, h, w] latent of the image with the balls blanked out (None: base UNet)
    masked_image_latents: torch.Tensor | None
    control: torch.Tensor  # [B, 3, H, W] depth ControlNet image in [0, 1]
    embedding: ExposureEmbedding  # zeta(ev), batch B
    null_embedding: ExposureEmbedding  # empty prompt, batch B (used when guidance != 1)


class InpaintDenoiser:
    def __init__(self, components: PriorComponents):
        from diffusers import DDIMScheduler  # noqa: PLC0415 — diffusers is heavy: imported when used

        self.c = components
        self._scheduler_config = DDIMScheduler.from_config(
            components.scheduler.config, timestep_spacing="trailing"
        ).config

    @property
    def latent_scale(self) -> float:
        return float(self.c.vae.config.scaling_factor)

    # -- VAE ----------------------------------------------------------------------------
    @torch.no_grad()
    def encode(self, image_signed: torch.Tensor) -> torch.Tensor:
        """[B, 3, H, W] in [-1, 1] -> scaled latents (the distribution's mode: deterministic)."""
        x = image_signed.to(self.c.device, self.c.dtype)
        return self.c.vae.encode(x).latent_dist.mode().float() * self.latent_scale

    @torch.no_grad()
    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        """Scaled latents -> [B, 3, H, W] in [-1, 1] (float32)."""
        z = (latents / self.latent_scale).to(self.c.device, self.c.dtype)
        return self.c.vae.decode(z).sample.float()

    # -- schedule -----------------------------------------------------------------------
    def schedule(self, tau: float, steps: int):
        """A fresh DDIM scheduler set up for noise level `tau`, and its k = `steps` timesteps.

        Fresh per call because set_timesteps mutates the scheduler, and a worker may share
        one prior between threads.
        """
        from diffusers import DDIMScheduler  # noqa: PLC0415 — diffusers is heavy: imported when used

        if not (0.0 < tau <= 1.0):
            raise PriorError(f"tau must be in (0, 1] to denoise, got {tau}")
        total = self._scheduler_config.num_train_timesteps
        if not (1 <= steps <= total):
            raise PriorError(f"steps must be in [1, {total}], got {steps}")
        scheduler = DDIMScheduler.from_config(self._scheduler_config)
        scheduler.set_timesteps(min(total, max(steps, round(steps / tau))), device=self.c.device)
        return scheduler, scheduler.timesteps[-steps:]

    # -- one network evaluation -----------------------------------------------------------
    @torch.no_grad()
    def predict_noise(
        self, scheduler, latents: torch.Tensor, t: torch.Tensor, cond: InpaintCondition, guidance_scale: float
    ) -> torch.Tensor:
        """Guided model output for `latents` at timestep t; one UNet call (both CFG branches batched)."""
        guided = guidance_scale != 1.0
        emb = ExposureEmbedding.cat([cond.null_embedding, cond.embedding]) if guided else cond.embedding
        reps = 2 if guided else 1
        x = scheduler.scale_model_input(latents, t).repeat(reps, 1, 1, 1)
        dt = self.c.dtype
        masked = cond.masked_image_latents
        out = inpaint_forward(
            self.c.unet,
            self.c.controlnet,
            x.to(dt),
            t,
            emb.tokens.to(self.c.device, dt),
            cond.mask.repeat(reps, 1, 1, 1).to(dt),
            None if masked is None else masked.repeat(reps, 1, 1, 1).to(dt),
            cond.control.repeat(reps, 1, 1, 1).to(self.c.device, dt),
            self.c.card.controlnet_conditioning_scale,
            sdxl_added_conditions(self.c, emb, x.shape) if self.c.is_sdxl else None,
        ).float()
        if not guided:
            return out
        uncond, text = out.chunk(2)
        return uncond + guidance_scale * (text - uncond)

    # -- the loop -------------------------------------------------------------------------
    @torch.no_grad()
    def refine(
        self,
        image_latents: torch.Tensor,
        cond: InpaintCondition,
        tau: float,
        steps: int,
        guidance_scale: float,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Noise `image_latents` to ~tau*T and denoise in `steps` DDIM steps, keeping the background."""
        from diffusers.utils.torch_utils import randn_tensor  # noqa: PLC0415 — diffusers is heavy: imported when used

        scheduler, timesteps = self.schedule(tau, steps)
        x0 = image_latents.float()
        noise = randn_tensor(x0.shape, generator=generator, device=x0.device, dtype=x0.dtype)
        keep = 1.0 - cond.mask.float()
        x = scheduler.add_noise(x0, noise, timesteps[:1])
        for i, t in enumerate(timesteps):
            eps = self.predict_noise(scheduler, x, t, cond, guidance_scale)
            x = scheduler.step(eps, t, x, eta=0.0, return_dict=False)[0]
            background = x0 if i + 1 == len(timesteps) else scheduler.add_noise(x0, noise, timesteps[i + 1 : i + 2])
            x = keep * background + (1.0 - keep) * x
        return x


def sdxl_time_ids(height: int, width: int) -> list[float]:
    """SDXL micro-conditioning: original size, crop top-left, target size (no aesthetic score),
    as diffusers' SDXL pipelines compute it for an uncropped image at the generation size."""
    return [float(height), float(width), 0.0, 0.0, float(height), float(width)]


def sdxl_added_conditions(c: PriorComponents, emb: ExposureEmbedding, latent_shape) -> dict:
    h, w = latent_shape[-2] * c.vae_scale_factor, latent_shape[-1] * c.vae_scale_factor
    ids = torch.tensor([sdxl_time_ids(h, w)], device=c.device, dtype=c.dtype).repeat(latent_shape[0], 1)
    return {"text_embeds": emb.pooled.to(c.device, c.dtype), "time_ids": ids}
