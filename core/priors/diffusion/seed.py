"""The `seed` profile's distillation target: the authors' released denoising, re-derived.

Read from ORionTMT/Sig25_4DLighting (not copied): Lighting/sds_utils.py
`PipeSDS21.loss_sds_image` (the sub-step loop, latent blending, final paste) and
`PipeSDS21.noise_predict` (CFG + rescale, ControlNet feed), Lighting/pipeline_utils.py
`custom_prepare_mask_latents` (bilinear latent mask, sampled VAE latent of the masked
image) and `rescale_noise_cfg`, Lighting/sds_scheduler.py `DDIMSchedulerSDS.step` (DDIM
with an explicit previous timestep), SDS/multiball_sds.py `sds_loop` (timestep and number
of sub-steps from t, the clean frame as the masked-image input).

One call, in model space (the canvas is the card resolution, squashed):

1. t0 = int(T tau); k = round(10 tau), and k <= 1 becomes 5 (their `if not multistep > 1`);
   k is clamped to t0 so a tiny tau cannot ask for more sub-steps than timesteps (their
   code asserts there). Sub-timesteps: the scheduler's full T-step grid (T-1 ... 0) indexed
   at linspace(idx(t0), T-1, k+1).round(), so the last sub-step lands on t = 0.
2. Latents: the composite's VAE posterior SAMPLE (generator), noise (generator), noised to t0.
3. Each sub-step: the clean ball-free frame's latent is re-sampled from its posterior
   (their `prepare_mask_latents` re-encodes it every sub-step with the same generator; the
   encoder is deterministic, so sampling the one posterior again is the same tensor), the
   latent mask is the image mask bilinearly downsampled (soft), CFG (when g > 1) with the
   negative prompt, then rescaled with phi = 1 (std-matched to the text branch), one DDIM
   step (eta 0) to the next sub-timestep, and -- except after the last sub-step -- the
   background is put back: x = (1 - m) add_noise(z0, noise, t_next) + m x with the SOFT mask.
4. Decode; the ball pixels (binary image mask) take the decoded image, all others the composite.

The only substitution: their noise comes from torch's global RNG (seeded by
`seed_everything`); here every draw comes from the request's generator, in the same order.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from core.priors.diffusion.exposure import ExposureEmbedding
from core.priors.diffusion.loading import PriorComponents
from core.priors.diffusion.network import inpaint_forward

AUTHORS_MULTISTEP = 10  # run_video_demo.py: args.sds_multistep
AUTHORS_MIN_SUBSTEPS = 5  # loss_sds_image: `if not multistep > 1: multistep = 5`


@dataclass
class SeedTrace:
    """Intermediate tensors of one call (for parity tests and debugging)."""

    timesteps: list[int] = field(default_factory=list)
    latent_mask: torch.Tensor | None = None
    image_latents: torch.Tensor | None = None
    noise: torch.Tensor | None = None
    masked_image_latents: list[torch.Tensor] = field(default_factory=list)
    control: torch.Tensor | None = None
    guided: list[torch.Tensor] = field(default_factory=list)  # CFG (+ rescale) output per sub-step
    latents: list[torch.Tensor] = field(default_factory=list)  # after each sub-step (and blending)
    decoded: torch.Tensor | None = None  # VAE output in [-1, 1], before the paste


def authors_substeps(tau: float, num_train_timesteps: int) -> tuple[int, int]:
    """(t0, k): the start timestep and the number of sub-steps the released loop uses for tau."""
    t0 = int(num_train_timesteps * tau)
    k = round(tau * AUTHORS_MULTISTEP)
    if not k > 1:
        k = AUTHORS_MIN_SUBSTEPS
    return t0, max(0, min(k, t0))


def authors_timesteps(grid: torch.Tensor, t0: int, k: int) -> torch.Tensor:
    """k + 1 timesteps from t0 down to the grid's last entry, evenly spaced in grid index."""
    idx = int((grid == t0).nonzero(as_tuple=True)[0][0])
    positions = torch.linspace(idx, len(grid) - 1, k + 1).round().int()
    return grid[positions.long()]


def rescale_cfg(guided: torch.Tensor, text: torch.Tensor, phi: float) -> torch.Tensor:
    """Guidance rescale (Lin et al. 2024, §3.4): match the text branch's per-sample std, mix by phi."""
    dims = list(range(1, text.ndim))
    rescaled = guided * (text.std(dim=dims, keepdim=True) / guided.std(dim=dims, keepdim=True))
    return phi * rescaled + (1.0 - phi) * guided


def ddim_step_to(scheduler, model_output: torch.Tensor, t: int, x: torch.Tensor, prev: int) -> torch.Tensor:
    """One deterministic DDIM step (eta = 0) from timestep t to an explicit `prev` (DDIM eq. 12)."""
    ac = scheduler.alphas_cumprod.to(x.device)
    a_t = ac[t]
    a_prev = ac[prev] if prev >= 0 else scheduler.final_alpha_cumprod.to(x.device)
    b_t = 1.0 - a_t
    kind = scheduler.config.prediction_type
    if kind == "epsilon":
        x0, eps = (x - b_t.sqrt() * model_output) / a_t.sqrt(), model_output
    elif kind == "v_prediction":
        x0, eps = a_t.sqrt() * x - b_t.sqrt() * model_output, a_t.sqrt() * model_output + b_t.sqrt() * x
    else:  # "sample"
        x0, eps = model_output, (x - a_t.sqrt() * model_output) / b_t.sqrt()
    if scheduler.config.thresholding:
        x0 = scheduler._threshold_sample(x0)
    elif scheduler.config.clip_sample:
        x0 = x0.clamp(-scheduler.config.clip_sample_range, scheduler.config.clip_sample_range)
    return a_prev.sqrt() * x0 + (1.0 - a_prev).sqrt() * eps


