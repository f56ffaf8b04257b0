"""Input encodings for light fields (pure torch, no custom kernels)."""
from __future__ import annotations

import math
from typing import Literal

import torch
from pydantic import Field
from torch import nn

from core.conventions import direction_to_theta_phi, theta_phi_to_equirect_pixel
from core.envmap import equirect_stencil, pad_poles, pixel_taps, taps_stencil
from core.fields.components.settings import FieldSettings


class EncodingSettings(FieldSettings):
    """Input encodings of the network kinds: PE(x) 6, PE(d) 4 frequencies, and time as PE(t)
    (4 frequencies, the paper's) or as learned time codes (`time_encoding="codes"`).

    Time codes: `time_knots` learned vectors of `time_code_dim` at evenly spaced normalised
    times (the engine sets one knot per frame), linearly interpolated. Unlike PE(t), a code
    changes only where the data asks (the engine adds an L1 total-variation penalty across
    knots), so a static stretch stays flat and a switch stays sharp (docs/engine.md)."""

    x_freqs: int = Field(6, ge=0, le=16)
    t_freqs: int = Field(4, ge=0, le=16)
    d_freqs: int = Field(4, ge=0, le=16)
    time_encoding: Literal["pe", "codes"] = "pe"
    time_knots: int = Field(2, ge=2, le=4096, description="knots of the time codes (the engine sets one per frame)")
    time_code_dim: int = Field(8, ge=1, le=64)


class PositionalEncoding(nn.Module):
    """NeRF positional encoding: [v, sin(2^k pi v), cos(2^k pi v)] for k < n_freqs.

    Inputs are expected in [-1, 1] (normalised coordinates or unit directions), so the
    lowest frequency spans the whole domain once. Output layout per frequency is
    [sin(all dims), cos(all dims)]; `out_dim` tells the width. No parameters, so it adds
    nothing to a state dict.
    """

    def __init__(self, in_dim: int, n_freqs: int, include_input: bool = True):
        super().__init__()
        if in_dim < 1 or n_freqs < 0:
            raise ValueError(f"PositionalEncoding needs in_dim >= 1 and n_freqs >= 0, got {in_dim}, {n_freqs}")
        self.in_dim = in_dim
        self.n_freqs = n_freqs
        self.include_input = include_input
        scales = math.pi * 2.0 ** torch.arange(n_freqs, dtype=torch.float32)
        self.register_buffer("scales", scales, persistent=False)

    @property
    def out_dim(self) -> int:
        return self.in_dim * (2 * self.n_freqs + int(self.include_input))

    def forward(self, v: torch.Tensor) -> torch.Tensor:
        parts = [v] if self.include_input else []
        if self.n_freqs:
            arg = (v[..., None, :] * self.scales.to(v.dtype)[:, None]).flatten(-2)  # [..., F*D]
            parts += [torch.sin(arg), torch.cos(arg)]
        if not parts:
            return v.new_zeros(*v.shape[:-1], 0)
        return torch.cat(parts, dim=-1)


def interpolate_knots(values: torch.Tensor, tn: torch.Tensor) -> torch.Tensor:
    """values [K, C] at K >= 2 evenly spaced normalised times in [-1, 1], read linearly at tn
    [B, 1] (clamped to the range) -> [B, C]."""
    k = values.shape[0]
    pos = (tn.reshape(-1).clamp(-1.0, 1.0) + 1.0) * 0.5 * (k - 1)
    i0 = pos.floor().clamp(max=k - 2)
    frac = (pos - i0)[:, None].to(values.dtype)
    i0 = i0.long()
    return values[i0] * (1.0 - frac) + values[i0 + 1] * frac


class TimeCodes(nn.Module):
    """Learned codes at `knots` evenly spaced normalised times in [-1, 1], linearly
    interpolated: tn [B, 1] -> [B, dim]. Every knot starts at the same vector, so an untrained
    field is constant in time and only the data (against the TV penalty) makes it change."""

    def __init__(self, knots: int, dim: int):
        super().__init__()
        if knots < 2 or dim < 1:
            raise ValueError(f"TimeCodes needs knots >= 2 and dim >= 1, got {knots}, {dim}")
        start = torch.randn(1, dim) * 0.5
        self.codes = nn.Parameter(start.expand(knots, dim).clone())

    @property
    def out_dim(self) -> int:
        return self.codes.shape[1]

    def forward(self, tn: torch.Tensor) -> torch.Tensor:
        return interpolate_knots(self.codes, tn)

    def total_variation(self) -> torch.Tensor:
        """Mean L1 change between neighbouring knots (per knot step and code channel)."""
        return (self.codes[1:] - self.codes[:-1]).abs().mean()


