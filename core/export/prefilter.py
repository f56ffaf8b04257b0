"""Prefiltered specular cube maps: GGX roughness mips in the standard face order.

Level i of `levels` has faces of `size >> i` texels and roughness r_i = i / (levels - 1)
(glTF EXT_lights_image_based: "mip levels evenly map to roughness values from 0 to 1";
three.js' PMREM, Filament and Unreal use the same split-sum lobe). GGX alpha = r^2 (the
glTF / Disney convention). Faces and orientation are core.cubemap's (+X, -X, +Y, -Y, +Z, -Z,
OpenGL table, row 0 first).

Each texel with direction n holds the split-sum prefiltered radiance with n = v = r:

    P(n) = integral L(l) w(n.l) dl / integral w(n.l) dl,   w(c) = D_GGX(sqrt((1 + c) / 2)) max(c, 0)

(Karis 2013: importance-sample the half vector from D, weight by n.l). Levels of at most
`QUADRATURE_MAX_FACE` texels (the rough, wide lobes) integrate the kernel directly over an
area-downsampled source with ~2 pixels per texel (exact up to that resolution). Larger,
sharper levels use `samples` Hammersley half vectors per texel and *filtered* importance
sampling (Colbert & Krivanek 2007): each sample reads a downsampled level of the source whose
pixel solid angle matches the sample's.
Level 0 (roughness 0) is the mirror map itself (core.cubemap.equirect_to_cubemap).
"""
from __future__ import annotations

import math

import torch

from core.conventions import equirect_directions
from core.cubemap import cubemap_directions, equirect_to_cubemap
from core.envmap import check_envmap, resize_envmap, sample_envmap, solid_angles

DEFAULT_SAMPLES = 64
LOD_BIAS = 0.0
QUADRATURE_MAX_FACE = 32  # levels this small (rough, wide lobes) are integrated directly, larger ones sampled
# source rows per face texel; 64 cube on 2 CPUs: 2 -> 1.1 % error, ~1 s; 1 -> 2.9 %, 0.23 s (bench/export_latency.py)
QUADRATURE_SOURCE_RATIO = 2
MIN_FACE = 4  # default mip chains stop at faces of this size or above (glTF: the last mip must hold roughness 1)


def roughness_of_level(level: int, levels: int) -> float:
    return level / (levels - 1) if levels > 1 else 0.0


def default_levels(size: int) -> int:
    """Mips from `size` down to max(MIN_FACE, size / 32): 6 levels for 128-texel faces."""
    return max(1, min(int(math.log2(size)) - int(math.log2(MIN_FACE)) + 1, 6))


def ggx_d(cos_h: torch.Tensor, alpha: float) -> torch.Tensor:
    """GGX / Trowbridge-Reitz normal distribution D(n.h) (integrates to 1 against n.h over the hemisphere)."""
    a2 = alpha * alpha
    denom = cos_h * cos_h * (a2 - 1.0) + 1.0
    return a2 / (math.pi * denom * denom)


def lobe_weight(cos_nl: torch.Tensor, roughness: float) -> torch.Tensor:
    """w(n.l) of the module doc: the split-sum prefilter kernel as a function of n.l (n = v).

    With (n.h)^2 = (1 + n.l) / 2, D's denominator is affine in n.l: a few in-place passes
    over the [texels, pixels] matrix, which is the whole cost of a quadrature level."""
    alpha = max(roughness * roughness, 1e-4)
    a2 = alpha * alpha
    k = (a2 - 1.0) / 2.0
    denom = cos_nl.mul(k).add_(k + 1.0)  # (n.h)^2 (a2 - 1) + 1
    denom.mul_(denom)
    return cos_nl.clamp_min(0.0).div_(denom).mul_(a2 / math.pi)


