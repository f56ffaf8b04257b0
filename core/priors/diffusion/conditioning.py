"""Image-space preparation of the prior's inputs and outputs (no model calls here).

* Model size: the frame is resized to the model card's pixel count with its aspect ratio
  kept (sides rounded to the UNet/VAE multiple), so balls stay round in model space; the
  result is resized back to the frame size.
* Masks: the union of the balls' anti-aliased coverage is binarised *conservatively*
  (a model or latent cell counts as ball if any ball pixel touches it), so the UNet
  regenerates every ball pixel; background cells that get regenerated too are restored
  exactly by `paste_outside`.
* Depth: a depth ControlNet (trained on MiDaS / DPT output) expects normalised inverse
  depth, near = bright: inv = 1/depth mapped linearly from its robust [1 %, 99 %] range to
  [0, 1], invalid depth -> 0 (far), repeated to 3 channels, values in [0, 1] as diffusers'
  ControlNet pipelines feed it.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from core.conventions import valid_depth_mask

_QUANTILE_MAX_ELEMENTS = 1 << 20  # torch.quantile has an input size limit; a strided subsample is plenty


def model_size(height: int, width: int, resolution: tuple[int, int], multiple: int) -> tuple[int, int]:
    """Size with the card's pixel count and the frame's aspect ratio, sides multiples of `multiple`.

    Sides are capped at twice the card's longer side, so a panorama strip cannot ask the
    model for a huge canvas (its aspect ratio is squeezed instead).
    """
    area = resolution[0] * resolution[1]
    longest = 2 * max(resolution)
    aspect = width / height
    h = math.sqrt(area / aspect)
    w = h * aspect

    def snap(x: float) -> int:
        return min(max(multiple, int(round(x / multiple)) * multiple), max(multiple, longest // multiple * multiple))

    return snap(h), snap(w)


def resize(x: torch.Tensor, size: tuple[int, int], mode: str = "bilinear") -> torch.Tensor:
    """[B, C, H, W] -> [B, C, *size]; antialiased when shrinking."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    if mode == "area":
        return F.interpolate(x, size=size, mode="area")
    return F.interpolate(x, size=size, mode=mode, align_corners=False, antialias=True)


def union_coverage(ball_masks: torch.Tensor) -> torch.Tensor:
    """[N, H, W] per-ball coverage (mutual occlusion applied, so they partition) -> [H, W] in [0, 1]."""
    m = torch.nan_to_num(ball_masks.float(), nan=0.0).clamp(0.0, 1.0)
    return m.sum(0).clamp(max=1.0)


def binary_mask_at(coverage: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """[..., H, W] coverage -> [..., h, w] float {0, 1}: 1 where any covered pixel falls in the cell."""
    lead = coverage.shape[:-2]
    c = (coverage > 0).float().reshape(-1, 1, *coverage.shape[-2:])
    small = (
        F.adaptive_max_pool2d(c, size)
        if all(s >= t for s, t in zip(c.shape[-2:], size))
        else F.interpolate(c, size=size, mode="nearest")
    )
    return small.reshape(*lead, *size)


def latent_mask(mask: torch.Tensor, factor: int) -> torch.Tensor:
    """[B, 1, H, W] binary mask -> [B, 1, H/f, W/f]: 1 where any pixel of the cell is masked."""
    return F.max_pool2d(mask, kernel_size=factor, stride=factor)


def depth_to_control(depth: torch.Tensor) -> torch.Tensor:
    """Planar depth [H, W] (NaN / inf / <= 0 invalid) -> normalised inverse depth [3, H, W] in [0, 1]."""
    d = depth.float()
    valid = valid_depth_mask(d)
    out = torch.zeros_like(d)
    if valid.any():
        inv = 1.0 / d[valid].double().clamp(min=1e-12)
        sample = inv if inv.numel() <= _QUANTILE_MAX_ELEMENTS else inv[:: inv.numel() // _QUANTILE_MAX_ELEMENTS + 1]
        lo, hi = torch.quantile(sample, torch.tensor([0.01, 0.99], dtype=inv.dtype))
        if hi - lo > 1e-12 * hi:
            out[valid] = ((inv - lo) / (hi - lo)).clamp(0.0, 1.0).float()
        else:
            out[valid] = 0.5  # flat scene: no depth structure to convey
    return out.expand(3, -1, -1).clone()


def to_signed(image01: torch.Tensor) -> torch.Tensor:
    """[0, 1] -> [-1, 1], what the VAE expects."""
    return image01 * 2.0 - 1.0


def to_unit(image_signed: torch.Tensor) -> torch.Tensor:
    """[-1, 1] -> [0, 1]; a NaN (e.g. a float16 overflow in the VAE) becomes mid grey, so the
    prior's contract (an image in [0, 1]) holds whatever the network does."""
    return torch.nan_to_num((image_signed + 1.0) * 0.5, nan=0.5).clamp(0.0, 1.0)


def paste_outside(generated: torch.Tensor, image: torch.Tensor, coverage: torch.Tensor) -> torch.Tensor:
    """Blend the generated balls in by their coverage; where coverage is 0 the input is copied exactly."""
    blended = coverage * generated + (1.0 - coverage) * image
    return torch.where(coverage > 0, blended, image)


def combine_per_ball(generated: torch.Tensor, per_ball: torch.Tensor) -> torch.Tensor:
    """[B, 3, H, W] generations -> one image: B = 1 is taken as is; else each ball's pixels from its own pass."""
    if generated.shape[0] == 1:
        return generated[0]
    w = per_ball.to(generated).clamp(0.0, 1.0)[:, None]  # [B, 1, H, W]
    total = w.sum(0)
    return (w * generated).sum(0) / total.clamp(min=1e-6)
