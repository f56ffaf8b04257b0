"""Observed surfaces: the frames' points and radiance, looked up along each direction.

A network over (x, d) learns slowly how what a direction hits changes with the probe's
position (parallax): on the moving-camera suite the draft field's matte error was 1.09x its
prior's, and blending the prior's own maps between lattice nodes 0.4 m apart lost as much
(docs/engine.md, "Where moving-camera's loss comes from"). This layer keeps what the frames
showed as a point cloud (positions [M, 3], linear radiance per time knot [M, K, 3] and a 0/1
`used` flag per row, saved with the field) and answers a probe the way the reprojection prior does: splat the
points seen from the probe into an `height`-row equirect map with a z-buffer
(core.envmap.splat_points), then read it bilinearly along each direction. Where the splat has
points (coverage c in [0, 1], the bilinear weight of seen pixels) the field's answer moves to it
linearly (energy kept) by s = c (1 - w), w the view-detail weight: near a capturing camera the photo
fit at full resolution answers, away from the cameras the observed surfaces do, and the network
(with its lattice and emitters) answers every direction nothing observed.

The engine fills the layer after the distillation (core.engine.surface_extraction): during training it is
empty, so the network still learns every direction. Time: each knot holds the frame nearest to
its time; a probe reads the nearest knot (a switch stays a step, as in the frames).
"""
from __future__ import annotations

import torch
from torch import nn

from core.conventions import equirect_width
from core.envmap import equirect_stencil, pad_poles, splat_points


class ObservedSurfaces(nn.Module):
    """Up to `count` points with `knots` radiance samples each, splatted at `height` rows."""

    def __init__(self, count: int, knots: int, height: int):
        super().__init__()
        if count < 1 or knots < 1 or height < 2:
            raise ValueError(
                f"ObservedSurfaces needs count, knots >= 1 and height >= 2, got {count}, {knots}, {height}"
            )
        self.height = int(height)
        self.register_buffer("points", torch.zeros(count, 3))
        self.register_buffer("colors", torch.zeros(count, knots, 3))
        self.register_buffer("used", torch.zeros(count))  # float 0 / 1: the artefact holds float32 only

    @property
    def knots(self) -> int:
        return self.colors.shape[1]

    def set_surfaces(self, points: torch.Tensor, colors: torch.Tensor) -> None:
        """points [P, 3] metres (P <= count; non-finite rows are dropped), colors [P, knots, 3]
        linear radiance (>= 0); the rest of the layer is emptied."""
        points = torch.as_tensor(points, dtype=torch.float32).reshape(-1, 3)
        colors = torch.as_tensor(colors, dtype=torch.float32).reshape(points.shape[0], self.knots, 3)
        ok = torch.isfinite(points).all(-1) & torch.isfinite(colors).all((-1, -2))
        points, colors = points[ok], colors[ok].clamp_min(0.0)
        if points.shape[0] > self.points.shape[0]:
            raise ValueError(f"{points.shape[0]} points for a layer of {self.points.shape[0]}")
        with torch.no_grad():
            for buffer in (self.points, self.colors, self.used):
                buffer.zero_()
            self.points[:points.shape[0]] = points
            self.colors[:points.shape[0]] = colors
            self.used[:points.shape[0]] = 1.0

    def knot_at(self, tn: torch.Tensor | None) -> int:
        """The knot nearest to one normalised time tn (a [1, 1] tensor or None: knot 0)."""
        if tn is None or self.knots == 1:
            return 0
        return int(torch.round((tn.reshape(-1)[0].clamp(-1.0, 1.0) + 1.0) * 0.5 * (self.knots - 1)))

    def is_empty(self) -> bool:
        return not bool((self.used > 0.5).any())

    def splat(self, x: torch.Tensor, tn: torch.Tensor | None, max_radiance: float) -> torch.Tensor | None:
        """The padded look-up table [(h + 2) * 2h, 4] of one probe at world x [1, 3] (normalised
        time tn [1, 1] or None): seen x radiance (3, capped at `max_radiance`) and seen (1); None
        when the layer holds no point."""
        ok = self.used > 0.5
        if not bool(ok.any()):
            return None
        pts = self.points[ok].to(x.dtype)
        col = self.colors[ok, self.knot_at(tn)].to(x.dtype).clamp(max=max_radiance)
        env, seen = splat_points(pts, col, x.reshape(1, 3), self.height)
        seen = seen[..., None].to(x.dtype)
        return pad_poles(torch.cat((seen * env, seen), -1))[0]

    def lookup(self, table: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(radiance [N, 3], coverage [N] in [0, 1]) of a probe's table along unit d [N, 3]:
        bilinear in linear radiance over the seen taps (as the prior resizes its maps, so a lamp
        keeps its energy; interpolating log radiance would lose it)."""
        index, weight = equirect_stencil(d, self.height)
        summed = (weight[..., None].to(table.dtype) * table[index]).sum(1)
        coverage = summed[:, 3].clamp(0.0, 1.0)
        return summed[:, :3] / summed[:, 3:].clamp_min(1e-12), coverage

    @staticmethod
    def blend(radiance: torch.Tensor, observed: torch.Tensor, strength: torch.Tensor, floor: float) -> torch.Tensor:
        """radiance [N, 3] moved linearly towards observed [N, 3] by strength [N], at least `floor`."""
        s = strength[:, None].to(radiance.dtype)
        return torch.lerp(radiance, observed.to(radiance.dtype), s).clamp_min(floor)

    def extra_repr(self) -> str:
        return (f"count={self.points.shape[0]}, knots={self.knots}, height={self.height} "
                f"({equirect_width(self.height)} columns)")
