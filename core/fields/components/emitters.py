"""Emitters: small bright sources as world-space spheres added to a field's radiance.

An MLP over (x, t, d) with positional encodings cannot hold a lamp a few degrees wide whose
direction moves with x: measured on the simulator, a lamp the prior showed at a held-out probe
(peak 6, 64-row map) came out of the distilled field at 0.4, and the probe's matte-sphere
error was 4.5x the prior's (docs/engine.md, "Small bright sources"). Here each such source is
an explicit sphere: centre p, radius R and an intensity I(t) (radiance x projected area, RGB,
per time knot, measured in the frames by core.engine.emitter_detection). Seen from x it adds a
spherical-Gaussian lobe towards p whose integral over the sphere is I(t) / |p - x|^2 (energy
exact at any distance), whose width is the sphere's angular radius or, where that is finer,
`sigma_floor` (half a pixel or so of the map asked for: a lamp narrower than a pixel is
area-averaged, not point-sampled and missed). A learned gate per emitter on a coarse grid over
the scene box (sigmoid, starting visible) lets the distillation turn a source off where the
prior sees it occluded (under a table).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

# the gate's logit at start: sigmoid(4.6) = 0.99, i.e. every emitter visible from everywhere
GATE_START = 4.6
MIN_LOG_INTENSITY = math.log(1e-12)
MAX_LOG_INTENSITY = 80.0  # exp(88) overflows float32, and inf x a zero lobe is NaN


class Emitters(nn.Module):
    """K spheres: centres and radii (buffers), per-knot log intensities and visibility gates
    (parameters the distillation refines), all saved with the field; `set_sources` sets them."""

    def __init__(self, count: int, knots: int, gate_resolution: int):
        super().__init__()
        if count < 1 or knots < 1 or gate_resolution < 1:
            raise ValueError(
                f"Emitters needs count, knots, gate_resolution >= 1, got {count}, {knots}, {gate_resolution}"
            )
        self.register_buffer("centres", torch.zeros(count, 3))
        self.register_buffer("radii", torch.full((count,), 0.01))
        # measured, then refined by the distillation (the prior's maps may hold more of a clipped lamp's energy)
        self.log_intensity = nn.Parameter(torch.full((count, knots, 3), MIN_LOG_INTENSITY))
        g = gate_resolution
        self.gate = nn.Parameter(torch.full((1, count, g, g, g), GATE_START))

    @property
    def count(self) -> int:
        return self.centres.shape[0]

    def set_sources(self, centres: torch.Tensor, radii: torch.Tensor, intensity: torch.Tensor) -> None:
        """centres [K, 3] metres, radii [K] metres, intensity [K, knots, 3] (>= 0, linear)."""
        with torch.no_grad():
            self.centres.copy_(torch.as_tensor(centres, dtype=torch.float32).reshape(self.centres.shape))
            self.radii.copy_(torch.as_tensor(radii, dtype=torch.float32).reshape(self.radii.shape).clamp_min(1e-4))
            i = torch.as_tensor(intensity, dtype=torch.float32).reshape(self.log_intensity.shape)
            self.log_intensity.copy_(torch.log(torch.nan_to_num(i, nan=0.0).clamp_min(0.0) + 1e-12))

    def total_variation(self) -> torch.Tensor:
        """Mean L1 change of the log intensities between neighbouring knots (0 with one knot)."""
        li = self.log_intensity
        return (li[:, 1:] - li[:, :-1]).abs().mean() if li.shape[1] > 1 else li.sum() * 0.0

    def intensity(self, tn: torch.Tensor | None) -> torch.Tensor:
        """[n or 1, K, 3] intensity at normalised times tn [n, 1] (None: one row; linear between knots)."""
        knots = self.log_intensity.shape[1]
        li = self.log_intensity.clamp(max=MAX_LOG_INTENSITY).exp()  # [K, knots, 3], finite in float32
        if knots == 1 or tn is None:
            return li[:, 0][None]
        pos = ((tn.reshape(-1).clamp(-1.0, 1.0) + 1.0) * 0.5 * (knots - 1)).to(li.dtype)
        i0 = pos.floor().long().clamp(0, knots - 2)
        w = (pos - i0.to(pos.dtype))[:, None, None]
        return (1.0 - w) * li[:, i0].permute(1, 0, 2) + w * li[:, i0 + 1].permute(1, 0, 2)

    def visibility(self, xn: torch.Tensor) -> torch.Tensor:
        """[B, K] gate in (0, 1) at normalised positions xn [B, 3] (trilinear on the grid)."""
        grid = xn.to(self.gate.dtype)[None, :, None, None, :]  # [1, B, 1, 1, 3] as (x, y, z) -> (W, H, D)
        g = F.grid_sample(self.gate, grid, mode="bilinear", padding_mode="border", align_corners=True)
        return torch.sigmoid(g.reshape(self.count, -1).T)

    def radiance(self, x: torch.Tensor, xn: torch.Tensor, tn: torch.Tensor | None, d: torch.Tensor,
                 sigma_floor: float) -> torch.Tensor:
        """[B, 3] added radiance at world positions x [B, 3] (normalised xn, times tn [B, 1]) along
        unit d [B, 3]; x, xn and tn may have one row for all of d (an env map's probe: its
        distances, lobe widths and gates are then worked out once)."""
        rel = self.centres[None].to(x.dtype) - x[:, None, :]  # [B, K, 3]
        dist = rel.norm(dim=-1).clamp_min(1e-6)
        dist_eff = torch.maximum(dist, self.radii[None].to(x.dtype))  # inside a source: as at its surface
        mu = rel / dist[..., None]
        cos = (mu * d[:, None, :]).sum(-1).clamp(-1.0, 1.0)  # [B, K]
        alpha = torch.asin((self.radii[None].to(x.dtype) / dist_eff).clamp(max=1.0))
        sigma = alpha.clamp_min(max(float(sigma_floor), 1e-4))
        lam = 1.0 / sigma.pow(2)
        # the lobe a exp(lam (cos - 1)) integrates to 2 pi a (1 - exp(-2 lam)) / lam
        norm = lam / (2.0 * math.pi * (-torch.expm1(-2.0 * lam)))
        energy = self.intensity(tn).to(x.dtype) / dist_eff.pow(2)[..., None]  # [B or 1, K, 3]
        lobe = norm * torch.exp(lam * (cos - 1.0)) * self.visibility(xn)
        return (energy * lobe[..., None]).sum(1)
