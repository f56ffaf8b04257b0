"""Warm start: a new field begins where an earlier field of the same room ended (a live
session's next version, core.engine.distill's `init_state`).

The two fields need not have the same shapes: a session's field gains a time knot per frame
(one learned code per frame, core.engine.distill.time_knots) and view anchors as the camera
moves. A parameter of the same name and shape is copied; one whose shape differs along a
single axis (the knots) is resampled linearly along it, so the curve learned over the old
frames is stretched over the new ones' span instead of being thrown away; anything else
keeps its fresh initialisation.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F


@dataclass
class WarmStart:
    copied: list[str] = field(default_factory=list)
    resampled: list[str] = field(default_factory=list)
    fresh: list[str] = field(default_factory=list)

    def describe(self) -> dict:
        return {"copied": len(self.copied), "resampled": len(self.resampled), "fresh": self.fresh[:20]}


def resample_axis(value: torch.Tensor, axis: int, size: int) -> torch.Tensor:
    """`value` linearly resampled to `size` samples along `axis` (end points kept)."""
    moved = value.movedim(axis, -1)
    shape = moved.shape
    flat = moved.reshape(1, -1, shape[-1]).double()
    if shape[-1] == 1:
        out = flat.expand(1, flat.shape[1], size)
    else:
        out = F.interpolate(flat, size=size, mode="linear", align_corners=True)
    return out.reshape(*shape[:-1], size).movedim(-1, axis).to(value.dtype)


def warm_start(module: torch.nn.Module, state: dict[str, torch.Tensor]) -> WarmStart:
    """Copy `state` (an earlier field's state_dict) into `module`'s parameters where they fit
    (see the module docstring); buffers (bounds, anchors, sources) stay the new capture's."""
    report = WarmStart()
    with torch.no_grad():
        for name, param in module.named_parameters():
            old = state.get(name)
            if old is None or old.ndim != param.ndim:
                report.fresh.append(name)
                continue
            if old.shape == param.shape:
                param.copy_(old.to(param.dtype))
                report.copied.append(name)
                continue
            differ = [i for i, (a, b) in enumerate(zip(old.shape, param.shape)) if a != b]
            if len(differ) == 1:
                param.copy_(resample_axis(old, differ[0], param.shape[differ[0]]).to(param.dtype))
                report.resampled.append(name)
            else:
                report.fresh.append(name)
    return report
