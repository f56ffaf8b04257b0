"""DiffusionPrior: the paper's chrome-ball inpainting prior behind core/priors/base.py.

One call = one pass of the network over one image that holds all N balls of the step
(the model is multi-ball). A single-ball model (card `multi_ball: false`, e.g. a
DiffusionLight-style checkpoint) gets a batch of N images instead, ball i inpainted with
only its own mask, and the N results are combined by each ball's coverage; still one
batched pass per denoising step.
"""
from __future__ import annotations

import os
from typing import TYPE_CHECKING

import torch
from pydantic import Field

from core.conventions import DEFAULT_BRACKET_EVS
from core.priors.base import Prior, PriorConfig, PriorError, PriorRequest, ProbeGeometry
from core.priors.diffusion.conditioning import (
    binary_mask_at,
    combine_per_ball,
    depth_to_control,
    latent_mask,
    model_size,
    paste_outside,
    resize,
    to_signed,
    to_unit,
    union_coverage,
)
from core.priors.diffusion.denoise import InpaintCondition, InpaintDenoiser
from core.priors.diffusion.exposure import ExposureConditioner
from core.priors.diffusion.loading import PriorComponents, load_components
from core.priors.registry import register_prior

if TYPE_CHECKING:
    from core.capture.base import Capture
    from core.priors.diffusion.sampling import BallSamples


class DiffusionSettings(PriorConfig):
    weights: str | None = Field(None, description="local model directory (docs/diffusion-prior.md); required")
    dtype: str | None = Field(None, description="float32 / float16 / bfloat16 (default: the loader's choice for the device)")


@register_prior("diffusion", for_jobs=True)
class DiffusionPrior(Prior):
    Config = DiffusionSettings

    def __init__(self, components: PriorComponents):
        self.components = components
        card = components.card
        self.conditioner = ExposureConditioner(
            components.text_encoder, components.tokenizer, card.prompts.max, card.prompts.min, card.ev_min
        )
        self.denoiser = InpaintDenoiser(components)

    @classmethod
    def from_pretrained(
        cls, weights_dir: str | os.PathLike, device: str | torch.device | None = None, dtype: str | torch.dtype | None = None
    ) -> "DiffusionPrior":
        """Load from a local model directory (see loading.py); PriorError if it is not one."""
        return cls(load_components(weights_dir, device=device, dtype=dtype))

    @classmethod
    def from_config(cls, config: DiffusionSettings, device: str | torch.device | None = None) -> "DiffusionPrior":
        return build_diffusion_prior(config.weights, device=device, dtype=config.dtype)

    # -- Prior protocol -------------------------------------------------------------------
    def bind(self, capture: "Capture", *, lighting_changes: bool = True) -> None:
        """Nothing is per-capture: prompts are encoded at load time and frames are sized per call."""

    def describe(self) -> dict:
        c = self.components
        return {
            "name": self.name,
            "weights": str(c.model_dir),
            "device": str(c.device),
            "dtype": str(c.dtype).replace("torch.", ""),
            "card": c.card.model_dump(mode="json"),
        }

    def __call__(self, request: PriorRequest) -> torch.Tensor:
        image, masks, depth = _validated(request)
        coverage = union_coverage(masks)
        if request.steps == 0 or request.tau <= 0.0 or not bool((coverage > 0).any()):
            return image.clone()
        per_ball = masks if not self.components.card.multi_ball else coverage[None]
        cond, image_latents = self.condition(image, per_ball, depth, request.ev)
        latents = self.denoiser.refine(
            image_latents, cond, float(request.tau), int(request.steps), float(request.guidance_scale), request.generator
        )
        generated = resize(to_unit(self.denoiser.decode(latents)), tuple(image.shape[-2:])).to(image.device)
        return paste_outside(combine_per_ball(generated, per_ball), image, coverage)

    def sample_balls(
        self,
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
    ) -> "BallSamples":
        """Direct sampling: inpaint from pure noise at each EV, unwrap, merge to HDR (see sampling.py)."""
        from core.priors.diffusion.sampling import sample_balls

        return sample_balls(self, image, masks, depth, probes, evs=evs, seed=seed, median_over=median_over,
                            steps=steps, guidance_scale=guidance_scale, env_height=env_height)

    # -- helpers ----------------------------------------------------------------------------
    def model_size(self, height: int, width: int) -> tuple[int, int]:
        c = self.components
        return model_size(height, width, c.card.resolution, c.size_multiple)

    def condition(
        self, image: torch.Tensor, per_ball: torch.Tensor, depth: torch.Tensor, ev: float
    ) -> tuple[InpaintCondition, torch.Tensor]:
        """Model-space conditioning and clean image latents for B = per_ball.shape[0] inpaintings of `image`."""
        c = self.components
        b = per_ball.shape[0]
        size = self.model_size(*image.shape[-2:])
        img = to_signed(resize(image[None].to(c.device), size)).expand(b, -1, -1, -1)
        mask = binary_mask_at(per_ball.to(c.device), size)[:, None]  # [B, 1, h, w]
        # masked image: balls blanked to 0 in [-1, 1] (mid grey), as diffusers' inpainting pipelines do
        latents = self.denoiser.encode(torch.cat([img[:1], img * (1.0 - mask)]))
        control = resize(depth_to_control(depth)[None], size).to(c.device).expand(b, -1, -1, -1)
        cond = InpaintCondition(
            mask=latent_mask(mask, c.vae_scale_factor),
            masked_image_latents=latents[1:],
            control=control,
            embedding=self.conditioner(ev).repeat(b),
            null_embedding=self.conditioner.null_embedding(b),
        )
        return cond, latents[:1].expand(b, -1, -1, -1)


def _validated(request: PriorRequest) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    image, masks, depth = request.image, request.ball_masks, request.depth
    if image.dim() != 3 or image.shape[0] != 3:
        raise PriorError(f"request.image must be [3, H, W], got {tuple(image.shape)}")
    h, w = image.shape[-2:]
    if masks.dim() != 3 or tuple(masks.shape[-2:]) != (h, w):
        raise PriorError(f"request.ball_masks must be [N, {h}, {w}], got {tuple(masks.shape)}")
    if tuple(depth.shape) != (h, w):
        raise PriorError(f"request.depth must be [{h}, {w}], got {tuple(depth.shape)}")
    if request.steps < 0:
        raise PriorError(f"request.steps must be >= 0, got {request.steps}")
    if not (0.0 <= request.tau <= 1.0):
        raise PriorError(f"request.tau must be in [0, 1], got {request.tau}")
    if not request.guidance_scale >= 0.0:
        raise PriorError(f"request.guidance_scale must be >= 0, got {request.guidance_scale}")
    return image.float(), masks.float(), depth


def build_diffusion_prior(
    weights: str | os.PathLike | None = None, device: str | torch.device | None = None, dtype: str | torch.dtype | None = None
) -> DiffusionPrior:
    """The prior from a local model directory (`build_prior("diffusion", {"weights": DIR})`)."""
    if weights is None:
        raise PriorError("the diffusion prior needs weights: a local model directory (--prior-weights DIR)")
    return DiffusionPrior.from_pretrained(weights, device=device, dtype=dtype)