class TimeGain(nn.Module):
    """A log brightness per knot (one value, or one per colour channel) at evenly spaced
    normalised times in [-1, 1], linearly interpolated: tn [B, 1] -> [B, channels]. Starts at 0
    (gain 1), so an untrained gain changes nothing; `set_gain` sets given values."""

    def __init__(self, knots: int, channels: int = 3):
        super().__init__()
        if knots < 2 or channels not in (1, 3):
            raise ValueError(f"TimeGain needs knots >= 2 and 1 or 3 channels, got {knots}, {channels}")
        self.log_gain = nn.Parameter(torch.zeros(knots, channels))

    def set_gain(self, log_gain: torch.Tensor) -> None:
        """log_gain [knots] or [knots, channels] (clamped to +-LOG_GAIN_LIMIT, non-finite -> 0)."""
        with torch.no_grad():
            v = torch.as_tensor(log_gain, dtype=self.log_gain.dtype)
            v = v.reshape(-1, 1).expand_as(self.log_gain) if v.dim() == 1 else v.reshape(self.log_gain.shape)
            self.log_gain.copy_(
                torch.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0).clamp(-LOG_GAIN_LIMIT, LOG_GAIN_LIMIT)
            )

    def forward(self, tn: torch.Tensor) -> torch.Tensor:
        return interpolate_knots(self.log_gain.clamp(-LOG_GAIN_LIMIT, LOG_GAIN_LIMIT), tn)

    def total_variation(self) -> torch.Tensor:
        """Mean L1 change between neighbouring knots (per knot step and channel)."""
        return (self.log_gain[1:] - self.log_gain[:-1]).abs().mean()


LOG_GAIN_LIMIT = 23.0  # 10 decades either way: beyond it a "dimming" is a camera fault, not light


class EquirectGridEncoding(nn.Module):
    """Learnable feature maps over the sphere, one equirect [h, 2h, F] per height, read
    bilinearly with the env maps' own taps (seam wrapped, poles continuous: core.envmap); the
    fields' view detail (core.fields.kinds.base). They start at zero, so an untrained grid adds
    nothing, and a cell changes only where the loss reaches its taps: unlike more PE(d)
    frequencies, nothing of it extends (rings) into directions no loss reached."""

    def __init__(self, heights: tuple[int, ...], features: int):
        super().__init__()
        if not heights or min(heights) < 2 or features < 1:
            raise ValueError(f"EquirectGridEncoding needs heights >= 2 and features >= 1, got {heights}, {features}")
        self.heights = tuple(int(h) for h in heights)
        self.grids = nn.ParameterList([nn.Parameter(torch.zeros(h, 2 * h, features)) for h in self.heights])

    @property
    def out_dim(self) -> int:
        return len(self.heights) * self.grids[0].shape[-1]

    def forward(self, d: torch.Tensor) -> torch.Tensor:
        theta, phi = direction_to_theta_phi(d.reshape(-1, 3).detach())  # the grids learn, directions do not
        out = []
        for h, grid in zip(self.heights, self.grids):
            index, weight = taps_stencil(pixel_taps(*theta_phi_to_equirect_pixel(theta, phi, h), h), h, grid.dtype)
            padded = pad_poles(grid[None])[0]  # [(h + 2) * 2h, F]
            out.append((weight[..., None] * padded[index]).sum(-2))
        return torch.cat(out, dim=-1).reshape(*d.shape[:-1], self.out_dim)


def nerf_encodings(
    settings: EncodingSettings, uses_time: bool
) -> tuple[PositionalEncoding, nn.Module | None, PositionalEncoding]:
    """PE(x), the time encoding (PE(t) or TimeCodes; None for a field without a time input)
    and PE(d) at the settings' frequencies."""
    pe_t: nn.Module | None = None
    if uses_time:
        pe_t = (TimeCodes(settings.time_knots, settings.time_code_dim) if settings.time_encoding == "codes"
                else PositionalEncoding(1, settings.t_freqs))
    return PositionalEncoding(3, settings.x_freqs), pe_t, PositionalEncoding(3, settings.d_freqs)


