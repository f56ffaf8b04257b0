"""The paper's ablation field: a lattice of learnable equirect env maps.

`resolution` = (nx, ny, nz) maps (default 3 x 3 x 3) of `env_height` x 2 `env_height` texels
sit at the nodes of a regular lattice spanning the normalised box [-1, 1]^3; with a time
input, `time_keyframes` such lattices span the capture's time range. L(x, t, d) is
multilinear over (t, x, y, z) and bilinear over d, in the logit domain (so interpolation
is geometric in radiance, like the other kinds' log-space outputs).

Direction sampling follows `core.envmap.sample_envmap` exactly (seam wrap, pole caps that
blend to the row mean), re-implemented here as a gather stencil so one call can read
a different map per row; tests check the two agree.
"""
from __future__ import annotations

import torch
from torch import nn

from core.conventions import direction_to_equirect_pixel, equirect_directions, equirect_width
from core.fields.base import INITIAL_RADIANCE, LightField, probe_chunks
from core.fields.config import FieldConfig
from core.fields.encodings import lattice_corners
from core.fields.normalization import SceneBounds


class GridField(LightField):
    def __init__(self, config: FieldConfig, bounds: SceneBounds):
        super().__init__(config, bounds)
        s = config.grid
        n_keys = s.time_keyframes if config.uses_time else 1
        self.lattice_dims = ((n_keys,) if config.uses_time else ()) + tuple(s.resolution)
        h = s.env_height
        init = self.logit_for_radiance(INITIAL_RADIANCE)
        # [keys * nx * ny * nz, h, 2h, 3] logits, lattice nodes in row-major (t, x, y, z) order
        self.maps = nn.Parameter(torch.full((_prod(self.lattice_dims), h, equirect_width(h), 3), init))

    def _lattice_coords(self, xn: torch.Tensor, tn: torch.Tensor | None) -> torch.Tensor:
        return xn if tn is None else torch.cat((tn, xn), dim=-1)

    def logits(self, xn, tn, d):
        node, w_node = lattice_corners(self._lattice_coords(xn, tn), self.lattice_dims)  # [B, C]
        pix, w_pix = equirect_stencil(d, self.config.grid.env_height)  # [B, 4]
        padded = pad_poles(self.maps)  # [M, (h+2) * w, 3]
        texels = padded.shape[1]
        flat = padded.reshape(-1, 3)
        index = node[:, :, None] * texels + pix[:, None, :]  # [B, C, 4]
        weight = w_node[:, :, None] * w_pix[:, None, :]
        return (weight[..., None] * flat[index]).sum(dim=(1, 2))

    def _envmap_logits(self, xn, tn, dirs, chunk_rows: int) -> torch.Tensor:
        """Blend the lattice maps once per probe, then resample them at `dirs` (both linear, so
        this equals evaluating every (probe, direction) pair)."""
        node, w_node = lattice_corners(self._lattice_coords(xn, tn), self.lattice_dims)  # [P, C]
        blended = (w_node[..., None, None, None] * self.maps[node]).sum(1)  # [P, h, w, 3]
        h = self.config.grid.env_height
        if dirs.shape[0] == h * equirect_width(h) and torch.equal(dirs, equirect_directions(h, device=dirs.device).reshape(-1, 3)):
            return blended.reshape(xn.shape[0], -1, 3)  # same pixel centres: sampling is the identity
        pix, w_pix = equirect_stencil(dirs, h)  # [N, 4]
        padded = pad_poles(blended)  # [P, texels, 3]
        out = xn.new_empty(xn.shape[0], dirs.shape[0], 3)
        for sl in probe_chunks(xn.shape[0], dirs.shape[0], chunk_rows):
            out[sl] = (w_pix[None, :, :, None] * padded[sl, pix]).sum(2)
        return out


def pad_poles(maps: torch.Tensor) -> torch.Tensor:
    """[M, h, w, 3] -> [M, (h + 2) * w, 3] with a pole row (the mean of the first / last row)
    above and below, the layout `equirect_stencil` indexes."""
    top = maps[:, :1].mean(dim=2, keepdim=True).expand(-1, 1, maps.shape[2], -1)
    bottom = maps[:, -1:].mean(dim=2, keepdim=True).expand(-1, 1, maps.shape[2], -1)
    return torch.cat((top, maps, bottom), dim=1).reshape(maps.shape[0], -1, maps.shape[-1])


def equirect_stencil(d: torch.Tensor, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear taps of unit directions d [N, 3] on a pole-padded h x 2h map.

    Returns (texel index into the (h + 2) x 2h padded layout [N, 4] long, weight [N, 4]).
    Same rule as core.envmap.sample_envmap: columns wrap at the seam; between the first
    (last) row centre and the pole the value blends towards the pole row.
    """
    h, w = int(height), equirect_width(height)
    row, col = direction_to_equirect_pixel(d, h)
    row = row.clamp(-0.5, h - 0.5)
    in_top, in_bottom = row < 0.0, row > h - 1
    r0 = torch.floor(row).clamp(0, max(h - 2, 0))
    t_row = row - r0
    upper = r0 + 1  # padded index of the upper row
    upper = torch.where(in_top, torch.zeros_like(upper), upper)
    t_row = torch.where(in_top, (row + 0.5) / 0.5, t_row)
    upper = torch.where(in_bottom, torch.full_like(upper, h), upper)
    t_row = torch.where(in_bottom, (row - (h - 1)) / 0.5, t_row)
    upper = upper.long()
    c0f = torch.floor(col)
    t_col = col - c0f
    c0 = c0f.long().remainder(w)
    c1 = (c0 + 1).remainder(w)
    index = torch.stack((upper * w + c0, upper * w + c1, (upper + 1) * w + c0, (upper + 1) * w + c1), dim=-1)
    weight = torch.stack(
        ((1 - t_row) * (1 - t_col), (1 - t_row) * t_col, t_row * (1 - t_col), t_row * t_col), dim=-1
    )
    return index, weight.to(d.dtype)


def _prod(values) -> int:
    out = 1
    for v in values:
        out *= int(v)
    return out
