"""Direct sampling ("Ours-sampling" and the DiffusionLight-style baseline).

Balls are inpainted from pure noise with diffusers' StableDiffusionControlNetInpaintPipeline
at each exposure of a bracket (EV 0, -2.5, -5 by default), all exposures with the same
seed so the bracket stays aligned; each ball is unwrapped to an env map
(core.chrome_ball.unwrap_ball) and the bracket is merged to HDR (core.exposure.merge_brackets).

`median_over > 1` inpaints every exposure with that many seeds and takes the per-pixel
median (DiffusionLight's trick against outlier samples). It multiplies the time by
`median_over`; BallSamples reports the wall time and the number of inpaintings.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from core.conventions import DEFAULT_BRACKET_EVS
from core.priors.base import PriorError, ProbeGeometry
from core.priors.diffusion.conditioning import (
    binary_mask_at,
    combine_per_ball,
    depth_to_control,
    paste_outside,
    resize,
    union_coverage,
)

if TYPE_CHECKING:
    from core.priors.diffusion.prior import DiffusionPrior


@dataclass
class BallSamples:
    envmaps: torch.Tensor  # [N, h, 2h, 3] linear HDR (merged bracket), 0 where not valid
    valid: torch.Tensor  # [N, h, 2h] directions every ball image shows
    images: dict[float, torch.Tensor]  # ev -> [3, H, W] LDR frame with the inpainted balls
    seconds: float  # wall time of all inpaintings (the cost of median_over)
    inpaintings: int  # network passes = len(evs) * median_over (single-ball models: x N in the batch)
    settings: dict = field(default_factory=dict)


def build_pipeline(prior: "DiffusionPrior"):
    """A diffusers inpainting + ControlNet pipeline sharing the prior's loaded models."""
    from diffusers import DDIMScheduler, StableDiffusionControlNetInpaintPipeline

    c = prior.components
    pipe = StableDiffusionControlNetInpaintPipeline(
        vae=c.vae,
        text_encoder=c.text_encoder,
        tokenizer=c.tokenizer,
        unet=c.unet,
        controlnet=c.controlnet,
        scheduler=DDIMScheduler.from_config(c.scheduler.config),
        safety_checker=None,
        feature_extractor=None,
        requires_safety_checker=False,
    )
    pipe.set_progress_bar_config(disable=True)
    return pipe


def sample_balls(
    prior: "DiffusionPrior",
    image: torch.Tensor,
    masks: torch.Tensor,
    depth: torch.Tensor,
    probes: ProbeGeometry,
    evs: tuple[float, ...] = DEFAULT_BRACKET_EVS,
    seed: int = 0,
    median_over: int = 1,
    steps: int = 30,
    guidance_scale: float | None = None,
    env_height: int = 64,
) -> BallSamples:
    """Inpaint the N balls of `masks` [N, H, W] into `image` [3, H, W] (LDR, balls may be
    blank) from pure noise at each EV; return one merged HDR env map per ball."""
    if median_over < 1:
        raise PriorError(f"median_over must be >= 1, got {median_over}")
    if not evs:
        raise PriorError("evs must name at least one exposure")
    if masks.dim() != 3 or masks.shape[0] != probes.centers.shape[0]:
        raise PriorError(f"masks must be [N, H, W] with N = {probes.centers.shape[0]} probes, got {tuple(masks.shape)}")
    c = prior.components
    guidance = c.card.default_guidance_scale if guidance_scale is None else float(guidance_scale)
    h, w = image.shape[-2:]
    size = prior.model_size(h, w)
    coverage = union_coverage(masks.float())
    per_ball = coverage[None] if c.card.multi_ball else masks.float()
    b = per_ball.shape[0]
    model_image = resize(image[None].float(), size).expand(b, -1, -1, -1).to(c.device)
    model_mask = binary_mask_at(per_ball, size)[:, None].to(c.device)
    control = resize(depth_to_control(depth)[None], size).expand(b, -1, -1, -1).to(c.device)

    pipe = build_pipeline(prior)
    images: dict[float, torch.Tensor] = {}
    start = time.perf_counter()
    for ev in evs:
        runs = []
        for j in range(median_over):
            out = pipe(
                image=model_image,
                mask_image=model_mask,
                control_image=control,
                height=size[0],
                width=size[1],
                prompt_embeds=prior.conditioner(ev).tokens.repeat(b, 1, 1).to(c.dtype),
                negative_prompt_embeds=prior.conditioner.null_embedding(b).tokens.to(c.dtype),
                num_inference_steps=steps,
                guidance_scale=guidance,
                controlnet_conditioning_scale=c.card.controlnet_conditioning_scale,
                strength=1.0,
                generator=torch.Generator(device="cpu").manual_seed(seed + j),
                output_type="pt",
            ).images.float()
            runs.append(combine_per_ball(resize(out.cpu(), (h, w)), per_ball))
        ldr = torch.stack(runs).median(dim=0).values if median_over > 1 else runs[0]
        images[float(ev)] = paste_outside(ldr.clamp(0.0, 1.0), image.float(), coverage)
    seconds = time.perf_counter() - start
    envmaps, valid = _unwrap_and_merge(images, probes, env_height)
    return BallSamples(
        envmaps=envmaps,
        valid=valid,
        images=images,
        seconds=seconds,
        inpaintings=len(evs) * median_over,
        settings={"evs": list(map(float, evs)), "seed": seed, "median_over": median_over, "steps": steps, "guidance_scale": guidance},
    )


def _unwrap_and_merge(images: dict[float, torch.Tensor], probes: ProbeGeometry, env_height: int):
    from core.chrome_ball import unwrap_ball
    from core.exposure import merge_brackets

    evs = list(images)
    envs, valids = [], []
    for i in range(probes.centers.shape[0]):
        brackets = []
        valid = None
        for ev in evs:
            env, ok = unwrap_ball(
                images[ev].permute(1, 2, 0), probes.camera, probes.centers[i], float(probes.radii[i]), env_height
            )
            brackets.append(env.float())
            valid = ok if valid is None else valid & ok
        hdr = merge_brackets(brackets, evs)
        envs.append(torch.where(valid[..., None], hdr, torch.zeros_like(hdr)))
        valids.append(valid)
    return torch.stack(envs), torch.stack(valids)
