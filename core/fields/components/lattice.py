"""Room lattice: a coarse lattice of learnable low-resolution log-radiance maps added to every
field kind's output, so the slowly varying part of the lighting (which wall is warm, which side
is bright) is fitted directly instead of through the network's slow convergence.

`resolution` = (nx, ny, nz) maps of `height` x 2 `height` texels at the nodes of a regular
lattice over the normalised box [-1, 1]^3; the residual at (xn, d) is trilinear over the nodes
and bilinear over d (core.envmap's stencil: seam wrap, pole rows), like the grid field's maps.
Every map starts at zero, so an untrained lattice changes nothing, and a texel moves only where
the loss reaches its taps: the lattice cannot ring. It has no time input: the network's time
codes carry what changes, and for a field with a time input the engine trains the lattice only
in the second half of the steps, once the codes have learnt the changes
(core.engine.distill.lattice_start_step).
"""
from __future__ import annotations

import math

import torch
from torch import nn

from core.conventions import equirect_width
from core.envmap import equirect_stencil, pad_poles
from core.fields.components.encodings import blend_lattice_maps, lattice_corners, lattice_maps_lookup


class RoomLattice(nn.Module):
    def __init__(self, resolution: tuple[int, int, int], height: int):
        super().__init__()
        self.dims = tuple(int(r) for r in resolution)
        self.height = int(height)
        self.maps = nn.Parameter(torch.zeros(math.prod(self.dims), self.height, equirect_width(self.height), 3))

    def forward(self, xn: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Residual logits [B, 3] at normalised positions xn [B, 3] along unit directions d [B, 3]."""
        node, w_node = lattice_corners(xn, self.dims)  # [B, 8]
        return lattice_maps_lookup(self.maps, node, w_node, d)

    def blended(self, xn: torch.Tensor) -> torch.Tensor:
        """The lattice's map at each normalised position [P, 3], padded for `sample`: [P, texels, 3]."""
        node, w_node = lattice_corners(xn, self.dims)
        return pad_poles(blend_lattice_maps(self.maps, node, w_node))

    def rows(self, blended: torch.Tensor, index: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Row b of blended [P, texels, 3] (probe index[b]) along unit d[b] -> [B, 3]: the training
        path, where thousands of rows share a dozen probes (cheaper than `forward`'s 32 taps a row)."""
        pix, w_pix = equirect_stencil(d, self.height)  # [B, 4]
        return (w_pix[..., None].to(blended.dtype) * blended[index[:, None], pix]).sum(1)

    def sample(self, blended: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """blended [P, texels, 3] (from `blended`) along unit directions d [N, 3] -> [P, N, 3]."""
        pix, w_pix = equirect_stencil(d, self.height)
        return (w_pix[None, :, :, None].to(blended.dtype) * blended[:, pix]).sum(2)
