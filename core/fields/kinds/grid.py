"""The paper's ablation field: a lattice of learnable equirect env maps.

`resolution` = (nx, ny, nz) maps (default 3 x 3 x 3) of `env_height` x 2 `env_height` texels
sit at the nodes of a regular lattice spanning the normalised box [-1, 1]^3; with a time
input, `time_keyframes` such lattices span the capture's time range. L(x, t, d) is
multilinear over (t, x, y, z) and bilinear over d, in the logit domain (so interpolation
is geometric in radiance, like the other kinds' log-space outputs).

Direction sampling is `core.envmap.sample_envmap`'s rule (seam wrap, pole caps that blend
to the row mean) as the gather stencil `core.envmap.equirect_stencil`, so one call can read
a different map per row; tests check the two agree.
"""
from __future__ import annotations

import math

import torch
from pydantic import Field, model_validator
from torch import nn

from core.conventions import equirect_directions, equirect_width
from core.envmap import equirect_stencil, pad_poles
from core.fields.components.encodings import blend_lattice_maps, lattice_corners, lattice_maps_lookup
from core.fields.components.normalization import SceneBounds
from core.fields.components.settings import FieldSettings
from core.fields.kinds.base import INITIAL_RADIANCE, LightField, direction_blocks, probe_chunks
from core.fields.kinds.config import FieldConfig
from core.fields.kinds.registry import register_field


class GridSettings(FieldSettings):
    """The paper's ablation: a resolution[0] x [1] x [2] lattice of learnable equirect maps."""

    resolution: tuple[int, int, int] = (3, 3, 3)
    env_height: int = Field(16, ge=2, le=256)  # each map is env_height x 2*env_height
    time_keyframes: int = Field(4, ge=2, le=256)  # linear interpolation between keys (uses_time only)

    @model_validator(mode="after")
    def _resolution_positive(self):
        if min(self.resolution) < 2:
            raise ValueError(f"grid.resolution must be >= 2 per axis, got {self.resolution}")
        return self


@register_field("grid")
class GridField(LightField):
    Config = GridSettings

    def __init__(self, config: FieldConfig, bounds: SceneBounds):
        super().__init__(config, bounds)
        s = self.settings
        n_keys = s.time_keyframes if config.uses_time else 1
        self.lattice_dims = ((n_keys,) if config.uses_time else ()) + tuple(s.resolution)
        h = s.env_height
        init = self.logit_for_radiance(INITIAL_RADIANCE)
        # [keys * nx * ny * nz, h, 2h, 3] logits, lattice nodes in row-major (t, x, y, z) order
        self.maps = nn.Parameter(torch.full((math.prod(self.lattice_dims), h, equirect_width(h), 3), init))

    def _lattice_coords(self, xn: torch.Tensor, tn: torch.Tensor | None) -> torch.Tensor:
        return xn if tn is None else torch.cat((tn, xn), dim=-1)

    def logits(self, xn, tn, d):
        node, w_node = lattice_corners(self._lattice_coords(xn, tn), self.lattice_dims)  # [B, C]
        return lattice_maps_lookup(self.maps, node, w_node, d)

    def _envmap_logits(self, xn, tn, dirs, chunk_rows: int) -> torch.Tensor:
        """Blend the lattice maps once per probe, then resample them at `dirs` (both linear, so
        this equals evaluating every (probe, direction) pair)."""
        node, w_node = lattice_corners(self._lattice_coords(xn, tn), self.lattice_dims)  # [P, C]
        blended = blend_lattice_maps(self.maps, node, w_node)  # [P, h, w, 3]
        h = self.settings.env_height
        if dirs.shape[0] == h * equirect_width(h) and torch.equal(
            dirs, equirect_directions(h, device=dirs.device).reshape(-1, 3)
        ):
            return blended.reshape(xn.shape[0], -1, 3)  # same pixel centres: sampling is the identity
        padded = pad_poles(blended)  # [P, texels, 3]
        out = xn.new_empty(xn.shape[0], dirs.shape[0], 3)
        for dl in direction_blocks(dirs.shape[0], chunk_rows):
            pix, w_pix = equirect_stencil(dirs[dl], h)  # [n, 4]
            for sl in probe_chunks(xn.shape[0], dl.stop - dl.start, chunk_rows):
                out[sl, dl] = (w_pix[None, :, :, None] * padded[sl][:, pix]).sum(2)
        return out
