"""Main (dominant) light + ambient SH split of an env map, as ARCore Environmental HDR reports it.

ARCore always gives AR clients a main directional light (direction, RGB intensity) plus
ambient spherical harmonics. A fixed "peak / surroundings" threshold finds nothing on real or
estimated maps (their lights are blurred: peaks ~2x their surroundings), so the light is
FITTED, and every answer carries a `confidence` and a `reason`:

1. **Search** (coarse, height 24): a matched filter over the sphere. For every candidate
   direction c and cap radius r in `cap_radii_deg`, the excess power of the cap
   P(c, r) = integral over the cap of (L - fill) dw, with fill = the mean luminance of the
   annulus r..2r around it. The (c, r) with the largest P is the light: a small bright lamp
   and a broad bright window are both found, at their own scale, and a wide gentle
   gradient gives little excess (its annulus is nearly as bright as its cap).
2. **Fit** (full resolution): within the cap, excess_i = max(L_i - fill, 0) per channel,
   fill = the per-channel median of the annulus (robust to a second light nearby), kept
   only where the excess luminance is >= `CORE_FRACTION` of the cap's peak excess: a lamp is
   the lamp, not the lamp plus the patch of wall it lights (that patch stays in the ambient
   SH), while a uniform window or a blurred lobe is kept whole. The cap is re-centred on the excess-weighted mean
   direction (twice). The lobe is summarised as a
   von Mises-Fisher lobe: `direction` = mean direction, `sharpness` kappa from the mean
   resultant length, `solid_angle` = the excess's effective area.
3. **Intensity**: `intensity_rgb` = integral of the excess (radiance x sr). The ambient SH is
   the SH of the map with the excess removed (L - excess), so `ambient SH + a directional
   light of intensity_rgb` has the map's total power and reproduces its irradiance up to the
   lobe's spread (exact for a point light; `irradiance_error` reports the worst relative
   difference over the sphere of normals).
4. **Confidence**: the share of the irradiance facing the light that the light gives,
   E_light(mu) / E_map(mu), times (1 - 1/contrast) with contrast = mean cap radiance / fill,
   times the uniqueness 1 - P_rival / P_light, where P_rival is the excess power of the best
   candidate at least 45 deg (or two cap radii) away: two comparable sources mean no single
   direction AR can trust. `found` = confidence >= `min_confidence` (0.1). A map with no
   dominant light (uniform, gentle gradients, all zero, several comparable sources) still gets
   the best candidate's direction with `found=False`, a small confidence and a reason saying why.
   On fields estimated from simulated captures (tests/test_readme_examples.py), a found light
   points within 20 deg of the source that dominates the probe's irradiance; estimated lamps
   that came out 20-50 deg away score 0.07-0.08 and are not found.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import torch

from core.conventions import equirect_directions
from core.envmap import check_envmap, irradiance, resize_envmap, solid_angles
from core.exposure import luminance
from core.sh import project_sh, sh_irradiance

SEARCH_HEIGHT = 24  # coarse search grid: 1152 candidate directions, 7.5 deg apart
CORE_FRACTION = 0.05  # the light = cap pixels whose excess is >= this x the cap's peak excess
ERROR_HEIGHT = 32  # irradiance_error is measured on the map area-downsampled to this height
SEPARATION_DEG = 45.0  # a rival source is a candidate at least this far (or two cap radii) from the light


@dataclass(frozen=True)
class DominantLightConfig:
    cap_radii_deg: tuple[float, ...] = (8.0, 16.0, 30.0)  # light scales searched (cap radius; annulus r..2r)
    # found = confidence >= this (maps without a light score < 0.005; estimated maps 20-50 deg off score 0.07-0.08)
    min_confidence: float = 0.1
    refine_steps: int = 2  # re-centrings of the cap at full resolution
    irradiance_normals: int = 128  # normals on which irradiance_error is measured

    def __post_init__(self):
        if not self.cap_radii_deg or not all(0.0 < r <= 45.0 for r in self.cap_radii_deg):
            raise ValueError(f"cap_radii_deg must be non-empty with every radius in (0, 45], got {self.cap_radii_deg}")
        if not (0.0 <= self.min_confidence <= 1.0):
            raise ValueError(f"min_confidence must be in [0, 1], got {self.min_confidence}")
        if self.refine_steps < 0:
            raise ValueError(f"refine_steps must be >= 0, got {self.refine_steps}")
        if self.irradiance_normals < 1:
            raise ValueError(f"irradiance_normals must be >= 1, got {self.irradiance_normals}")


@dataclass
class DominantLight:
    direction: torch.Tensor  # [3] unit, direction light arrives FROM (world frame)
    intensity_rgb: torch.Tensor  # [3] integrated excess radiance of the lobe (radiance x sr)
    solid_angle: float  # effective sr of the lobe's excess (0 for an all-zero map)
    ambient_sh: torch.Tensor  # [9, 3] radiance SH of the map without the light (core.sh basis)
    found: bool  # confidence >= config.min_confidence
    reason: str  # why it was or was not found, in words
    confidence: float = 0.0  # [0, 1], see the module doc
    sharpness: float = 0.0  # vMF kappa of the lobe (large = compact); 0 when unknown
    contrast: float = 1.0  # mean cap radiance / fill (luminance)
    irradiance_error: float = 0.0  # max over normals |E_split - E_map| / max E_map
    mask: torch.Tensor | None = field(default=None, repr=False)  # [H, 2H] bool, the cap used

    @property
    def angular_radius_deg(self) -> float:
        """Radius of the cap holding ~63 % of a vMF lobe of this sharpness (0 when unknown)."""
        return math.degrees(math.acos(max(-1.0, 1.0 - 1.0 / self.sharpness))) if self.sharpness > 0 else 0.0

    def to_dict(self) -> dict:
        """JSON-able summary; ambient_sh in our layout (a consumer's: core.export.sh_layouts)."""
        return {
            "found": self.found,
            "reason": self.reason,
            "confidence": float(self.confidence),
            "direction": [float(v) for v in self.direction],
            "intensity_rgb": [float(v) for v in self.intensity_rgb],
            "solid_angle_sr": float(self.solid_angle),
            "sharpness": float(self.sharpness),
            "contrast": float(self.contrast),
            "irradiance_error": float(self.irradiance_error),
            "ambient_sh": self.ambient_sh.tolist(),
        }


@functools.lru_cache(maxsize=4)
def _search_grid(radii_deg: tuple[float, ...]):
    """Directions, solid angles and float32 cap indicator matrices [N, N] of the coarse grid
    (one per radius r and 2r; cached: the matched filter is then a few mat-vec products)."""
    d = equirect_directions(SEARCH_HEIGHT, dtype=torch.float64).reshape(-1, 3)
    omega = solid_angles(SEARCH_HEIGHT, dtype=torch.float64).reshape(-1)
    cos = (d @ d.T).to(torch.float32)
    angles = sorted({a for r in radii_deg for a in (r, 2 * r)})
    caps = {a: (cos >= math.cos(math.radians(a))).to(torch.float32) for a in angles}
    return d, omega.to(torch.float32), caps


def _search(L: torch.Tensor, radii_deg: tuple[float, ...]) -> tuple[torch.Tensor, float, float]:
    """Coarse matched filter: (direction [3], cap radius in degrees) with the largest excess power,
    and the share of that power the best candidate elsewhere (at least `SEPARATION_DEG` or two
    radii away, any radius) has: near 1 when another source is as strong."""
    d, omega, caps = _search_grid(radii_deg)
    small = resize_envmap(L, SEARCH_HEIGHT) if L.shape[0] > SEARCH_HEIGHT else L
    if small.shape[0] != SEARCH_HEIGHT:  # tiny maps: upsample by nearest rows/cols
        rows = (torch.arange(SEARCH_HEIGHT) * small.shape[0]) // SEARCH_HEIGHT
        cols = (torch.arange(2 * SEARCH_HEIGHT) * small.shape[1]) // (2 * SEARCH_HEIGHT)
        small = small[rows][:, cols]
    power = (luminance(small).reshape(-1) * omega.double()).to(torch.float32)
    excess = {}
    for r in radii_deg:
        cap_sr, cap2_sr = caps[r] @ omega, caps[2 * r] @ omega
        cap_p, cap2_p = caps[r] @ power, caps[2 * r] @ power
        fill = (cap2_p - cap_p) / (cap2_sr - cap_sr).clamp_min(1e-30)  # mean of the annulus r..2r
        excess[r] = cap_p - fill * cap_sr
    best_r = max(radii_deg, key=lambda r: float(excess[r].max()))
    best = int(excess[best_r].argmax())
    top = float(excess[best_r][best])
    far = (d @ d[best]) < math.cos(math.radians(max(SEPARATION_DEG, 2.0 * best_r)))
    rival = max(float(excess[r][far].max()) if bool(far.any()) else 0.0 for r in radii_deg)
    return d[best], best_r, (min(max(rival, 0.0) / top, 1.0) if top > 0 else 1.0)


def _fit(L, dirs, omega, centre, radius_deg, steps):
    """Excess of the cap around `centre` over its annulus' median, re-centred `steps` times."""
    cos_r, cos_2r = math.cos(math.radians(radius_deg)), math.cos(math.radians(2 * radius_deg))
    for _ in range(steps + 1):
        cos = dirs @ centre
        cap = cos >= cos_r
        ring = (cos < cos_r) & (cos >= cos_2r)
        fill = L[ring].median(dim=0).values if bool(ring.any()) else torch.zeros(3, dtype=L.dtype)
        excess = (L - fill).clamp_min(0.0) * cap[..., None]
        lum = luminance(excess)
        excess = excess * (lum >= CORE_FRACTION * lum.max())[..., None]
        weights = luminance(excess) * omega
        mean = (dirs * weights[..., None]).sum((0, 1))
        if float(mean.norm()) <= 0.0:
            break
        centre = mean / mean.norm()
    return centre, cap, fill, excess, weights, mean


def extract_dominant_light(envmap: torch.Tensor, config: DominantLightConfig | None = None) -> DominantLight:
    """Fit the main light of an HDR env map [H, 2H, 3] and split off the ambient SH (module doc).

    Non-finite radiance is treated as 0 and negative radiance is clamped to 0.
    """
    cfg = config or DominantLightConfig()
    h = check_envmap(envmap)
    device, dtype = envmap.device, envmap.dtype
    L = torch.nan_to_num(envmap.detach().cpu().to(torch.float64), nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
    omega = solid_angles(h, dtype=torch.float64)
    dirs = equirect_directions(h, dtype=torch.float64)

    def out(direction, intensity, sr, ambient, found, reason, **kw) -> DominantLight:
        return DominantLight(direction=direction.to(device, dtype), intensity_rgb=intensity.to(device, dtype),
                             solid_angle=float(sr), ambient_sh=ambient.to(device, dtype), found=found, reason=reason,
                             **kw)

    total = float((luminance(L) * omega).sum())
    if not total > 0.0:
        return out(
            torch.tensor([0.0, 1.0, 0.0]),
            torch.zeros(3),
            0.0,
            project_sh(L),
            False,
            "no dominant light: the map is all zero",
            mask=torch.zeros(h, 2 * h, dtype=torch.bool, device=device),
        )

    centre, radius, rival = _search(L, tuple(cfg.cap_radii_deg))
    centre, cap, fill, excess, weights, mean = _fit(L, dirs, omega, centre, radius, cfg.refine_steps)
    intensity = (excess * omega[..., None]).sum((0, 1))
    power = float(weights.sum())
    ambient_sh = project_sh(L - excess)
    mask = cap.to(device)
    if not power > 0.0:
        return out(centre, torch.zeros(3), 0.0, ambient_sh, False,
                   "no dominant light: no direction is brighter than its surroundings", mask=mask)

    r_bar = min(float(mean.norm()) / power, 1.0 - 1e-12)  # mean resultant length of the excess
    kappa = r_bar * (3.0 - r_bar * r_bar) / (1.0 - r_bar * r_bar)  # Banerjee et al.'s vMF estimate
    peak = float((luminance(excess) * omega).max())
    solid_angle = power / max(float(luminance(excess).max()), 1e-300) if peak > 0 else 0.0
    cap_sr = float(omega[cap].sum())
    fill_lum = float(luminance(fill))
    cap_lum = float((luminance(L) * omega)[cap].sum()) / max(cap_sr, 1e-300)
    contrast = cap_lum / fill_lum if fill_lum > 0 else math.inf
    facing = float(luminance(irradiance(L, centre[None]))[0])
    share = min(power / facing, 1.0) if facing > 0 else 0.0
    uniqueness = 1.0 - rival
    confidence = share * (1.0 - 1.0 / contrast) * uniqueness if contrast > 1.0 else 0.0
    found = confidence >= cfg.min_confidence

    normals = torch.nn.functional.normalize(
        torch.randn(cfg.irradiance_normals, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64), dim=-1)
    split = sh_irradiance(ambient_sh, normals) + (normals @ centre).clamp_min(0.0)[:, None] * intensity
    coarse = resize_envmap(L, ERROR_HEIGHT) if h > ERROR_HEIGHT else L
    full = irradiance(coarse, normals)
    err = float((split - full).abs().max() / full.abs().max().clamp_min(1e-300))

    words = (f"main light gives {share:.0%} of the irradiance facing it, {contrast:.3g}x its surroundings"
             + (f", a rival source elsewhere has {rival:.0%} of its power" if rival >= 0.25 else "")
             + f" (confidence {confidence:.2f}")
    reason = (f"found: {words} >= {cfg.min_confidence:g})" if found
              else f"no dominant light: {words} < {cfg.min_confidence:g}); direction is the best guess")
    return out(centre, intensity, solid_angle, ambient_sh, found, reason, confidence=confidence, sharpness=kappa,
               contrast=contrast, irradiance_error=err, mask=mask)


__all__ = ["DominantLight", "DominantLightConfig", "extract_dominant_light"]
