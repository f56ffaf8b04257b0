"""Camera transfer functions: how a file's code values relate to the light the camera saw.

A capture's frames are decoded from their own transfer (`Transfer`, `params.transfer`,
docs/captures.md "The camera's response") to linear light, then re-encoded in the engine's one
convention (core.conventions.tonemap: x^(1/2.4), clip at 1). The engine never sees a file's
curve, so every stage after loading keeps reading frames one way, and a camera whose curve is
not the convention's is no longer read as light that changes with each exposure (a curve's toe
moves with the exposure; exposure compensation cancels it only when the curve is known).

The curves, each as the standard defines its OETF (scene light -> code; the inverse is applied
on reading, since lighting is about the scene, not a display):
* ``srgb``: IEC 61966-2-1, a linear toe below 0.0031308 and 1.055 x^(1/2.4) - 0.055 above;
* ``rec709``: ITU-R BT.709 (also BT.2020's 10/12-bit SDR curve), 4.5 x below 0.018 and
  1.099 x^0.45 - 0.099 above;
* ``gamma:G``: a pure power, code = x^(1/G) (``gamma:2.4`` is the engine's own convention);
* ``linear``: code = x;
* ``hlg``: ITU-R BT.2100 hybrid log-gamma; scene light in [0, 1], the top of the range is where
  the sensor clips, and highlights up to 12x reference white stay unclipped;
* ``pq``: SMPTE ST 2084 (display light up to 10,000 nits); read so that 1,000 nits (the peak
  that phones master HDR video to) is the clip point, 1.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import torch

from core.conventions import GAMMA

NAMES = ("srgb", "rec709", "linear", "hlg", "pq")  # and "gamma:G"
AUTO = "auto"
MIN_GAMMA, MAX_GAMMA = 1.0, 4.0
_GAMMA_RE = re.compile(r"^gamma:(\d+(?:\.\d+)?)$")

# BT.2100 HLG constants
_HLG_A = 0.17883277
_HLG_B = 1.0 - 4.0 * _HLG_A
_HLG_C = 0.5 - _HLG_A * math.log(4.0 * _HLG_A)
# ST 2084 PQ constants
_PQ_M1 = 2610.0 / 16384.0
_PQ_M2 = 2523.0 / 4096.0 * 128.0
_PQ_C1 = 3424.0 / 4096.0
_PQ_C2 = 2413.0 / 4096.0 * 32.0
_PQ_C3 = 2392.0 / 4096.0 * 32.0
PQ_WHITE_NITS = 1000.0  # PQ is read with this many nits at 1 (the engine's clip point)


@dataclass(frozen=True)
class Transfer:
    """One camera transfer: `name` in NAMES or "gamma" (then `gamma` is G)."""

    name: str
    gamma: float | None = None

    def __str__(self) -> str:
        return f"gamma:{self.gamma:g}" if self.name == "gamma" else self.name

    @property
    def is_hdr(self) -> bool:
        return self.name in ("hlg", "pq")

    @property
    def is_convention(self) -> bool:
        """True when the code values are already the engine's (gamma GAMMA): nothing to convert."""
        return self.name == "gamma" and abs(float(self.gamma) - GAMMA) < 1e-9

    def to_linear(self, code: torch.Tensor) -> torch.Tensor:
        """Code values in [0, 1] -> linear light (1 = the clip point; PQ may exceed 1)."""
        v = code.clamp(0.0, 1.0)
        if self.name == "linear":
            return v
        if self.name == "gamma":
            return v.pow(float(self.gamma))
        if self.name == "srgb":
            return torch.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055).pow(2.4))
        if self.name == "rec709":
            return torch.where(v < 0.081, v / 4.5, ((v + 0.099) / 1.099).pow(1.0 / 0.45))
        if self.name == "hlg":
            high = (torch.exp((v - _HLG_C) / _HLG_A) + _HLG_B) / 12.0
            return torch.where(v <= 0.5, v * v / 3.0, high)
        if self.name == "pq":
            p = v.pow(1.0 / _PQ_M2)
            y = ((p - _PQ_C1).clamp_min(0.0) / (_PQ_C2 - _PQ_C3 * p)).pow(1.0 / _PQ_M1)
            return y * (10000.0 / PQ_WHITE_NITS)
        raise ValueError(f"unknown transfer {self}")

    def from_linear(self, linear: torch.Tensor) -> torch.Tensor:
        """Linear light -> code values in [0, 1] (the camera's side: what a file holds)."""
        x = torch.nan_to_num(linear, nan=0.0, posinf=1e30).clamp_min(0.0)
        if self.name == "pq":
            y = (x * (PQ_WHITE_NITS / 10000.0)).clamp(0.0, 1.0).pow(_PQ_M1)
            return ((_PQ_C1 + _PQ_C2 * y) / (1.0 + _PQ_C3 * y)).pow(_PQ_M2)
        x = x.clamp(0.0, 1.0)
        if self.name == "linear":
            return x
        if self.name == "gamma":
            return x.pow(1.0 / float(self.gamma))
        if self.name == "srgb":
            return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.pow(1.0 / 2.4) - 0.055)
        if self.name == "rec709":
            return torch.where(x < 0.018, 4.5 * x, 1.099 * x.pow(0.45) - 0.099)
        if self.name == "hlg":
            high = _HLG_A * torch.log((12.0 * x - _HLG_B).clamp_min(1e-12)) + _HLG_C
            return torch.where(x <= 1.0 / 12.0, torch.sqrt(3.0 * x), high).clamp(0.0, 1.0)
        raise ValueError(f"unknown transfer {self}")

    def to_convention(self, code: torch.Tensor) -> torch.Tensor:
        """Code values -> the engine's LDR convention, clip((linear)^(1/GAMMA), 0, 1)."""
        if self.is_convention:
            return code.clamp(0.0, 1.0)
        return self.to_linear(code.float()).clamp(0.0, 1.0).pow(1.0 / GAMMA)


CONVENTION = Transfer("gamma", GAMMA)
SRGB = Transfer("srgb")


def parse_transfer(text: str) -> Transfer:
    """'srgb' | 'rec709' | 'linear' | 'hlg' | 'pq' | 'gamma:G' (1 <= G <= 4) -> Transfer;
    ValueError naming the accepted forms otherwise ('auto' is the caller's to resolve)."""
    s = str(text).strip().lower()
    if s in NAMES:
        return Transfer(s)
    m = _GAMMA_RE.match(s)
    if m:
        g = float(m.group(1))
        if not (MIN_GAMMA <= g <= MAX_GAMMA):
            raise ValueError(f"transfer gamma must be in [{MIN_GAMMA:g}, {MAX_GAMMA:g}], got {g:g}")
        return Transfer("gamma", g)
    raise ValueError(f"transfer must be 'auto', one of {', '.join(NAMES)}, or 'gamma:G', got {text!r}")


# H.273 / ISO/IEC 23091-2 transfer characteristics (what H.264/HEVC VUI and PNG cICP carry)
H273_TRANSFERS = {
    1: "rec709", 6: "rec709", 14: "rec709", 15: "rec709",  # BT.709, BT.601, BT.2020 10/12-bit
    4: "gamma:2.2", 5: "gamma:2.8", 8: "linear", 13: "srgb", 16: "pq", 18: "hlg",
}


def transfer_from_h273(code: int | None) -> Transfer | None:
    """The transfer an H.273 `transfer_characteristics` code names, or None (unspecified,
    reserved, or a curve this product does not read)."""
    name = H273_TRANSFERS.get(int(code)) if code is not None else None
    return parse_transfer(name) if name else None
