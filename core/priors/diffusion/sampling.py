"""Direct sampling ("Ours-sampling" and the DiffusionLight-style baseline).

Balls are inpainted from pure noise with diffusers' StableDiffusionControlNetInpaintPipeline
at each exposure of a bracket (EV 0, -2.5, -5 by default), all exposures with the same
seed so the bracket stays aligned; each ball is unwrapped to an env map
(core.chrome_ball.unwrap_ball) and the bracket is merged to HDR (core.exposure.merge_brackets).

`median_over > 1` inpaints every exposure with that many seeds and takes the per-pixel
median (DiffusionLight's trick against outlier samples). It multiplies the time by
`median_over`; BallSamples reports the wall time and the number of inpaintings.

DiffusionLight's weights (card profile `diffusionlight`) run as its `inpaint.py` does in
its single-pass ("normal") algorithm: SDXL ControlNet inpainting pipeline (or the SD one
for its SD-2 + normal-map variant), the exposure LoRA fused at load, prompt AND pooled
embeddings interpolated between its two prompts, its negative prompt, UniPC, 30 steps,
guidance 5, ControlNet scale 0.5, the frame letterboxed into the square canvas. Its
default "iterative" refinement (30 balls per pass, median, strength 0.8 re-inpainting)
is not reproduced; `median_over` is the nearest knob.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from core.chrome_ball import unwrap_ball
from core.conventions import DEFAULT_BRACKET_EVS
from core.exposure import merge_brackets
from core.priors.base import PriorError, ProbeGeometry
from core.priors.diffusion.conditioning import combine_per_ball, paste_outside, union_coverage
from core.priors.diffusion.control import ControlInputs, control_image

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
    """A diffusers inpainting + ControlNet pipeline (SD or SDXL) sharing the prior's loaded models."""
    from diffusers import (  # noqa: PLC0415 — diffusers is heavy: imported when used
        DDIMScheduler,
        StableDiffusionControlNetInpaintPipeline,
        StableDiffusionXLControlNetInpaintPipeline,
        UniPCMultistepScheduler,
    )

    c = prior.components
    scheduler_cls = UniPCMultistepScheduler if c.card.sampler == "unipc" else DDIMScheduler
    if c.is_sdxl:
        pipe = StableDiffusionXLControlNetInpaintPipeline(
            vae=c.vae, text_encoder=c.text_encoder, text_encoder_2=c.text_encoder_2, tokenizer=c.tokenizer,
            tokenizer_2=c.tokenizer_2, unet=c.unet, controlnet=c.controlnet,
            scheduler=scheduler_cls.from_config(c.scheduler.config), requires_aesthetics_score=False,
            force_zeros_for_empty_prompt=True, add_watermarker=False,
        )
        pipe.set_progress_bar_config(disable=True)
        return pipe
    pipe = StableDiffusionControlNetInpaintPipeline(
        vae=c.vae,
        text_encoder=c.text_encoder,
        tokenizer=c.tokenizer,
        unet=c.unet,
        controlnet=c.controlnet,
        scheduler=scheduler_cls.from_config(c.scheduler.config),
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
    steps: int | None = None,
    guidance_scale: float | None = None,
    env_height: int = 64,
    background_depth: torch.Tensor | None = None,
) -> BallSamples:
    """Inpaint the N balls of `masks` [N, H, W] into `image` [3, H, W] (LDR, balls may be
    blank) from pure noise at each EV; return one merged HDR env map per ball. `depth` is
    the planar depth with the balls, `background_depth` the scene's own (default: `depth`).
    `steps` and `guidance_scale` default to the card's."""
    if median_over < 1:
        raise PriorError(f"median_over must be >= 1, got {median_over}")
    if not evs:
        raise PriorError("evs must name at least one exposure")
    if masks.dim() != 3 or masks.shape[0] != probes.centers.shape[0]:
        raise PriorError(f"masks must be [N, H, W] with N = {probes.centers.shape[0]} probes, got {tuple(masks.shape)}")
    c = prior.components
    guidance = c.card.default_guidance_scale if guidance_scale is None else float(guidance_scale)
    steps = c.card.sampling_steps if steps is None else int(steps)
    h, w = image.shape[-2:]
    canvas = prior.canvas(h, w)
    size = canvas.size
    coverage = union_coverage(masks.float())
    per_ball = coverage[None] if c.card.multi_ball else masks.float()
    b = per_ball.shape[0]
    model_image = canvas.to_model(image[None].float()).expand(b, -1, -1, -1).to(c.device)
    model_mask = canvas.mask_to_model(per_ball)[:, None].to(c.device)
    inputs = ControlInputs(depth, depth if background_depth is None else background_depth, masks.float(), probes)
    control = control_image(prior.control_encoding, inputs, canvas, c.device)[None].expand(b, -1, -1, -1)

    pipe = build_pipeline(prior)
    images: dict[float, torch.Tensor] = {}
    start = time.perf_counter()
    for ev in evs:
        runs = []
        for j in range(median_over):
            emb, null = prior.conditioner(ev).repeat(b), prior.conditioner.null_embedding(b)
            pooled = {} if not c.is_sdxl else {"pooled_prompt_embeds": emb.pooled.to(c.dtype),
                                                "negative_pooled_prompt_embeds": null.pooled.to(c.dtype)}
            out = pipe(
                image=model_image,
                mask_image=model_mask,
                control_image=control,
                height=size[0],
                width=size[1],
                prompt_embeds=emb.tokens.to(c.dtype),
                negative_prompt_embeds=null.tokens.to(c.dtype),
                **pooled,
                num_inference_steps=steps,
                guidance_scale=guidance,
                controlnet_conditioning_scale=c.card.controlnet_conditioning_scale,
                strength=1.0,
                generator=torch.Generator(device="cpu").manual_seed(seed + j),
                output_type="pt",
            ).images.float()
            runs.append(combine_per_ball(canvas.to_frame(out.cpu()), per_ball))
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
        settings={"evs": list(map(float, evs)), "seed": seed, "median_over": median_over, "steps": steps,
                  "guidance_scale": guidance, "sampler": c.card.sampler, "profile": prior.profile.name,
                  "control_encoding": prior.control_encoding, "canvas": list(size)},
    )


def _unwrap_and_merge(images: dict[float, torch.Tensor], probes: ProbeGeometry, env_height: int):
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
