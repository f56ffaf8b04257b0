"""One evaluation of the inpainting UNet with its depth ControlNet, shared by sampling,
the distillation target and training so all three feed the networks identically.

Input layout (diffusers' SD inpainting convention): the UNet sees
cat([noisy latent, mask, masked-image latent]) (4 + 1 + 4 = 9 channels); the ControlNet
sees only the noisy latent plus its depth image and adds residuals to the UNet's skips.
A base (4-channel) UNet, DiffusionLight's SDXL, sees the noisy latent alone and inpaints
by masked latent blending in the caller. SDXL networks also take `added_cond_kwargs`
(pooled text embedding and size/crop time ids).
"""
from __future__ import annotations

import torch
from torch import nn


def inpaint_forward(
    unet,
    controlnet,
    noisy_latents: torch.Tensor,
    timesteps: torch.Tensor,
    tokens: torch.Tensor,
    mask: torch.Tensor,
    masked_image_latents: torch.Tensor,
    control: torch.Tensor,
    conditioning_scale: float = 1.0,
    added_cond_kwargs: dict | None = None,
) -> torch.Tensor:
    """Model output (noise or v, per the scheduler's prediction_type) for a batch.

    `masked_image_latents=None` feeds a base (4-channel) UNet the noisy latent alone."""
    extra = {} if added_cond_kwargs is None else {"added_cond_kwargs": added_cond_kwargs}
    down, mid = controlnet(
        noisy_latents,
        timesteps,
        encoder_hidden_states=tokens,
        controlnet_cond=control,
        conditioning_scale=conditioning_scale,
        return_dict=False,
        **extra,
    )
    unet_in = (
        noisy_latents if masked_image_latents is None else torch.cat([noisy_latents, mask, masked_image_latents], dim=1)
    )
    return unet(
        unet_in,
        timesteps,
        encoder_hidden_states=tokens,
        down_block_additional_residuals=down,
        mid_block_additional_residual=mid,
        return_dict=False,
        **extra,
    )[0]


class InpaintNetwork(nn.Module):
    """UNet + ControlNet as one module: what fine-tuning optimises and accelerate wraps."""

    def __init__(self, unet, controlnet, conditioning_scale: float = 1.0):
        super().__init__()
        self.unet = unet
        self.controlnet = controlnet
        self.conditioning_scale = conditioning_scale

    def forward(self, noisy_latents, timesteps, tokens, mask, masked_image_latents, control):
        return inpaint_forward(
            self.unet, self.controlnet, noisy_latents, timesteps, tokens, mask, masked_image_latents, control,
            self.conditioning_scale,
        )
