"""Probes off the camera rays: points of the scene box that no frame shows inside a surface.

The radiance loop's other probes all lie on camera rays (in front of the depth, along a ray,
at the camera centre), so a field is only supervised inside the frusta. Users also query
beside and behind the camera, where the field would otherwise extrapolate while the prior
still answers (a reprojection of everything the frames saw). A free-space probe is drawn
uniformly in the scene box without its padding (core.fields.components.normalization) and kept unless a
frame sees it at or behind the depth there (inside a wall or furniture, or out of a window);
points no frame sees are kept: a room's free space is the likely guess there.

Only priors that answer anywhere (`PriorCapabilities.envmaps_anywhere`) get these probes: the
simulator's oracle, for one, refuses a point inside unseen furniture.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from core.capture.base import Capture
from core.conventions import camera_point_to_pixel, valid_depth_mask
from core.fields.components.normalization import MARGIN_FRACTION, SceneBounds

SURFACE_CLEARANCE = 0.95  # a kept probe is in front of 95 % of the planar depth where a frame sees it
MAX_FRAMES_CHECKED = 32  # evenly spaced frames a candidate is tested against (a long clip repeats itself)
CANDIDATES_PER_PROBE = 16  # draws per wanted probe; fewer probes come back when most of the box is solid


@dataclass(frozen=True)
class FreeSpaceSampler:
    lo: torch.Tensor  # [3] float64 world box
    hi: torch.Tensor
    w2c: torch.Tensor  # [F, 4, 4] float64 world-to-camera of the checked frames
    depth: torch.Tensor  # [F, H, W] planar depth of the checked frames
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def for_capture(cls, capture: Capture, bounds: SceneBounds) -> "FreeSpaceSampler":
        lo, hi = torch.tensor(bounds.lo, dtype=torch.float64), torch.tensor(bounds.hi, dtype=torch.float64)
        pad = (hi - lo) * MARGIN_FRACTION / (1.0 + 2.0 * MARGIN_FRACTION)  # undo the box's padding
        frames = capture.spread_frames(MAX_FRAMES_CHECKED)
        k = capture.intrinsics
        return cls(lo + pad, hi - pad, torch.linalg.inv(capture.poses[frames].double()), capture.depth[frames].double(),
                   float(k.fx), float(k.fy), float(k.cx), float(k.cy))

    def sample(self, n: int, gen: torch.Generator) -> torch.Tensor:
        """Up to n free-space points [m, 3] (float32, m <= n; 0 when every draw was inside a surface)."""
        if n <= 0:
            return torch.zeros(0, 3)
        cand = self.lo + (self.hi - self.lo) * torch.rand(
            n * CANDIDATES_PER_PROBE, 3, generator=gen, dtype=torch.float64
        )
        return cand[self.free(cand)][:n].float()

    def free(self, points: torch.Tensor) -> torch.Tensor:
        """[N] bool: no checked frame sees the point at or behind its depth (or past invalid depth)."""
        homog = torch.cat((points, torch.ones_like(points[:, :1])), -1)
        cam = torch.einsum("fij,nj->fni", self.w2c, homog)[..., :3]  # [F, N, 3]
        u, v, z = camera_point_to_pixel(cam, self.fx, self.fy, self.cx, self.cy)
        h, w = self.depth.shape[1:]
        seen = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        ui, vi = u.long().clamp(0, w - 1), v.long().clamp(0, h - 1)
        d = self.depth[torch.arange(self.depth.shape[0])[:, None], vi, ui]
        blocked = seen & (~valid_depth_mask(d) | (z >= SURFACE_CLEARANCE * d))
        return ~blocked.any(0)
