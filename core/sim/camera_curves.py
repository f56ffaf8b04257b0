"""Camera curves: how a simulated camera turns the light it was exposed to into file codes, and
what its file says about it (issue 60: no privileged curve in the benches).

Every synthetic capture (the simulator's capture directories, panorama rooms, room scans, the
benches' photos and clips) is encoded through one of these curves, and written declaring what
a real file of that camera declares. The engine's own convention (core.conventions.tonemap,
x^(1/2.4)) is kept only as a labelled reference row: it is the curve the product used to
assume, not one a camera writes.

Curves (`CURVES`), each mapping exposed linear light x = 2^ev L (1 = where the camera clips,
except HLG's headroom) to codes in [0, 1] quantised to its bit depth:

| name | curve | bits | a PNG still declares | a video declares |
|---|---|---|---|---|
| `srgb` | IEC 61966-2-1 OETF | 8 | srgb | srgb |
| `rec709` | ITU-R BT.709 OETF | 8 | nothing | rec709 |
| `filmic` | a phone's S-curve (`filmic_tone`) then the sRGB OETF | 8 | srgb (the tone curve is not stated) | srgb |
| `hlg10` | BT.2100 HLG, reference white (x = 1) at 75 % signal | 10 | (video only: a still takes srgb) | hlg |
| `gamma2.4` | x^(1/2.4): the reference row | 8 | gamma:2.4 | nothing (no H.273 code: `job_params`) |

A bench DRAWS a curve per capture from the realistic set (`draw`, seeded by the capture's
name: the same capture gets the same curve on every run and machine), or is forced to one
(`--curve NAME`), or runs every realistic curve and the reference (`--curve all`,
`run_choices`). The scoring side linearises a capture with the curve it was encoded with
(`CameraCurve.decode`: its exact inverse, tone curve included), never with the convention's
inverse: a constant map of the mean colour would otherwise be biased by the curve.
"""
from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass
from typing import Literal

import torch

from core.transfer import Transfer, parse_transfer

Medium = Literal["still", "video"]
STILL: Medium = "still"
VIDEO: Medium = "video"

REALISTIC = ("srgb", "rec709", "filmic", "hlg10")
REFERENCE = "gamma2.4"
NAMES = (*REALISTIC, REFERENCE)
DRAWN, ALL = "drawn", "all"
CHOICES = (DRAWN, ALL, *NAMES)  # what `--curve` takes
REFERENCE_LABEL = "reference: the curve the product used to assume"
STILL_FALLBACK = "srgb"  # a video-only curve forced on a still

# The filmic tone curve: Narkowicz's fit of the ACES film curve, f(x) = x (A x + B) / (x (C x + D) + E),
# scaled so that FILMIC_WHITE (the camera's clip point) maps to 1: a toe (slope 0.27 at 0), mid-grey
# 0.18 lifted to 0.33 (sRGB code 0.61, as phones brighten), a shoulder (slope 0.26 at white).
_FA, _FB, _FC, _FD, _FE = 2.51, 0.03, 2.43, 0.59, 0.14
FILMIC_WHITE = 1.0
# HLG: exposed x = 1 (what the SDR curves put at white) is BT.2408's reference white, 75 % signal:
# scene light 0.2647 of the HLG range, so highlights up to 1 / 0.2647 = 3.8x stay unclipped.
HLG_REFERENCE_WHITE = (math.exp((0.75 - 0.55991073) / 0.17883277) + 0.28466892) / 12.0


def _filmic_raw(x: torch.Tensor) -> torch.Tensor:
    return x * (_FA * x + _FB) / (x * (_FC * x + _FD) + _FE)


_FILMIC_NORM = float(_filmic_raw(torch.tensor(FILMIC_WHITE, dtype=torch.float64)))


def filmic_tone(x: torch.Tensor) -> torch.Tensor:
    """The filmic tone curve in linear light: [0, FILMIC_WHITE] -> [0, 1], monotone, clipped above."""
    x = x.clamp(0.0, FILMIC_WHITE)
    return (_filmic_raw(x) / _FILMIC_NORM).clamp(0.0, 1.0)


def filmic_tone_inverse(y: torch.Tensor) -> torch.Tensor:
    """The inverse of `filmic_tone` on [0, 1] (the positive root of its quadratic)."""
    c = y.clamp(0.0, 1.0).double() * _FILMIC_NORM
    a, b, k = _FA - _FC * c, _FB - _FD * c, _FE * c
    x = (-b + torch.sqrt(b * b + 4.0 * a * k)) / (2.0 * a)
    return x.clamp(0.0, FILMIC_WHITE).to(y.dtype if y.is_floating_point() else torch.float32)


