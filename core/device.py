"""Which torch device work runs on: one rule for the engine and every prior.

LIGHTFIELD_DEVICE (a deployment setting) overrides the caller's setting; 'auto' means CUDA
when torch sees a GPU, else CPU; an explicit CUDA device without one is an error (a GPU job
silently running for hours on CPU is worse than failing).
"""
from __future__ import annotations

import os
import re

import torch

DEVICE_ENV = "LIGHTFIELD_DEVICE"
DEVICE_PATTERN = r"^(auto|cpu|cuda(:\d+)?)$"


class DeviceError(ValueError):
    """The requested torch device is malformed or not available; the message names the setting."""


def resolve_device(setting: str = "auto", environ: dict[str, str] | None = None,
                   source: str = "DistillConfig.device") -> torch.device:
    """LIGHTFIELD_DEVICE if set, else `setting` ('auto', 'cpu', 'cuda', 'cuda:N');
    `source` names the setting in error messages."""
    env = os.environ if environ is None else environ
    raw = (env.get(DEVICE_ENV) or "").strip()
    source, value = (DEVICE_ENV, raw) if raw else (source, str(setting))
    if not re.match(DEVICE_PATTERN, value):
        raise DeviceError(f"{source}={value!r}: expected 'auto', 'cpu', 'cuda' or 'cuda:N'")
    if value == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(value)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise DeviceError(f"{source}={value!r} but CUDA is not available (use 'auto' or 'cpu')")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise DeviceError(f"{source}={value!r} but only {torch.cuda.device_count()} CUDA device(s) exist")
    return device
