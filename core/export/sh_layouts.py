"""Every consumer's spherical-harmonics layout, in one table: the only place that knows signs,
scales, axes and packing. Every exporter, the CLI and the API convert through `to_layout` /
`pack`; nothing else flips a sign.

Our coefficients c_k (core.sh): radiance, real orthonormal basis *without* the Condon-Shortley
phase, k = 0..8 = (l, m) = (0,0), (1,-1), (1,0), (1,1), (2,-2), (2,-1), (2,0), (2,1), (2,2)
(1, y, z, x, xy, yz, 3z^2-1, xz, x^2-y^2), in our frame (+y up, camera -z). A layout's value for
coefficient k is, per channel,

    v_k = phase_k * mirror_k * scale_k * c_k

- phase_k = (-1)^m when the consumer's basis carries the Condon-Shortley phase (its Y_1^1 is
  -C1 x): ARCore, Babylon.js (`SH3ylmBasisConstants` has -sqrt(3/4pi) for l1_1 and l11) and
  therefore glTF EXT_lights_image_based, whose reference loader is Babylon's.
- mirror_k = the parity of Y_k under the flip from our axes to the consumer's (Unity: z -> -z,
  so k = 2 (z), 5 (yz), 7 (xz) change sign).
- scale_k: 1 for radiance; the clamped-cosine lobe A_l (pi, 2pi/3, pi/4) for irradiance; for
  Unity's SphericalHarmonicsL2, A_l * C_k / pi (Unity folds the basis constant and the Lambert
  1/pi into what it stores, so ShadeSH9 returns outgoing radiance).
- packing: 'rgb_interleaved' (c0.r, c0.g, c0.b, c1.r, ...; also glTF's 9 x [r, g, b]) or
  'channel_planes' (nine R, nine G, nine B; Unity's [channel][k], ARKit's three planes).

Each row names what checks it against the consumer's own code (tests/test_export_node.py runs
three.js and Babylon.js; Unity and ARKit do not install here and are checked against their
documented formulas).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from core.sh import C0, C1, C2, C2_0, C2_2, COSINE_LOBE_BY_BAND, SH_BANDS, SH_COUNT, SH_ORDERS, SHError, check_coeffs

_BASIS_CONSTANTS = (C0, C1, C1, C1, C2, C2, C2_0, C2, C2_2)
_LOBE = tuple(COSINE_LOBE_BY_BAND[l] for l in SH_BANDS)
# Parity of each basis function under negating one axis: which of 1, y, z, x, xy, yz, 3z^2-1, xz, x^2-y^2 flip.
_ODD_IN = {"x": (3, 4, 7), "y": (1, 4, 5), "z": (2, 5, 7)}


@dataclass(frozen=True)
class SHLayout:
    name: str
    reads_it: str  # the consumer API that reads these numbers
    quantity: str  # 'radiance', 'irradiance' or 'lambertian radiance x basis constant' (Unity)
    condon_shortley: bool  # odd-m entries negated
    mirrored_axes: tuple[str, ...]  # our axes negated to reach the consumer's frame
    scale: tuple[float, ...]  # scale_k, k = 0..8
    packing: str  # 'rgb_interleaved' or 'channel_planes'
    checked_by: str

    @property
    def signs(self) -> np.ndarray:
        """phase_k * mirror_k, [9]."""
        s = np.array([-1.0 if (self.condon_shortley and m % 2) else 1.0 for m in SH_ORDERS])
        for axis in self.mirrored_axes:
            s[list(_ODD_IN[axis])] *= -1.0
        return s

    @property
    def factors(self) -> np.ndarray:
        """v_k / c_k, [9]."""
        return self.signs * np.asarray(self.scale, np.float64)

    def describe(self) -> str:
        flipped = [k for k, s in enumerate(self.signs) if s < 0]
        return (
            f"{self.name}: {self.quantity} for {self.reads_it}; "
            f"{'entries k = ' + ', '.join(map(str, flipped)) + ' negated' if flipped else 'no sign change'}"
            f"{'' if set(self.scale) == {1.0} else ', scaled per band'}; "
            + ("27 floats, coefficient-major, RGB interleaved" if self.packing == "rgb_interleaved"
               else "27 floats, three planes of 9 (R, G, B)")
        )


LAYOUTS: dict[str, SHLayout] = {layout.name: layout for layout in (
    SHLayout("arcore", "ARCore LightEstimate.getEnvironmentalHdrAmbientSphericalHarmonics", "radiance", True, (),
             (1.0,) * 9, "rgb_interleaved",
             "the factors ARCore's hello_ar shader multiplies them with (tests/test_sh.py)"),
    SHLayout("threejs", "three.js SphericalHarmonics3.fromArray / LightProbe", "radiance", False, (),
             (1.0,) * 9, "rgb_interleaved", "three r187's SphericalHarmonics3 in Node (tests/test_export_node.py)"),
    SHLayout("babylon", "Babylon.js SphericalHarmonics.FromArray; glTF EXT_lights_image_based irradianceCoefficients",
             "irradiance", True, (), _LOBE, "rgb_interleaved",
             "@babylonjs/core's SH -> polynomial path against its own cube projection (tests/test_export_node.py)"),
    SHLayout("unity", "Unity SphericalHarmonicsL2 [channel, k] (UnityCG ShadeSH9)",
             "lambertian radiance x basis constant", False, ("z",),
             tuple(a * c / math.pi for a, c in zip(_LOBE, _BASIS_CONSTANTS)), "channel_planes",
             "UnityCG.cginc's ShadeSH9 formula (Unity does not install here; tests/test_export.py)"),
    SHLayout("arkit", "ARKit ARDirectionalLightEstimate.sphericalHarmonicsCoefficients", "radiance", False, (),
             (1.0,) * 9, "channel_planes",
             "layout only: Apple documents three planes of 9 but not the basis signs (no Apple device here)"),
)}
LAYOUT_NAMES = tuple(LAYOUTS)
ALIASES = {"gltf": "babylon"}


def get_layout(name: str) -> SHLayout:
    key = ALIASES.get(name, name)
    if key not in LAYOUTS:
        raise ValueError(f"SH layout must be one of {', '.join(LAYOUT_NAMES)}, got {name!r}")
    return LAYOUTS[key]


def _coeffs(radiance_sh) -> np.ndarray:
    c = radiance_sh.detach().cpu().double().numpy() if hasattr(radiance_sh, "detach") else radiance_sh
    c = np.asarray(c, np.float64)
    if c.shape != (SH_COUNT, 3):
        raise ValueError(f"SH must be [9, 3] (RGB), got {c.shape}")
    return c


def to_layout(radiance_sh, name: str) -> np.ndarray:
    """Our radiance SH [9, 3] -> the layout's values v_k, [9, 3] (index k, RGB)."""
    return _coeffs(radiance_sh) * get_layout(name).factors[:, None]