class DenseGridEncoding(nn.Module):
    """Learnable feature grid over [-1, 1]^D (D = 3 or 4), interpolated (tri/quadri)linearly.

    A cheap, smooth alternative to a hash grid at the resolutions a room's lighting needs
    (lighting varies slowly in space). Inputs outside [-1, 1] are clamped to the border.
    Features start small (uniform +-1e-2) so the MLP on top dominates early training.
    """

    def __init__(self, resolution: tuple[int, ...], features: int):
        super().__init__()
        if len(resolution) not in (3, 4) or min(resolution) < 2:
            raise ValueError(f"DenseGridEncoding resolution must be 3 or 4 sizes >= 2, got {resolution}")
        self.resolution = tuple(int(r) for r in resolution)
        self.features = int(features)
        self.grid = nn.Parameter(torch.empty(*self.resolution, self.features).uniform_(-1e-2, 1e-2))

    @property
    def out_dim(self) -> int:
        return self.features

    def forward(self, v: torch.Tensor) -> torch.Tensor:
        return multilinear_lookup(self.grid, v)


def lattice_corners(v: torch.Tensor, dims: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """Multilinear interpolation stencil on a lattice spanning [-1, 1]^D.

    v [B, D] (clamped to [-1, 1]); lattice node r of axis a sits at -1 + 2 r / (dims[a] - 1),
    so the lattice corners are the domain corners. Returns (flat row-major node index
    [B, 2^D] long, weight [B, 2^D]); weights are >= 0 and sum to 1.
    """
    n_axes = len(dims)
    size = torch.tensor(dims, device=v.device, dtype=v.dtype)
    pos = (v.clamp(-1.0, 1.0) + 1.0) * 0.5 * (size - 1)  # [B, D] in [0, R-1]
    i0 = torch.minimum(pos.floor(), size - 2)  # keep i0 + 1 in range at the upper border
    frac = pos - i0
    i0 = i0.long()
    strides = [1] * n_axes
    for a in range(n_axes - 2, -1, -1):
        strides[a] = strides[a + 1] * dims[a + 1]
    bits = torch.tensor([[(c >> a) & 1 for a in range(n_axes)] for c in range(2**n_axes)], device=v.device)  # [C, D]
    stride = torch.tensor(strides, device=v.device)
    index = ((i0[:, None, :] + bits[None]) * stride).sum(-1)  # [B, C]
    weight = torch.where(bits[None].bool(), frac[:, None, :], 1.0 - frac[:, None, :]).prod(-1)  # [B, C]
    return index, weight


def multilinear_lookup(grid: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Interpolate grid [R0, .., R(D-1), C] at points v [B, D] in [-1, 1] (clamped) -> [B, C]."""
    index, weight = lattice_corners(v, tuple(grid.shape[:-1]))
    flat = grid.reshape(-1, grid.shape[-1])
    return (weight[..., None] * flat[index]).sum(1)


def lattice_maps_lookup(maps: torch.Tensor, node: torch.Tensor, w_node: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Equirect maps [M, h, 2h, C] at lattice nodes, read at a node stencil (node, w_node) [B, K]
    (from `lattice_corners`) along unit directions d [B, 3]: multilinear over the nodes, bilinear
    over d (core.envmap's stencil: seam wrap, pole rows) -> [B, C]. The grid field's and the room
    lattice's per-ray path."""
    pix, w_pix = equirect_stencil(d, maps.shape[1])  # [B, 4]
    padded = pad_poles(maps)  # [M, texels, C]
    flat = padded.reshape(-1, padded.shape[-1])
    index = node[:, :, None] * padded.shape[1] + pix[:, None, :]  # [B, K, 4]
    weight = (w_node[:, :, None] * w_pix[:, None, :]).to(flat.dtype)
    return (weight[..., None] * flat[index]).sum(dim=(1, 2))


def blend_lattice_maps(maps: torch.Tensor, node: torch.Tensor, w_node: torch.Tensor) -> torch.Tensor:
    """The maps [M, h, 2h, C] blended at each probe's node stencil [P, K] -> [P, h, 2h, C]: the
    per-probe path (linear, so resampling the blend equals `lattice_maps_lookup` per direction)."""
    return (w_node[..., None, None, None].to(maps.dtype) * maps[node]).sum(1)
