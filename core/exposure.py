"""Exposure brackets -> HDR (DiffusionLight's merge) and a display tone map for previews.

The exposure / tone map themselves are the project's conventions and live in
core.conventions; they are re-exported here so callers have one place to look.
"""
from __future__ import annotations

from typing import Sequence

import torch

from core.conventions import DEFAULT_BRACKET_EVS, expose, inverse_tonemap, tonemap

__all__ = [
    "DEFAULT_BRACKET_EVS",
    "ExposureError",
    "LUMINANCE_WEIGHTS",
    "display_tonemap",
    "expose",
    "inverse_tonemap",
    "luminance",
    "merge_brackets",
    "to_uint8",
    "tonemap",
]

# Rec. 709 / sRGB luminance weights, as in DiffusionLight's exposure2hdr.py.
LUMINANCE_WEIGHTS = (0.212671, 0.715160, 0.072169)
# A bracket is trusted fully below 90 % of its clip level and not at all at the clip level.
_SATURATION_START = 0.9
_EPS = 1e-10


class ExposureError(ValueError):
    """Malformed bracket list, exposure values or tone-map parameters."""


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    """Linear RGB [..., 3] -> luminance [...]."""
    w = torch.tensor(LUMINANCE_WEIGHTS, dtype=rgb.dtype, device=rgb.device)
    return (rgb * w).sum(-1)


def chromaticity(rgb: torch.Tensor) -> torch.Tensor:
    """Linear RGB [..., 3] divided by its luminance (colour at unit luminance); black (luminance
    under 1e-12) stays near 0 instead of dividing by zero."""
    return rgb / luminance(rgb).clamp_min(1e-12)[..., None]


def merge_brackets(ldr_list: Sequence[torch.Tensor], evs: Sequence[float] = DEFAULT_BRACKET_EVS) -> torch.Tensor:
    """Merge LDR brackets [..., 3] in [0, 1] (tone mapped at `evs`) into linear HDR [..., 3].

    The rule of DiffusionLight's `exposure2hdr.py` (Phongthawee et al., CVPR 2024):

    1. Sort brackets by EV, brightest (EV 0) first. Linearise each with the inverse tone
       map, L_i = ldr_i^2.4 / 2^ev_i, and take its luminance Y_i.
    2. Start from the darkest bracket: Y = Y_darkest (it saturates last).
    3. Going up in exposure, bracket i (clip level m_i = 1 / 2^ev_i in radiance) replaces Y
       where it is not saturated: w = clip((Y_i - 0.9 m_i) / (0.1 m_i), 0, 1) * [Y > Y_i],
       Y <- Y_i (1 - w) + Y w. So Y_i is used fully below 90 % of its clip level, fades out
       linearly up to the clip, and is never used to lower a brighter estimate there.
    4. Colour from the brightest bracket: HDR = L_0 * Y / (Y_0 + 1e-10). Saturated pixels
       of EV 0 therefore come out with EV 0's (whitened) chroma and the merged luminance.

    Saturation is judged on luminance, as in DiffusionLight: a strongly coloured pixel
    whose brightest channel clips while its luminance is still below 90 % of the clip
    level is taken from that bracket, and its luminance is underestimated.
    """
    if len(ldr_list) == 0 or len(ldr_list) != len(evs):
        raise ExposureError(f"need one exposure value per bracket, got {len(ldr_list)} brackets and evs={list(evs)}")
    evs = [float(e) for e in evs]
    if len(set(evs)) != len(evs):
        raise ExposureError(f"evs must be distinct, got {evs}")
    shape = tuple(ldr_list[0].shape)
    if shape[-1:] != (3,) or any(tuple(x.shape) != shape for x in ldr_list):
        raise ExposureError(f"brackets must all have the same shape [..., 3], got {[tuple(x.shape) for x in ldr_list]}")
    order = sorted(range(len(evs)), key=lambda i: -evs[i])
    linear = [inverse_tonemap(torch.nan_to_num(ldr_list[i].float(), nan=0.0), evs[i]) for i in order]
    lum = [luminance(x) for x in linear]
    sorted_evs = [evs[i] for i in order]

    merged = lum[-1]
    for i in range(len(order) - 2, -1, -1):
        clip_level = 1.0 / (2.0 ** sorted_evs[i])
        fade = ((lum[i] - _SATURATION_START * clip_level) / ((1.0 - _SATURATION_START) * clip_level)).clamp(0.0, 1.0)
        keep_darker = fade * (merged > lum[i]).to(fade.dtype)
        merged = lum[i] * (1.0 - keep_darker) + merged * keep_darker
    return linear[0] * (merged / (lum[0] + _EPS))[..., None]


def display_tonemap(
    hdr: torch.Tensor, percentile: float = 99.0, gamma: float = 2.2, max_mapping: float = 0.9
) -> torch.Tensor:
    """HDR [..., 3] -> LDR in [0, 1] for previews (DiffusionLight's TonemapHDR rule).

    x = hdr^(1/gamma) is scaled so its `percentile`-th percentile maps to `max_mapping`,
    then clipped. The percentile ignores non-finite values (NaN -> 0, +inf -> white), so
    all-zero, all-inf and mixed inputs give finite output.
    """
    if not (0.0 < percentile <= 100.0) or not gamma > 0 or not max_mapping > 0:
        raise ExposureError(
            f"need 0 < percentile <= 100, gamma > 0, max_mapping > 0; got {percentile}, {gamma}, {max_mapping}"
        )
    x = hdr.float()
    posinf = x == float("inf")
    x = torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0).pow(1.0 / gamma)
    finite = x[~posinf].reshape(-1)
    if finite.numel() > 1_000_000:  # torch.quantile has a size limit; a strided subset is plenty
        finite = finite[:: finite.numel() // 1_000_000 + 1]
    level = float(torch.quantile(finite, percentile / 100.0)) if finite.numel() else 0.0
    scale = max_mapping / level if level > _EPS else 1.0
    out = (x * scale).clamp(0.0, 1.0)
    return torch.where(posinf, torch.ones_like(out), out)


def to_uint8(ldr: torch.Tensor) -> torch.Tensor:
    """LDR in [0, 1] -> uint8 (rounded; NaN -> 0, out-of-range clipped)."""
    return (torch.nan_to_num(ldr.float(), nan=0.0).clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)