@dataclass(frozen=True)
class CameraCurve:
    """One camera: its curve (`tone` then the `oetf` transfer, after `scale`), bit depth, and
    what its files declare (a core.transfer name, or None: nothing)."""

    name: str
    oetf: str  # the standard transfer the codes are in (core.transfer form)
    bit_depth: int
    still_declares: str | None
    video_declares: str | None
    tone: str | None = None  # "filmic": a tone curve in linear light before the OETF (not declared)
    scale: float = 1.0  # exposed x -> the transfer's scene light (HLG: reference white below the clip)
    video_only: bool = False
    reference: bool = False
    description: str = ""

    @property
    def transfer(self) -> Transfer:
        return parse_transfer(self.oetf)

    @property
    def levels(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def label(self) -> str:
        """The name as reports print it (the reference row says it is one)."""
        return f"{self.name} ({REFERENCE_LABEL})" if self.reference else self.name

    @property
    def clip(self) -> float:
        """The exposed linear value where the codes reach 1."""
        return (FILMIC_WHITE if self.tone == "filmic" else 1.0) / self.scale

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """Exposed linear light (already x 2^ev) -> continuous codes in [0, 1] (no quantisation)."""
        x = torch.nan_to_num(torch.as_tensor(x).float(), nan=0.0, posinf=1e30, neginf=0.0).clamp_min(0.0)
        y = (x * self.scale).clamp(0.0, 1.0)
        if self.tone == "filmic":
            y = filmic_tone(y)
        return self.transfer.from_linear(y).clamp(0.0, 1.0)

    def quantise(self, codes: torch.Tensor) -> torch.Tensor:
        """Codes rounded to the curve's bit depth (float, in [0, 1])."""
        return torch.round(codes.clamp(0.0, 1.0) * self.levels) / self.levels

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Exposed linear light -> the file's codes, quantised to `bit_depth` (float in [0, 1])."""
        return self.quantise(self.apply(x))

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """Codes -> exposed linear light: the exact inverse of `apply` (tone curve and HLG scale
        included) below the clip; what a bench that knows the camera linearises with."""
        y = self.transfer.to_linear(torch.as_tensor(codes).float().clamp(0.0, 1.0))
        if self.tone == "filmic":
            y = filmic_tone_inverse(y)
        return y / self.scale

    def declares(self, medium: Medium) -> str | None:
        """What a file of this camera states of its transfer (core.transfer form; None: nothing)."""
        return self.video_declares if medium == VIDEO else self.still_declares

    def job_params(self, medium: Medium) -> dict:
        """Capture parameters a bench passes with the file: {} for every realistic camera (the
        file says what it says, as a user uploads it); {"transfer": "gamma:2.4"} for the
        reference where its file cannot state it (a video: H.273 has no code for gamma 2.4)."""
        if self.reference and self.declares(medium) is None:
            return {"transfer": self.oetf}
        return {}

    def loaded(self, codes: torch.Tensor, medium: Medium) -> torch.Tensor:
        """What a loader that believes the declaration (sRGB when there is none) hands the engine:
        the codes in the engine's convention (core.transfer.Transfer.to_convention). For benches
        that build a capture in memory (capture_from_arrays) rather than through a file."""
        stated = self.job_params(medium).get("transfer") or self.declares(medium) or "srgb"
        return parse_transfer(stated).to_convention(torch.as_tensor(codes).float())


CURVES: dict[str, CameraCurve] = {
    "srgb": CameraCurve("srgb", "srgb", 8, "srgb", "srgb", description="the sRGB OETF, 8-bit"),
    "rec709": CameraCurve("rec709", "rec709", 8, None, "rec709",
                          description="the BT.709 OETF, 8-bit (a still declares nothing, a video rec709)"),
    "filmic": CameraCurve("filmic", "srgb", 8, "srgb", "srgb", tone="filmic",
                          description="a phone's filmic S-curve then the sRGB OETF, 8-bit, declared as sRGB"),
    "hlg10": CameraCurve("hlg10", "hlg", 10, None, "hlg", scale=HLG_REFERENCE_WHITE, video_only=True,
                         description="BT.2100 HLG, 10-bit video, reference white at 75 % signal"),
    REFERENCE: CameraCurve(REFERENCE, "gamma:2.4", 8, "gamma:2.4", None, reference=True,
                           description="x^(1/2.4), 8-bit: " + REFERENCE_LABEL),
}


def get_curve(name: str) -> CameraCurve:
    """The curve called `name` (ValueError naming the known ones otherwise)."""
    try:
        return CURVES[name]
    except KeyError:
        raise ValueError(f"unknown camera curve {name!r}; known: {', '.join(NAMES)}") from None


def realistic(medium: Medium) -> tuple[str, ...]:
    """The realistic curves a capture of this medium can be drawn from (a still: no HLG)."""
    return tuple(n for n in REALISTIC if medium == VIDEO or not CURVES[n].video_only)


def draw(capture_name: str, medium: Medium) -> CameraCurve:
    """The capture's curve, drawn uniformly from `realistic(medium)` by a hash of its name
    (deterministic across runs, processes and machines)."""
    pool = realistic(medium)
    digest = hashlib.sha256(str(capture_name).encode()).digest()
    return CURVES[pool[int.from_bytes(digest[:8], "big") % len(pool)]]


def resolve(choice: str, capture_name: str, medium: Medium) -> CameraCurve:
    """The curve a capture is encoded with: `choice` "drawn" draws it (`draw`), a name forces
    it; a video-only curve forced on a still falls back to STILL_FALLBACK."""
    if choice == DRAWN:
        return draw(capture_name, medium)
    curve = get_curve(choice)
    return CURVES[STILL_FALLBACK] if curve.video_only and medium != VIDEO else curve


def run_choices(choice: str, medium: Medium) -> tuple[str, ...]:
    """The runs `--curve choice` asks for: "all" -> every realistic curve of the medium, then
    the reference; else the one choice ("drawn" or a name)."""
    if choice == ALL:
        return (*realistic(medium), REFERENCE)
    if choice != DRAWN:
        get_curve(choice)
    return (choice,)


def check_choice(choice: str) -> str:
    if choice not in CHOICES:
        raise ValueError(f"--curve must be one of {', '.join(CHOICES)}, got {choice!r}")
    return choice


def add_curve_argument(parser, default: str = DRAWN, allow_all: bool = True) -> None:
    """A bench's `--curve` option (`allow_all`: whether the bench can run once per curve)."""
    every = (f", 'all' runs every realistic curve and the reference {REFERENCE} ({REFERENCE_LABEL}) and reports each"
             if allow_all else "")
    parser.add_argument(
        "--curve", default=default, choices=CHOICES if allow_all else tuple(c for c in CHOICES if c != ALL),
        help="the camera curve the captures are encoded with (core.sim.camera_curves): 'drawn' (default) draws one "
             "per capture from the realistic set (seeded by its name), a name forces it" + every)


def curve_label(name: str) -> str:
    """A curve name or "drawn" as a report prints it."""
    return CURVES[name].label if name in CURVES else name


def group_by_curve(rows: list[dict], summarise, key: str = "curve") -> dict:
    """{curve label: summarise(rows encoded with that curve)}, realistic curves first, the
    reference last (rows without `key` are left out)."""
    names = [n for n in NAMES if any(r.get(key) == n for r in rows)]
    return {CURVES[n].label: summarise([r for r in rows if r.get(key) == n]) for n in names}


def display_exposure(hdr: torch.Tensor, percentile: float = 99.0, max_mapping: float = 0.9,
                     gamma: float = 2.4) -> float:
    """DiffusionLight's TonemapHDR exposure rule (core.exposure.display_tonemap) as a linear
    factor k: display_tonemap(hdr) == clip((k hdr)^(1/gamma)). The benches keep the rule and
    change only the curve: their photos are `curve.encode(k * hdr)`."""
    x = hdr.float()
    finite = torch.nan_to_num(x[x != float("inf")], nan=0.0, neginf=0.0).clamp_min(0.0).pow(1.0 / gamma).reshape(-1)
    if finite.numel() > 1_000_000:  # as display_tonemap: torch.quantile's size limit
        finite = finite[:: finite.numel() // 1_000_000 + 1]
    level = float(torch.quantile(finite, percentile / 100.0)) if finite.numel() else 0.0
    return (max_mapping / level) ** gamma if level > 1e-10 else 1.0


# ---------------------------------------------------------------------------------------
# Writing captures as the camera's files
# ---------------------------------------------------------------------------------------
def write_png(path: str | os.PathLike, codes, curve: CameraCurve):
    """An 8-bit PNG of the codes [H, W, 3] declaring what a still of `curve` declares (a camera
    that declares nothing: no colour chunk at all, core.io.images.UNTAGGED)."""
    from core.io.images import UNTAGGED, write_png as _write_png  # noqa: PLC0415 — core.io.images pulls in av, cv2, OpenEXR, PIL: imported when used

    if curve.bit_depth != 8:
        raise ValueError(f"a PNG still is 8-bit; curve {curve.name} is {curve.bit_depth}-bit (video only)")
    return _write_png(path, _numpy(codes), transfer=curve.declares(STILL) or UNTAGGED)


def write_video(path: str | os.PathLike, codes, fps: float, curve: CameraCurve, crf: int = 18):
    """An MP4 of the codes [T, H, W, 3] at the curve's bit depth, its stream declaring the
    curve's transfer characteristics (nothing where H.273 has no code for it); 10-bit curves as
    HEVC, as phones record HDR video."""
    from core.io.video import write_video as _write_video  # noqa: PLC0415 — core.io.video pulls in av, cv2, OpenEXR, PIL: imported when used

    return _write_video(path, _numpy(codes), fps, crf=crf, transfer=curve.declares(VIDEO),
                        bit_depth=curve.bit_depth, codec="libx265" if curve.bit_depth > 8 else None)


def _numpy(codes):
    return codes.detach().cpu().float().numpy() if isinstance(codes, torch.Tensor) else codes
