"""Room lattice: a coarse lattice of learnable low-resolution log-radiance maps added to every
field kind's output, so the slowly varying part of the lighting (which wall is warm, which side
is bright) is fitted directly instead of through the network's slow convergence.

`resolution` = (nx, ny, nz) maps of `height` x 2 `height` texels at the nodes of a regular
lattice over the normalised box [-1, 1]^3; the residual at (xn, d) is trilinear over the nodes
and bilinear over d (core.envmap's stencil: seam wrap, pole rows), like the grid field's maps.
Every map starts at zero, so an untrained lattice changes nothing, and a texel moves only where
the loss reaches its taps: the lattice cannot ring. It has no time input: the network's time
codes carry what changes. With `chroma_only` its residual has zero mean over the colour channels
(each texel's mean is removed before use), so it moves a direction's colour and leaves its
brightness (the geometric mean of the channels) alone up to the output sigmoid's curvature: the
setting for a field with a time input, where a static brightness term would hold the average of
a light that switches.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from core.conventions import equirect_width
from core.envmap import equirect_stencil, pad_poles
from core.fields.encodings import lattice_corners


class RoomLattice(nn.Module):
    def __init__(self, resolution: tuple[int, int, int], height: int, chroma_only: bool = False):
        super().__init__()
        self.dims = tuple(int(r) for r in resolution)
        self.height = int(height)
        self.chroma_only = bool(chroma_only)
        self.maps = nn.Parameter(torch.zeros(math.prod(self.dims), self.height, equirect_width(self.height), 3))

    def residual_maps(self) -> torch.Tensor:
        """The maps as added to the logits: `maps`, less each texel's channel mean if chroma_only."""
        return self.maps - self.maps.mean(-1, keepdim=True) if self.chroma_only else self.maps

    def forward(self, xn: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Residual logits [B, 3] at normalised positions xn [B, 3] along unit directions d [B, 3]."""
        node, w_node = lattice_corners(xn, self.dims)  # [B, 8]
        pix, w_pix = equirect_stencil(d, self.height)  # [B, 4]
        padded = pad_poles(self.residual_maps())  # [M, texels, 3]
        flat = padded.reshape(-1, 3)
        index = node[:, :, None] * padded.shape[1] + pix[:, None, :]  # [B, 8, 4]
        weight = (w_node[:, :, None] * w_pix[:, None, :]).to(flat.dtype)
        return (weight[..., None] * flat[index]).sum(dim=(1, 2))

    def blended(self, xn: torch.Tensor) -> torch.Tensor:
        """The lattice's map at each normalised position [P, 3], padded for `sample`: [P, texels, 3]."""
        node, w_node = lattice_corners(xn, self.dims)
        maps = self.residual_maps()
        return pad_poles((w_node[..., None, None, None].to(maps.dtype) * maps[node]).sum(1))

    def rows(self, blended: torch.Tensor, index: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Row b of blended [P, texels, 3] (probe index[b]) along unit d[b] -> [B, 3]: the training
        path, where thousands of rows share a dozen probes (cheaper than `forward`'s 32 taps a row)."""
        pix, w_pix = equirect_stencil(d, self.height)  # [B, 4]
        return (w_pix[..., None].to(blended.dtype) * blended[index[:, None], pix]).sum(1)

    def sample(self, blended: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """blended [P, texels, 3] (from `blended`) along unit directions d [N, 3] -> [P, N, 3]."""
        pix, w_pix = equirect_stencil(d, self.height)
        return (w_pix[None, :, :, None].to(blended.dtype) * blended[:, pix]).sum(2)
