"""The paper's light-field MLP (Tong et al. 2025, §3.2).

Input encoding e = [PE(xn) (6 freqs), PE(tn) (4, only when the field uses time), PE(d) (4)];
`layers` ReLU layers of `width`; layer `skip_layer` (1-based) sees [h, e] as in NeRF, so the
deep layers keep direct access to the high-frequency encodings; a linear head gives the
3 log-radiance logits.
"""
from __future__ import annotations

import torch
from pydantic import Field, model_validator
from torch import nn

from core.fields.components.encodings import EncodingSettings, nerf_encodings
from core.fields.components.normalization import SceneBounds
from core.fields.kinds.base import LightField, direction_blocks, probe_chunks
from core.fields.kinds.config import FieldConfig
from core.fields.kinds.registry import register_field


class MLPSettings(EncodingSettings):
    """The paper's MLP: PE(x) 6 freqs, PE(t) 4, PE(d) 4; 6 x 256 ReLU, skip into layer 3."""

    width: int = Field(256, ge=1)
    layers: int = Field(6, ge=1)
    skip_layer: int | None = Field(3, ge=1, description="1-based hidden layer that also receives the input encoding")

    @model_validator(mode="after")
    def _skip_in_range(self):
        if self.skip_layer is not None and self.skip_layer > self.layers:
            raise ValueError(f"mlp.skip_layer={self.skip_layer} exceeds mlp.layers={self.layers}")
        return self


@register_field("mlp")
class MLPField(LightField):
    Config = MLPSettings

    def __init__(self, config: FieldConfig, bounds: SceneBounds):
        super().__init__(config, bounds)
        s = self.settings
        self.pe_x, self.pe_t, self.pe_d = nerf_encodings(s, config.uses_time)
        enc_dim = self.pe_x.out_dim + (self.pe_t.out_dim if self.pe_t else 0) + self.pe_d.out_dim
        self.encoding_dim = enc_dim
        self.skip_layer = s.skip_layer
        layers = []
        for i in range(1, s.layers + 1):
            fan_in = enc_dim if i == 1 else s.width
            if i == s.skip_layer and i != 1:
                fan_in += enc_dim
            layers.append(nn.Linear(fan_in, s.width))
        self.layers = nn.ModuleList(layers)
        self.output = nn.Linear(s.width, 3)
        self._start_near_initial_radiance(self.output)

    def encode(self, xn: torch.Tensor, tn: torch.Tensor | None, d: torch.Tensor) -> torch.Tensor:
        """[PE(xn), PE(tn), PE(d)]: probe part first, direction part last (see _envmap_logits)."""
        return torch.cat((self._probe_encoding(xn, tn), self.pe_d(d)), dim=-1)

    def _probe_encoding(self, xn: torch.Tensor, tn: torch.Tensor | None) -> torch.Tensor:
        return self.pe_x(xn) if self.pe_t is None else torch.cat((self.pe_x(xn), self.pe_t(tn)), dim=-1)

    def logits(self, xn, tn, d):
        e = self.encode(xn, tn, d)
        h = e
        for i, layer in enumerate(self.layers, start=1):
            if i == self.skip_layer and i != 1:
                h = torch.cat((h, e), dim=-1)
            h = torch.relu(layer(h))
        return self.output(h)

    def _split_encoding_layers(self, e_probe: torch.Tensor, e_dir: torch.Tensor) -> dict:
        """Every layer that reads the encoding is linear in it, so its pre-activation splits
        into a per-probe term (PE(x), PE(t) columns, + bias) and a per-direction term (PE(d)
        columns). Returns {layer number: (probe term [P, W], direction term [N, W])}."""
        n_probe_cols, n_dir_cols = e_probe.shape[1], e_dir.shape[1]
        terms = {}
        for i, layer in enumerate(self.layers, start=1):
            if i == 1 or i == self.skip_layer:
                w = layer.weight[:, layer.in_features - n_probe_cols - n_dir_cols :]
                terms[i] = (e_probe @ w[:, :n_probe_cols].T + layer.bias, e_dir @ w[:, n_probe_cols:].T)
        return terms

    def _layers_from_terms(self, encoded) -> torch.Tensor:
        """The network, given `encoded(i)` = layer i's pre-activation contribution of the encoding."""
        h = torch.relu(encoded(1))
        for i, layer in enumerate(self.layers[1:], start=2):
            if i == self.skip_layer:
                w_h = layer.weight[:, : layer.in_features - self.encoding_dim]
                h = torch.relu(h @ w_h.T + encoded(i))
            else:
                h = torch.relu(layer(h))
        return self.output(h)

    def _probe_logits(self, xn, tn, index, d) -> torch.Tensor:
        terms = self._split_encoding_layers(self._probe_encoding(xn, tn), self.pe_d(d))
        return self._layers_from_terms(lambda i: terms[i][0][index] + terms[i][1])

    def _envmap_logits(self, xn, tn, dirs, chunk_rows: int) -> torch.Tensor:
        e_probe = self._probe_encoding(xn, tn)
        out = xn.new_empty(xn.shape[0], dirs.shape[0], 3)
        for dl in direction_blocks(dirs.shape[0], chunk_rows):
            terms = self._split_encoding_layers(e_probe, self.pe_d(dirs[dl]))
            for sl in probe_chunks(xn.shape[0], dl.stop - dl.start, chunk_rows):
                out[sl, dl] = self._layers_from_terms(lambda i: terms[i][0][sl, None] + terms[i][1][None])
        return out
