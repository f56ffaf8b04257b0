"""DiffusionPrior: the paper's chrome-ball inpainting prior behind core/priors/base.py.

One call = one pass of the network over one image that holds all N balls of the step
(the model is multi-ball). A single-ball model (card `multi_ball: false`, e.g.
DiffusionLight's weights) gets a batch of N images instead, ball i inpainted with only its
own mask, and the N results are combined by each ball's coverage; still one batched pass
per denoising step.

How the target is computed follows the prior's inference profile (profiles.py): `paper`
and `diffusionlight` use denoise.InpaintDenoiser, `seed` the authors' released loop
(seed.py). The profile is the card's unless the job names one.
"""
from __future__ import annotations

import os
from typing import TYPE_CHECKING

import torch
from pydantic import Field

from core.conventions import DEFAULT_BRACKET_EVS, tonemap
from core.priors.base import Prior, PriorConfig, PriorError, PriorRequest, ProbeGeometry
from core.priors.diffusion.canvas import Canvas, make_canvas
from core.priors.diffusion.conditioning import (
    combine_per_ball,
    latent_mask,
    paste_outside,
    to_signed,
    to_unit,
    union_coverage,
)
from core.priors.diffusion.control import ControlInputs, control_image
from core.priors.diffusion.denoise import InpaintCondition, InpaintDenoiser
from core.priors.diffusion.exposure import ExposureConditioner
from core.priors.diffusion.loading import PriorComponents, load_components
from core.priors.diffusion.profiles import ProfileName, get_profile
from core.priors.diffusion.sampling import sample_balls
from core.priors.diffusion.seed import SeedDenoiser
from core.priors.registry import register_prior

if TYPE_CHECKING:
    from core.capture.base import Capture
    from core.priors.diffusion.sampling import BallSamples


class DiffusionSettings(PriorConfig):
    weights: str | None = Field(None, description="local model directory (docs/diffusion-prior.md); required")
    dtype: str | None = Field(
        None, description="float32 / float16 / bfloat16 (default: the loader's choice for the device)"
    )
    profile: ProfileName | None = Field(None, description="inference profile (profiles.py); default: the model card's")


