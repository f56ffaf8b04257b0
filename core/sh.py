"""Real spherical harmonics up to band 2 (9 coefficients) in OUR world frame.

Basis (orthonormal over the sphere, Ramamoorthi & Hanrahan 2001 sign convention, i.e. no
Condon-Shortley phase), evaluated on the unit direction d = (x, y, z) of core.conventions
(+y up, -z forward). Index k, band l, order m:

    k=0  l=0 m= 0   0.282095
    k=1  l=1 m=-1   0.488603 y
    k=2  l=1 m= 0   0.488603 z
    k=3  l=1 m=+1   0.488603 x
    k=4  l=2 m=-2   1.092548 x y
    k=5  l=2 m=-1   1.092548 y z
    k=6  l=2 m= 0   0.315392 (3 z^2 - 1)
    k=7  l=2 m=+1   1.092548 x z
    k=8  l=2 m=+2   0.546274 (x^2 - y^2)

The formulas use our axes literally, so the basis' polar axis (m = 0) is our z (backward),
not up. This is exactly the polynomial form ARCore's samples evaluate in ARCore's world
frame (also +y up, -z forward); ARCore's coefficients differ only by the sign of the odd-m
entries (k = 1, 3, 5, 7): core.export.sh_layouts holds every consumer's layout (`to_arcore_27`
there) and docs/conventions.md explains them.
"""
from __future__ import annotations

import math

import torch

from core.conventions import equirect_directions
from core.envmap import check_envmap

SH_COUNT = 9
SH_BANDS = (0, 1, 1, 1, 2, 2, 2, 2, 2)  # band l of each coefficient index
SH_ORDERS = (0, -1, 0, 1, -2, -1, 0, 1, 2)  # order m of each coefficient index

# Normalisation constants, from their closed forms (printed to 6 digits in the docstring).
C0 = 0.5 * math.sqrt(1.0 / math.pi)  # 0.282095
C1 = math.sqrt(3.0 / (4.0 * math.pi))  # 0.488603
C2 = 0.5 * math.sqrt(15.0 / math.pi)  # 1.092548
C2_0 = 0.25 * math.sqrt(5.0 / math.pi)  # 0.315392
C2_2 = 0.25 * math.sqrt(15.0 / math.pi)  # 0.546274

# Clamped-cosine convolution (Ramamoorthi & Hanrahan 2001): E_lm = A_l L_lm.
COSINE_LOBE_BY_BAND = (math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0)


class SHError(ValueError):
    """Malformed SH coefficients or ARCore arrays."""


def check_coeffs(coeffs: torch.Tensor) -> None:
    if coeffs.shape[0] != SH_COUNT:
        raise SHError(f"SH coefficients must have shape [9, ...], got {tuple(coeffs.shape)}")


def sh_basis(d: torch.Tensor) -> torch.Tensor:
    """Basis values [..., 9] at directions d [..., 3] (normalised here; zero d gives band 0 only)."""
    if d.shape[-1] != 3:
        raise SHError(f"directions must have shape [..., 3], got {tuple(d.shape)}")
    n = d.norm(dim=-1, keepdim=True)
    u = d / n.clamp_min(torch.finfo(d.dtype).tiny)
    x, y, z = u.unbind(-1)
    return torch.stack(
        (
            torch.full_like(x, C0),
            C1 * y,
            C1 * z,
            C1 * x,
            C2 * x * y,
            C2 * y * z,
            C2_0 * (3.0 * z * z - 1.0) * (n[..., 0] > 0),  # zero vector: keep only the constant
            C2 * x * z,
            C2_2 * (x * x - y * y),
        ),
        dim=-1,
    )


