"""A faster field: a position/time trunk and a light-direction head.

trunk(PE(xn), PE(tn)[, dense grid features at xn]) -> feature f (per probe); head(f, PE(d)) -> 3 logits (per direction).
An env map needs the trunk ONCE per probe, and the head's first layer is split as
W [f, PE(d)] = W_f f + W_d PE(d), so per direction only the (small) head runs on a sum of a
per-probe and a per-direction term. The head is narrow (64 by default) because lighting
is mostly a function of direction with a slowly varying spatial modulation.
"""
from __future__ import annotations

import torch
from pydantic import Field, model_validator
from torch import nn

from core.fields.components.encodings import DenseGridEncoding, EncodingSettings, nerf_encodings
from core.fields.components.normalization import SceneBounds
from core.fields.kinds.base import LightField, direction_blocks, probe_chunks
from core.fields.kinds.config import FieldConfig
from core.fields.kinds.registry import register_field


class TrunkSettings(EncodingSettings):
    """Faster field: trunk over (x, t) -> feature; head over (feature, PE(d)) -> radiance."""

    trunk_width: int = Field(128, ge=1)
    trunk_layers: int = Field(3, ge=1)
    feature_dim: int = Field(64, ge=1)
    head_width: int = Field(64, ge=1)
    head_layers: int = Field(2, ge=1)
    # Optional learnable dense feature grid over the box, concatenated to PE(x): local
    # capacity near lights without widening the trunk. None = PE only.
    x_grid: tuple[int, int, int] | None = None
    x_grid_features: int = Field(8, ge=1, le=64)

    @model_validator(mode="after")
    def _grid_positive(self):
        if self.x_grid is not None and min(self.x_grid) < 2:
            raise ValueError(f"trunk.x_grid must be >= 2 per axis, got {self.x_grid}")
        return self


@register_field("trunk")
class TrunkField(LightField):
    Config = TrunkSettings

    def __init__(self, config: FieldConfig, bounds: SceneBounds):
        super().__init__(config, bounds)
        s = self.settings
        self.pe_x, self.pe_t, self.pe_d = nerf_encodings(s, config.uses_time)
        self.x_grid = DenseGridEncoding(s.x_grid, s.x_grid_features) if s.x_grid is not None else None
        trunk_in = self.pe_x.out_dim + (self.pe_t.out_dim if self.pe_t else 0)
        trunk_in += self.x_grid.out_dim if self.x_grid is not None else 0
        self.trunk = _relu_mlp(trunk_in, s.trunk_width, s.trunk_layers, s.feature_dim)
        self.head_in = nn.Linear(s.feature_dim + self.pe_d.out_dim, s.head_width)
        self.head = _relu_mlp(s.head_width, s.head_width, s.head_layers - 1, 3, relu_input=True)
        self._start_near_initial_radiance(self.head[-1])

    def features(self, xn: torch.Tensor, tn: torch.Tensor | None) -> torch.Tensor:
        parts = [self.pe_x(xn)] + ([self.pe_t(tn)] if self.pe_t is not None else [])
        if self.x_grid is not None:
            parts.append(self.x_grid(xn))
        return self.trunk(torch.cat(parts, dim=-1))

    def logits(self, xn, tn, d):
        return self.head(self.head_in(torch.cat((self.features(xn, tn), self.pe_d(d)), dim=-1)))

    def _split_head_input(self, xn, tn, d) -> tuple[torch.Tensor, torch.Tensor]:
        """head_in(f, PE(d)) = (W_f f + b) [P, head_width] + W_d PE(d) [N, head_width]."""
        f_dim = self.settings.feature_dim
        w, b = self.head_in.weight, self.head_in.bias
        return self.features(xn, tn) @ w[:, :f_dim].T + b, self.pe_d(d) @ w[:, f_dim:].T

    def _probe_logits(self, xn, tn, index, d) -> torch.Tensor:
        per_probe, per_row = self._split_head_input(xn, tn, d)
        return self.head(per_probe[index] + per_row)

    def _envmap_logits(self, xn, tn, dirs, chunk_rows: int) -> torch.Tensor:
        out = xn.new_empty(xn.shape[0], dirs.shape[0], 3)
        for dl in direction_blocks(dirs.shape[0], chunk_rows):
            per_probe, per_dir = self._split_head_input(xn, tn, dirs[dl])  # the probe part is cheap to redo
            for sl in probe_chunks(xn.shape[0], dl.stop - dl.start, chunk_rows):
                out[sl, dl] = self.head(per_probe[sl, None] + per_dir[None])
        return out


def _relu_mlp(n_in: int, width: int, hidden: int, n_out: int, relu_input: bool = False) -> nn.Sequential:
    """[ReLU] -> hidden x (Linear, ReLU) -> Linear. With hidden = 0 it is ([ReLU,] Linear)."""
    mods: list[nn.Module] = [nn.ReLU()] if relu_input else []
    fan_in = n_in
    for _ in range(hidden):
        mods += [nn.Linear(fan_in, width), nn.ReLU()]
        fan_in = width
    mods.append(nn.Linear(fan_in, n_out))
    return nn.Sequential(*mods)
