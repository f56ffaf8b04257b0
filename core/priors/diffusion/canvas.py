"""Where a frame lands in the model's input ("canvas"), per inference profile.

* `keep_aspect` (paper): the card's pixel count with the frame's aspect ratio, sides
  rounded to the UNet/VAE multiple (conditioning.model_size); balls stay round.
* `squash` (seed): exactly the card's resolution, aspect ratio ignored (the authors'
  `image_processor.preprocess(..., height=512, width=512)`).
* `letterbox` (diffusionlight): the frame scaled to fit the card's square and centred on
  black (DiffusionLight's `pil_square_image`, its `force_square` default).

`to_model` maps [B, C, h, w] frame-space tensors onto the canvas, `to_frame` maps model
outputs back (crop the frame's box, resize).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F

from core.priors.diffusion.conditioning import binary_mask_at, model_size, resize

CanvasKind = Literal["keep_aspect", "squash", "letterbox"]


@dataclass(frozen=True)
class Canvas:
    frame: tuple[int, int]  # [h, w] of the frame
    size: tuple[int, int]  # [H, W] of the model input
    box: tuple[int, int, int, int]  # top, left, height, width of the frame inside the canvas

    @property
    def full(self) -> bool:
        return self.box == (0, 0, *self.size)

    def _pad(self, x: torch.Tensor, fill: float) -> torch.Tensor:
        if self.full:
            return x
        top, left, bh, bw = self.box
        return F.pad(x, (left, self.size[1] - left - bw, top, self.size[0] - top - bh), value=fill)

    def to_model(self, x: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
        """[B, C, h, w] -> [B, C, H, W] (bilinear, antialiased when shrinking; `fill` outside the box)."""
        return self._pad(resize(x, self.box[2:]), fill)

    def mask_to_model(self, coverage: torch.Tensor) -> torch.Tensor:
        """[..., h, w] coverage -> [..., H, W] binary: 1 where any covered pixel falls in the cell."""
        lead = coverage.shape[:-2]
        m = binary_mask_at(coverage, self.box[2:]).reshape(-1, 1, *self.box[2:])
        return self._pad(m, 0.0).reshape(*lead, *self.size)

    def to_frame(self, y: torch.Tensor) -> torch.Tensor:
        """[B, C, H, W] model output -> [B, C, h, w]."""
        top, left, bh, bw = self.box
        return resize(y[..., top : top + bh, left : left + bw], self.frame)


def make_canvas(kind: CanvasKind, frame: tuple[int, int], resolution: tuple[int, int], multiple: int) -> Canvas:
    h, w = int(frame[0]), int(frame[1])
    if kind == "keep_aspect":
        size = model_size(h, w, resolution, multiple)
        return Canvas((h, w), size, (0, 0, *size))
    size = (int(resolution[0]), int(resolution[1]))
    if kind == "squash":
        return Canvas((h, w), size, (0, 0, *size))
    if kind == "letterbox":
        scale = min(size[0] / h, size[1] / w)
        bh, bw = max(1, min(size[0], int(h * scale))), max(1, min(size[1], int(w * scale)))
        return Canvas((h, w), size, ((size[0] - bh) // 2, (size[1] - bw) // 2, bh, bw))
    raise ValueError(f"unknown canvas kind {kind!r}")