def pixel_basis_integrals(height: int, device=None) -> torch.Tensor:
    """Exact integrals of each basis function over each equirect pixel's cell, [H, 2H, 9] float64.

    Treating a pixel as constant radiance over its cell (the same model as the exact
    per-pixel solid angles), projection is then exact: a constant map has exactly zero
    band 1 and 2 coefficients, which midpoint quadrature only reaches as O(1/H^2).
    With x = sin t sin p, y = cos t, z = -sin t cos p and dw = sin t dt dp, every integral
    is a product of a theta integral and a phi integral in closed form.
    """
    h = int(height)
    w = 2 * h
    t = torch.arange(h + 1, dtype=torch.float64) * (math.pi / h)
    a, b = t[:-1, None], t[1:, None]  # [H, 1]
    p = torch.arange(w + 1, dtype=torch.float64) * (2.0 * math.pi / w) - math.pi
    q0, q1 = p[None, :-1], p[None, 1:]  # [1, W]
    ca, cb = torch.cos(a), torch.cos(b)
    # theta integrals (with the sin t Jacobian)
    i_s1 = ca - cb  # sin
    i_cs = (ca * ca - cb * cb) / 2  # cos sin
    i_s2 = (b - a) / 2 - (torch.sin(2 * b) - torch.sin(2 * a)) / 4  # sin^2
    i_c2s = (ca**3 - cb**3) / 3  # cos^2 sin
    i_s3 = i_s1 - i_c2s  # sin^3
    i_s2c = (torch.sin(b) ** 3 - torch.sin(a) ** 3) / 3  # sin^2 cos
    # phi integrals
    j1 = q1 - q0
    js = torch.cos(q0) - torch.cos(q1)
    jc = torch.sin(q1) - torch.sin(q0)
    d2 = (torch.sin(2 * q1) - torch.sin(2 * q0)) / 4
    jss, jcc = j1 / 2 - d2, j1 / 2 + d2
    jsc = (torch.sin(q1) ** 2 - torch.sin(q0) ** 2) / 2
    out = torch.stack(
        (
            C0 * i_s1 * j1,
            C1 * i_cs * j1,  # y
            -C1 * i_s2 * jc,  # z
            C1 * i_s2 * js,  # x
            C2 * i_s2c * js,  # x y
            -C2 * i_s2c * jc,  # y z
            C2_0 * (3 * i_s3 * jcc - i_s1 * j1),  # 3 z^2 - 1
            -C2 * i_s3 * jsc,  # x z
            C2_2 * (i_s3 * jss - i_c2s * j1),  # x^2 - y^2
        ),
        dim=-1,
    )
    return out.to(device)


def project_sh(envmap: torch.Tensor) -> torch.Tensor:
    """Projection c_k = integral L Y_k dw of the pixel-wise constant map -> [9, 3] (exact per cell)."""
    h = check_envmap(envmap)
    cells = pixel_basis_integrals(h, device=envmap.device)
    coeffs = torch.einsum("hwk,hwc->kc", cells, envmap.to(torch.float64))
    return coeffs.to(envmap.dtype)


def eval_sh(coeffs: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Reconstruct sum_k c_k Y_k(d): coeffs [9, C], d [..., 3] -> [..., C]."""
    check_coeffs(coeffs)
    return sh_basis(d.to(coeffs.dtype)) @ coeffs


def sh_irradiance(coeffs: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """Irradiance E(n) = integral L(d) max(0, n.d) dd of the band-limited radiance -> [..., C].

    Divide by pi for the outgoing radiance of a white Lambertian surface.
    """
    check_coeffs(coeffs)
    a = torch.tensor([COSINE_LOBE_BY_BAND[l] for l in SH_BANDS], dtype=coeffs.dtype, device=coeffs.device)
    return eval_sh(coeffs * a[:, None], normal)


def sh_to_envmap(coeffs: torch.Tensor, height: int) -> torch.Tensor:
    """Render band-limited radiance into an equirect map [H, 2H, C]."""
    d = equirect_directions(height, device=coeffs.device, dtype=coeffs.dtype)
    return eval_sh(coeffs, d)


__all__ = [
    "SH_COUNT",
    "SH_BANDS",
    "SH_ORDERS",
    "COSINE_LOBE_BY_BAND",
    "SHError",
    "check_coeffs",
    "sh_basis",
    "project_sh",
    "pixel_basis_integrals",
    "eval_sh",
    "sh_irradiance",
    "sh_to_envmap",
]