def _hammersley(n: int, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    i = torch.arange(n, dtype=torch.int64)
    bits = torch.zeros(n, dtype=torch.float64)
    scale, v = 0.5, i.clone()
    for _ in range(32):  # radical inverse in base 2
        bits += (v & 1).to(torch.float64) * scale
        v >>= 1
        scale /= 2
    return ((i.to(torch.float64) + 0.5) / n).to(dtype), bits.to(dtype)


def _tangent_frame(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    up = torch.where((n[..., 1:2].abs() < 0.999), torch.tensor([0.0, 1.0, 0.0], dtype=n.dtype),
                     torch.tensor([1.0, 0.0, 0.0], dtype=n.dtype))
    t = torch.nn.functional.normalize(torch.cross(up.expand_as(n), n, dim=-1), dim=-1)
    return t, torch.cross(n, t, dim=-1)


def _prefilter_level(pyramid: list[torch.Tensor], n: torch.Tensor, roughness: float, samples: int) -> torch.Tensor:
    """P(n) for unit directions n [K, 3] from an equirect pyramid (finest first) -> [K, 3]."""
    alpha = max(roughness * roughness, 1e-4)
    u1, u2 = _hammersley(samples, dtype=n.dtype)
    cos_h = torch.sqrt((1.0 - u1) / (1.0 + (alpha * alpha - 1.0) * u1))
    sin_h = torch.sqrt((1.0 - cos_h * cos_h).clamp_min(0.0))
    phi = 2.0 * math.pi * u2
    # sample solid angle 1 / (N pdf(l)), pdf(l) = D(h) (n.h) / (4 v.h) = D / 4 when n = v
    omega_s = 4.0 / (samples * ggx_d(cos_h, alpha))
    h0 = pyramid[0].shape[0]
    omega_p = 2.0 * math.pi / (h0 * h0)  # mean pixel solid angle of the finest level (4 pi / (2 h^2))
    lod = (0.5 * torch.log2(omega_s / omega_p) + LOD_BIAS).clamp(0.0, len(pyramid) - 1.0)
    tangent, bitangent = _tangent_frame(n)
    # all samples at once: h [K, M, 3], l = reflect(-n, h)
    h = (
        tangent[:, None] * (sin_h * torch.cos(phi))[None, :, None]
        + bitangent[:, None] * (sin_h * torch.sin(phi))[None, :, None]
        + n[:, None] * cos_h[None, :, None]
    )
    nh = (n[:, None] * h).sum(-1, keepdim=True)
    l = 2.0 * nh * h - n[:, None]
    nl = (n[:, None] * l).sum(-1, keepdim=True).clamp_min(0.0)  # [K, M, 1]
    value = torch.zeros_like(l)
    lo = lod.floor().long()
    frac = (lod - lo)[None, :, None].to(l.dtype)
    for level in sorted(set(lo.tolist()) | set((lo + 1).clamp(max=len(pyramid) - 1).tolist())):
        w_lo = torch.where(lo == level, 1.0, 0.0)[None, :, None] * (1.0 - frac)
        w_hi = torch.where((lo + 1).clamp(max=len(pyramid) - 1) == level, 1.0, 0.0)[None, :, None] * frac
        w = w_lo + w_hi
        cols = (w[0, :, 0] > 0).nonzero()[:, 0]
        if cols.numel():
            value[:, cols] += sample_envmap(pyramid[level], l[:, cols]) * w[:, cols]
    return (value * nl).sum(1) / nl.sum(1).clamp_min(1e-30)


def _quadrature_level(pyramid: list[torch.Tensor], n: torch.Tensor, roughness: float, size: int) -> torch.Tensor:
    """P(n) by direct quadrature of the kernel over a source level with ~2 pixels per texel."""
    target = max(16, QUADRATURE_SOURCE_RATIO * size)
    source = next((p for p in pyramid if p.shape[0] <= target), pyramid[-1])
    h = source.shape[0]
    d = equirect_directions(h, dtype=torch.float32).reshape(-1, 3)
    radiance = (source.reshape(-1, 3).double() * solid_angles(h, dtype=torch.float64).reshape(-1, 1)).to(torch.float32)
    omega = solid_angles(h, dtype=torch.float32).reshape(-1, 1)
    rhs = torch.cat((radiance, omega), dim=1)  # [P, 4]: weighted radiance and the normaliser in one product
    out = []
    for chunk in n.to(torch.float32).split(max(1, (1 << 22) // d.shape[0])):
        out.append(lobe_weight(chunk @ d.T, roughness) @ rhs)
    acc = torch.cat(out).to(torch.float64)
    return acc[:, :3] / acc[:, 3:].clamp_min(1e-300)


def prefiltered_cubemap(envmap: torch.Tensor, size: int, levels: int | None = None,
                        samples: int = DEFAULT_SAMPLES) -> list[torch.Tensor]:
    """GGX-prefiltered cube mip chain: `levels` tensors [6, size >> i, size >> i, 3] (float32)."""
    check_envmap(envmap)
    if size < 1 or size & (size - 1):
        raise ValueError(f"cube face size must be a power of two, got {size}")
    levels = levels or default_levels(size)
    if not 1 <= levels <= int(math.log2(size)) + 1:
        raise ValueError(f"levels must be in 1..{int(math.log2(size)) + 1} for {size}-texel faces, got {levels}")
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    source = torch.nan_to_num(envmap.detach().to(torch.float32), nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
    pyramid = [source]
    while pyramid[-1].shape[0] > 2:
        pyramid.append(resize_envmap(pyramid[-1], pyramid[-1].shape[0] // 2))
    out = [equirect_to_cubemap(source, size).to(torch.float32)]
    for i in range(1, levels):
        s = size >> i
        n = cubemap_directions(s, dtype=torch.float32).reshape(-1, 3)
        r = roughness_of_level(i, levels)
        if s <= QUADRATURE_MAX_FACE:
            faces = _quadrature_level(pyramid, n, r, s)
        else:
            faces = _prefilter_level(pyramid, n, r, samples)
        out.append(faces.reshape(6, s, s, 3).to(torch.float32))
    return out


__all__ = ["prefiltered_cubemap", "roughness_of_level", "default_levels", "lobe_weight", "ggx_d"]