class SeedDenoiser:
    def __init__(self, components: PriorComponents):
        from diffusers import DDIMScheduler  # noqa: PLC0415 — diffusers is heavy: imported when used

        self.c = components
        # the released code swaps in a DDIM scheduler built from the checkpoint's config and
        # never calls set_timesteps: its grid is every training timestep, T-1 ... 0
        self.scheduler = DDIMScheduler.from_config(components.scheduler.config)

    @torch.no_grad()
    def _posterior(self, image_signed: torch.Tensor):
        from diffusers.models.autoencoders.vae import DiagonalGaussianDistribution  # noqa: PLC0415 — diffusers is heavy: imported when used

        params = self.c.vae.encode(image_signed.to(self.c.device, self.c.dtype)).latent_dist.parameters.float()
        return [DiagonalGaussianDistribution(params[i : i + 1]) for i in range(params.shape[0])]

    def _sample(self, posteriors, generator) -> torch.Tensor:
        sf = float(self.c.vae.config.scaling_factor)
        return torch.cat([p.sample(generator=generator) for p in posteriors]) * sf

    @torch.no_grad()
    def refine(
        self,
        composite: torch.Tensor,  # [B, 3, H, W] in [-1, 1]: the frame with the field's balls
        clean: torch.Tensor,  # [B, 3, H, W] in [-1, 1]: the frame without balls
        image_mask: torch.Tensor,  # [B, 1, H, W] binary
        control: torch.Tensor,  # [B, 3, H, W] in [0, 1]
        embedding: ExposureEmbedding,  # batch B
        null_embedding: ExposureEmbedding,  # batch B
        tau: float,
        guidance_scale: float,
        cfg_rescale: float,
        generator: torch.Generator | None,
        trace: SeedTrace | None = None,
    ) -> torch.Tensor:
        """The decoded target in [-1, 1] ([B, 3, H, W]), composite outside the binary mask."""
        from diffusers.utils.torch_utils import randn_tensor  # noqa: PLC0415 — diffusers is heavy: imported when used

        c, sch = self.c, self.scheduler
        t0, k = authors_substeps(tau, sch.config.num_train_timesteps)
        if k == 0:
            return composite.clone()
        steps = [int(s) for s in authors_timesteps(sch.timesteps, t0, k)]
        f = c.vae_scale_factor
        h, w = composite.shape[-2:]
        latent_mask = F.interpolate(image_mask.float(), size=(h // f, w // f), mode="bilinear", align_corners=False)
        posteriors = self._posterior(torch.cat([composite, clean]))
        b = composite.shape[0]
        z0 = self._sample(posteriors[:b], generator)
        noise = randn_tensor(z0.shape, generator=generator, device=z0.device, dtype=z0.dtype)
        x = sch.add_noise(z0, noise, torch.tensor([t0]))
        if trace is not None:
            trace.timesteps, trace.latent_mask, trace.image_latents, trace.noise = steps, latent_mask, z0, noise
            trace.control = control
        for i in range(k):
            t, prev = steps[i], steps[i + 1]
            masked = self._sample(posteriors[b:], generator)
            eps = self._guided(
                x, t, latent_mask, masked, control, embedding, null_embedding, guidance_scale, cfg_rescale
            )
            x = ddim_step_to(sch, eps, t, x, prev)
            if i < k - 1:  # no blending after the last sub-step
                background = sch.add_noise(z0, noise, torch.tensor([prev]))
                x = (1.0 - latent_mask) * background + latent_mask * x
            if trace is not None:
                trace.masked_image_latents.append(masked)
                trace.guided.append(eps)
                trace.latents.append(x)
        decoded = c.vae.decode((x / float(c.vae.config.scaling_factor)).to(c.device, c.dtype)).sample.float()
        if trace is not None:
            trace.decoded = decoded
        m = image_mask.float()
        return (1.0 - m) * composite + m * decoded

    def _guided(self, x, t, mask, masked_latents, control, emb, null, g, phi) -> torch.Tensor:
        c = self.c
        guided = g > 1.0  # noise_predict: do_classifier_free_guidance = guidance_scale > 1.0
        reps = 2 if guided else 1
        tokens = torch.cat([null.tokens, emb.tokens]) if guided else emb.tokens
        dt = c.dtype
        out = inpaint_forward(
            c.unet, c.controlnet,
            self.scheduler.scale_model_input(x, t).repeat(reps, 1, 1, 1).to(c.device, dt),
            torch.tensor(t, device=c.device),
            tokens.to(c.device, dt),
            mask.repeat(reps, 1, 1, 1).to(c.device, dt),
            masked_latents.repeat(reps, 1, 1, 1).to(c.device, dt),
            control.repeat(reps, 1, 1, 1).to(c.device, dt),
            c.card.controlnet_conditioning_scale,
        ).float()
        if not guided:
            return out
        uncond, text = out.chunk(2)
        cfg = uncond + g * (text - uncond)
        return rescale_cfg(cfg, text, phi) if phi > 0 else cfg
