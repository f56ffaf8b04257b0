"""Dominant light + ambient SH split of an env map (ARCore Environmental HDR style).

ARCore reports a main directional light (direction, RGB intensity) plus ambient
spherical harmonics. We do the same from an HDR env map:

1. luminance peak; region = pixels brighter than `threshold_fraction` x peak that are
   connected to the peak (4-connected, wrapping across the phi seam and across the poles);
2. local fill = solid-angle-weighted mean radiance of a thin ring around the region;
3. intensity = integral over the region of (L - fill) dw, so a directional light of that
   RGB intensity gives the same irradiance as the region's excess (for a small region);
   direction = the (L - fill)-luminance- and solid-angle-weighted mean direction, normalised;
4. ambient SH = SH of the map with the region replaced by the fill, so
   light + ambient reproduces the map's low-frequency lighting without double counting.

No dominant light (uniform-ish maps, all-zero maps): intensity 0, `found=False` and a
`reason`; the ambient SH then carries the whole map.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from core.conventions import equirect_directions
from core.envmap import check_envmap, solid_angles
from core.exposure import luminance
from core.sh import project_sh, to_arcore_27


@dataclass(frozen=True)
class DominantLightConfig:
    threshold_fraction: float = 0.5  # region = connected pixels with luminance >= this x peak
    max_solid_angle: float = 0.1 * 4.0 * math.pi  # larger bright regions are "ambient", not a light
    min_contrast: float = 4.0  # peak luminance / fill luminance needed to call it a light
    ring_width: int = 2  # pixels of the ring used to estimate the local fill

    def __post_init__(self):
        if not (0.0 < self.threshold_fraction < 1.0):
            raise ValueError(f"threshold_fraction must be in (0, 1), got {self.threshold_fraction}")
        if not (self.max_solid_angle > 0.0):
            raise ValueError(f"max_solid_angle must be > 0, got {self.max_solid_angle}")
        if not (self.min_contrast >= 1.0):
            raise ValueError(f"min_contrast must be >= 1, got {self.min_contrast}")
        if self.ring_width < 1:
            raise ValueError(f"ring_width must be >= 1, got {self.ring_width}")


@dataclass
class DominantLight:
    direction: torch.Tensor  # [3] unit, direction light arrives FROM (world frame)
    intensity_rgb: torch.Tensor  # [3] integrated excess radiance of the region (radiance x sr)
    solid_angle: float  # sr covered by the region (0 when not found)
    ambient_sh: torch.Tensor  # [9, 3] radiance SH of the map without the light (core.sh basis)
    found: bool
    reason: str  # why no light was found ("" when found)
    mask: torch.Tensor | None = None  # [H, 2H] bool, the region

    def to_dict(self) -> dict:
        """JSON-able summary (ARCore-compatible ambient SH included)."""
        return {
            "found": self.found,
            "reason": self.reason,
            "direction": [float(v) for v in self.direction],
            "intensity_rgb": [float(v) for v in self.intensity_rgb],
            "solid_angle_sr": float(self.solid_angle),
            "ambient_sh": self.ambient_sh.tolist(),
            "ambient_sh_arcore27": to_arcore_27(self.ambient_sh),
        }


def _connected_region(mask: np.ndarray, seed: tuple[int, int]) -> np.ndarray:
    """Pixels of `mask` 4-connected to `seed`, wrapping across the seam and the poles."""
    from scipy import ndimage
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    labels, n = ndimage.label(mask)
    h, w = mask.shape
    pairs = [(labels[:, 0], labels[:, -1])]  # phi seam
    half = w // 2
    for row in (0, h - 1):  # across a pole: column j meets column j + W/2 of the same row
        pairs.append((labels[row, :half], labels[row, half:]))
    a = np.concatenate([p[0] for p in pairs])
    b = np.concatenate([p[1] for p in pairs])
    keep = (a > 0) & (b > 0)
    graph = coo_matrix((np.ones(keep.sum()), (a[keep], b[keep])), shape=(n + 1, n + 1))
    _, component = connected_components(graph, directed=False)
    seed_label = labels[seed]
    return (labels > 0) & (component[labels] == component[seed_label])


def _ring(region: np.ndarray, width: int) -> np.ndarray:
    """Pixels within `width` steps of the region (seam-wrapped), excluding the region."""
    from scipy import ndimage

    pad = width
    wrapped = np.concatenate((region[:, -pad:], region, region[:, :pad]), axis=1)
    grown = ndimage.binary_dilation(wrapped, iterations=width)[:, pad:-pad]
    return grown & ~region


def extract_dominant_light(envmap: torch.Tensor, config: DominantLightConfig | None = None) -> DominantLight:
    """Split an HDR env map [H, 2H, 3] into one dominant light and ambient SH (see module doc).

    Non-finite radiance is treated as 0 and negative radiance is clamped to 0.
    """
    cfg = config or DominantLightConfig()
    h = check_envmap(envmap)
    device, dtype = envmap.device, envmap.dtype
    L = torch.nan_to_num(envmap.detach().to(torch.float64), nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
    omega = solid_angles(h, device=device, dtype=torch.float64)
    dirs = equirect_directions(h, device=device, dtype=torch.float64)
    lum = luminance(L)

    def none(reason: str) -> DominantLight:
        return DominantLight(
            direction=torch.tensor([0.0, 1.0, 0.0], dtype=dtype, device=device),
            intensity_rgb=torch.zeros(3, dtype=dtype, device=device),
            solid_angle=0.0,
            ambient_sh=project_sh(L).to(dtype),
            found=False,
            reason=reason,
            mask=torch.zeros(lum.shape, dtype=torch.bool, device=device),
        )

    peak = float(lum.max())
    if not peak > 0.0:
        return none("map is all zero (no light)")
    seed = tuple(int(i) for i in np.unravel_index(int(lum.argmax()), lum.shape))
    lum_np = lum.cpu().numpy()
    region_np = _connected_region(lum_np >= cfg.threshold_fraction * peak, seed)
    region = torch.from_numpy(region_np).to(device)
    region_sr = float(omega[region].sum())
    if region_sr > cfg.max_solid_angle:
        return none(f"brightest region covers {region_sr:.3g} sr > max_solid_angle {cfg.max_solid_angle:.3g} sr (no dominant light)")

    ring = torch.from_numpy(_ring(region_np, cfg.ring_width)).to(device)
    ring_sr = omega[ring].sum()
    fill = (L[ring] * omega[ring][:, None]).sum(0) / ring_sr if ring_sr > 0 else torch.zeros(3, dtype=torch.float64, device=device)
    fill_lum = float(luminance(fill))
    if peak < cfg.min_contrast * fill_lum:
        return none(f"peak luminance is only {peak / fill_lum:.3g}x its surroundings < min_contrast {cfg.min_contrast}")

    excess = (L[region] - fill).clamp_min(0.0) * omega[region][:, None]  # [N, 3] radiance x sr
    intensity = excess.sum(0)
    weights = luminance(excess)
    mean_dir = (dirs[region] * weights[:, None]).sum(0)
    norm = mean_dir.norm()
    direction = mean_dir / norm if norm > 1e-12 * max(float(weights.sum()), 1e-300) else dirs[seed]

    ambient = torch.where(region[..., None], fill.expand_as(L), L)
    return DominantLight(
        direction=direction.to(dtype),
        intensity_rgb=intensity.to(dtype),
        solid_angle=region_sr,
        ambient_sh=project_sh(ambient).to(dtype),
        found=True,
        reason="",
        mask=region,
    )