def pack(radiance_sh, name: str) -> list[float]:
    """Our radiance SH [9, 3] -> the 27 floats the consumer reads, in its packing."""
    v = to_layout(radiance_sh, name)
    return [float(a) for a in (v.T if get_layout(name).packing == "channel_planes" else v).reshape(-1)]


def unpack(values, name: str) -> np.ndarray:
    """Inverse of `pack`: 27 floats in the layout -> our radiance SH [9, 3] (float64)."""
    a = np.asarray(values, np.float64).reshape(-1)
    if a.size != 27:
        raise ValueError(f"an SH layout holds exactly 27 floats, got {a.size}")
    layout = get_layout(name)
    v = a.reshape(3, 9).T if layout.packing == "channel_planes" else a.reshape(9, 3)
    return v / layout.factors[:, None]


def to_arcore_27(coeffs: torch.Tensor) -> list[float]:
    """Our [9, 3] radiance coefficients -> ARCore's 27 floats.

    ARCore (`LightEstimate.getEnvironmentalHdrAmbientSphericalHarmonics`): coefficient-major,
    RGB interleaved [c0.r, c0.g, c0.b, c1.r, ...], same band order and world frame as ours,
    but with the Condon-Shortley phase, so entries with odd m (k = 1, 3, 5, 7) are negated.
    """
    check_coeffs(coeffs)
    if tuple(coeffs.shape) != (SH_COUNT, 3):
        raise SHError(f"ARCore layout needs RGB coefficients [9, 3], got {tuple(coeffs.shape)}")
    return pack(coeffs, "arcore")


def from_arcore_27(values: Sequence[float] | torch.Tensor, dtype=torch.float32) -> torch.Tensor:
    """Inverse of `to_arcore_27`: 27 floats -> our [9, 3] coefficients."""
    t = torch.as_tensor(values, dtype=torch.float64).reshape(-1)
    if t.numel() != 27:
        raise SHError(f"ARCore spherical harmonics need exactly 27 floats, got {t.numel()}")
    if not torch.isfinite(t).all():
        raise SHError("ARCore spherical harmonics contain non-finite values")
    return torch.from_numpy(unpack(t.numpy(), "arcore")).to(dtype)


__all__ = ["SHLayout", "LAYOUTS", "LAYOUT_NAMES", "get_layout", "to_layout", "pack", "unpack", "to_arcore_27",
           "from_arcore_27"]