@register_prior("diffusion", for_jobs=True)
class DiffusionPrior(Prior):
    Config = DiffusionSettings

    def __init__(self, components: PriorComponents, profile: str | None = None):
        self.components = components
        card = components.card
        self.profile = get_profile(profile or card.profile)
        if self.profile.schedule == "authors" and (components.is_sdxl or not components.concat_inpaint):
            raise PriorError(
                "the 'seed' profile reproduces the authors' SD-2 inpainting model (9-channel UNet); "
                f"this model is {card.base_family} with a {card.unet_in_channels}-channel UNet: use 'paper' or "
                "'diffusionlight'"
            )
        self.conditioner = ExposureConditioner(
            components.text_encoder,
            components.tokenizer,
            card.prompts.max,
            card.prompts.min,
            card.ev_min,
            negative_prompt=card.negative_prompt,
            text_encoder_2=components.text_encoder_2,
            tokenizer_2=components.tokenizer_2,
        )
        self.denoiser = InpaintDenoiser(components)
        self._seed = None

    @classmethod
    def from_pretrained(
        cls, weights_dir: str | os.PathLike, device: str | torch.device | None = None,
        dtype: str | torch.dtype | None = None, profile: str | None = None,
    ) -> "DiffusionPrior":
        """Load from a local model directory (see loading.py); PriorError if it is not one."""
        return cls(load_components(weights_dir, device=device, dtype=dtype), profile=profile)

    @property
    def control_encoding(self) -> str:
        return "normals" if self.components.card.controlnet_conditioning == "normals" else self.profile.depth_encoding

    @property
    def seed_denoiser(self):
        if self._seed is None:
            self._seed = SeedDenoiser(self.components)
        return self._seed

    @classmethod
    def from_config(cls, config: DiffusionSettings, device: str | torch.device | None = None) -> "DiffusionPrior":
        return build_diffusion_prior(config.weights, device=device, dtype=config.dtype, profile=config.profile)

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
            "profile": self.profile.model_dump(mode="json"),
            "control_encoding": self.control_encoding,
            "card": c.card.model_dump(mode="json"),
        }

    def __call__(self, request: PriorRequest) -> torch.Tensor:
        image, masks, depth = _validated(request)
        coverage = union_coverage(masks)
        if request.steps == 0 or request.tau <= 0.0 or not bool((coverage > 0).any()):
            return image.clone()
        per_ball = masks if not self.components.card.multi_ball else coverage[None]
        canvas = self.canvas(*image.shape[-2:])
        inputs = control_inputs(request, depth, masks)
        if self.profile.schedule == "authors":
            return self._seed_target(request, image, per_ball, coverage, canvas, inputs)
        cond, image_latents = self.condition(image, per_ball, depth, request.sweep_ev, inputs, canvas)
        latents = self.denoiser.refine(
            image_latents,
            cond,
            float(request.tau),
            int(request.steps),
            float(request.guidance_scale),
            request.generator,
        )
        generated = canvas.to_frame(to_unit(self.denoiser.decode(latents))).to(image.device)
        return paste_outside(combine_per_ball(generated, per_ball), image, coverage)

    def _seed_target(self, request, image, per_ball, coverage, canvas: Canvas, inputs: ControlInputs, trace=None):
        """The authors' released target (seed.py): clean frame as the masked image, binary paste."""
        c = self.components
        b = per_ball.shape[0]
        comp = to_signed(canvas.to_model(image[None].to(c.device))).expand(b, -1, -1, -1)
        clean = to_signed(canvas.to_model(clean_frame(request, image)[None].to(c.device))).expand(b, -1, -1, -1)
        mask = canvas.mask_to_model(per_ball.to(c.device))[:, None]
        control = control_image(self.control_encoding, inputs, canvas, c.device).expand(b, -1, -1, -1)
        out = self.seed_denoiser.refine(
            comp,
            clean,
            mask,
            control,
            self.conditioner(request.sweep_ev).repeat(b),
            self.conditioner.null_embedding(b),
            float(request.tau),
            float(request.guidance_scale),
            self.profile.cfg_rescale,
            request.generator,
            trace,
        )
        generated = combine_per_ball(canvas.to_frame(to_unit(out)).to(image.device), per_ball)
        return torch.where(coverage > 0, generated, image)

    def sample_balls(
        self,
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
    ) -> "BallSamples":
        """Direct sampling: inpaint from pure noise at each EV, unwrap, merge to HDR (see sampling.py)."""
        return sample_balls(self, image, masks, depth, probes, evs=evs, seed=seed, median_over=median_over,
                            steps=steps, guidance_scale=guidance_scale, env_height=env_height,
                            background_depth=background_depth)

    # -- helpers ----------------------------------------------------------------------------
    def canvas(self, height: int, width: int) -> Canvas:
        c = self.components
        return make_canvas(self.profile.canvas, (height, width), c.card.resolution, c.size_multiple)

    def model_size(self, height: int, width: int) -> tuple[int, int]:
        return self.canvas(height, width).size

    def condition(
        self, image: torch.Tensor, per_ball: torch.Tensor, depth: torch.Tensor, ev: float,
        inputs: ControlInputs | None = None, canvas: Canvas | None = None,
    ) -> tuple[InpaintCondition, torch.Tensor]:
        """Model-space conditioning and clean image latents for B = per_ball.shape[0] inpaintings of `image`."""
        c = self.components
        b = per_ball.shape[0]
        canvas = canvas or self.canvas(*image.shape[-2:])
        inputs = inputs or ControlInputs(depth, depth, per_ball, None)
        img = to_signed(canvas.to_model(image[None].to(c.device))).expand(b, -1, -1, -1)
        mask = canvas.mask_to_model(per_ball.to(c.device))[:, None]  # [B, 1, h, w]
        if c.concat_inpaint:
            # masked image: balls blanked to 0 in [-1, 1] (mid grey), as diffusers' inpainting pipelines do
            latents = self.denoiser.encode(torch.cat([img[:1], img * (1.0 - mask)]))
            clean, masked = latents[:1], latents[1:]
        else:  # a base UNet inpaints by latent blending alone: no masked-image latent
            clean, masked = self.denoiser.encode(img[:1]), None
        control = control_image(self.control_encoding, inputs, canvas, c.device).expand(b, -1, -1, -1)
        cond = InpaintCondition(
            mask=latent_mask(mask, c.vae_scale_factor),
            masked_image_latents=masked,
            control=control,
            embedding=self.conditioner(ev).repeat(b),
            null_embedding=self.conditioner.null_embedding(b),
        )
        return cond, clean.expand(b, -1, -1, -1)


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


def control_inputs(request: PriorRequest, depth: torch.Tensor, masks: torch.Tensor) -> ControlInputs:
    """What the ControlNet encodings need; the scene's own depth comes from the engine's extras
    ("depth_background"), else the composite depth stands in."""
    background = request.extras.get("depth_background")
    background = depth if background is None else background.to(depth.device)
    return ControlInputs(depth, background, masks, request.probes)


def clean_frame(request: PriorRequest, image: torch.Tensor) -> torch.Tensor:
    """[3, H, W] the frame without balls at the request's exposure (the engine passes the
    linear frame in extras["frame_linear"]); the composite stands in without it."""
    linear = request.extras.get("frame_linear")
    if linear is None:
        return image
    return tonemap(linear.to(image.device).float(), request.ev).permute(2, 0, 1)


def build_diffusion_prior(
    weights: str | os.PathLike | None = None, device: str | torch.device | None = None,
    dtype: str | torch.dtype | None = None, profile: str | None = None,
) -> DiffusionPrior:
    """The prior from a local model directory (`build_prior("diffusion", {"weights": DIR})`)."""
    if weights is None:
        raise PriorError("the diffusion prior needs weights: a local model directory (--prior-weights DIR)")
    return DiffusionPrior.from_pretrained(weights, device=device, dtype=dtype, profile=profile)
