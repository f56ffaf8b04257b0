"""The paper's light-field MLP (Tong et al. 2025, §3.2).

Input encoding e = [PE(xn) (6 freqs), PE(tn) (4, only when the field uses time), PE(d) (4)];
`layers` ReLU layers of `width`; layer `skip_layer` (1-based) sees [h, e] as in NeRF, so the
deep layers keep direct access to the high-frequency encodings; a linear head gives the
3 log-radiance logits.
"""
from __future__ import annotations

import torch
from torch import nn

from core.fields.base import LightField
from core.fields.config import FieldConfig
from core.fields.encodings import PositionalEncoding
from core.fields.normalization import SceneBounds

# The untrained field starts near this radiance everywhere (small output weights), so the
# first renders are a plain grey room rather than random 12-decade noise.
INITIAL_RADIANCE = 1.0
OUTPUT_WEIGHT_SCALE = 0.1


class MLPField(LightField):
    def __init__(self, config: FieldConfig, bounds: SceneBounds):
        super().__init__(config, bounds)
        s = config.mlp
        self.pe_x = PositionalEncoding(3, s.x_freqs)
        self.pe_t = PositionalEncoding(1, s.t_freqs) if config.uses_time else None
        self.pe_d = PositionalEncoding(3, s.d_freqs)
        enc_dim = self.pe_x.out_dim + (self.pe_t.out_dim if self.pe_t else 0) + self.pe_d.out_dim
        self.skip_layer = s.skip_layer
        layers = []
        for i in range(1, s.layers + 1):
            fan_in = enc_dim if i == 1 else s.width
            if i == s.skip_layer and i != 1:
                fan_in += enc_dim
            layers.append(nn.Linear(fan_in, s.width))
        self.layers = nn.ModuleList(layers)
        self.output = nn.Linear(s.width, 3)
        with torch.no_grad():
            self.output.weight.mul_(OUTPUT_WEIGHT_SCALE)
            self.output.bias.fill_(self.logit_for_radiance(INITIAL_RADIANCE))

    def encode(self, xn: torch.Tensor, tn: torch.Tensor | None, d: torch.Tensor) -> torch.Tensor:
        parts = [self.pe_x(xn)]
        if self.pe_t is not None:
            parts.append(self.pe_t(tn))
        parts.append(self.pe_d(d))
        return torch.cat(parts, dim=-1)

    def logits(self, xn, tn, d):
        e = self.encode(xn, tn, d)
        h = e
        for i, layer in enumerate(self.layers, start=1):
            if i == self.skip_layer and i != 1:
                h = torch.cat((h, e), dim=-1)
            h = torch.relu(layer(h))
        return self.output(h)
