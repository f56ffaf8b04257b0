"""Evaluation: the three-sphere protocol and a temporal-flicker metric.

Three-sphere protocol (StyleLight / DiffusionLight evaluation): render a diffuse grey, a
rough silver ("matte") and a mirror sphere under the predicted and the ground-truth env
map, and compare the renders with scale-invariant RMSE, angular error and normalised RMSE.

Our renderer is analytic, not Blender Cycles. Differences from the published renders:
* view: orthographic, from +z looking along -z at a unit sphere filling the image
  (Blender: perspective 85 mm camera, so slightly more of the back is visible);
* diffuse: Lambertian, albedo 0.8, exact cosine convolution of a 32 x 64 area-downsampled
  map (Blender: Principled BSDF, path traced);
* matte: a normalised Phong lobe around the mirror direction, exponent 40 (about 9 deg
  wide, roughly GGX roughness 0.33), reflectance 0.8, integrated over a 64 x 128 map
  (Blender: metallic Principled roughness 0.327 mixed with a Glossy BSDF by Fresnel);
* mirror: reflectance 1, bilinear lookup in the 128 x 256 map;
* no Fresnel, no self-shadowing, no interreflection, no anti-aliasing at the rim.
Absolute numbers are therefore comparable between our own methods, not with tables in
papers.

Errors follow the reference implementation (DiffusionLight-evaluation's fast_rmse.py):
squared errors are summed over RGB and averaged over mask pixels. nRMSE maps each image
by its own 0.1th / 99.9th percentiles over the mask pixels (the reference code uses the
0.01th percentile over the whole image).
"""
from __future__ import annotations

import math
from typing import Literal

import torch

from core.conventions import equirect_directions
from core.envmap import check_envmap, resize_envmap, sample_envmap, solid_angles
from core.exposure import luminance

Material = Literal["diffuse", "matte", "mirror"]
MATERIALS: tuple[str, ...] = ("diffuse", "matte", "mirror")

EVAL_HEIGHT = 128  # env maps are compared at 128 x 256
DIFFUSE_ALBEDO = 0.8
DIFFUSE_MAP_HEIGHT = 32
MATTE_REFLECTANCE = 0.8
MATTE_PHONG_EXPONENT = 40.0
MATTE_MAP_HEIGHT = 64
MIRROR_REFLECTANCE = 1.0
NRMSE_PERCENTILES = (0.1, 99.9)
_LOBE_CHUNK = 1024


class MetricsError(ValueError):
    """Bad input to a metric (shape mismatch, empty mask, non-finite values, unknown material)."""


# ---------------------------------------------------------------------------------------
# Probe-sphere renders
# ---------------------------------------------------------------------------------------
def sphere_normals(size: int, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit normals [size, size, 3] (zeros outside) and mask of an orthographic unit sphere
    seen from +z: pixel (r, c) centre is x = 2 (c + 1/2)/size - 1, y = 1 - 2 (r + 1/2)/size."""
    if size < 1:
        raise MetricsError(f"size must be >= 1, got {size}")
    t = (torch.arange(size, dtype=torch.float64, device=device) + 0.5) * (2.0 / size) - 1.0
    y, x = torch.meshgrid(-t, t, indexing="ij")
    rho2 = x * x + y * y
    mask = rho2 < 1.0
    z = torch.sqrt((1.0 - rho2).clamp_min(0.0))
    n = torch.stack((x, y, z), dim=-1) * mask[..., None]
    return n, mask


def _reflect_view(n: torch.Tensor) -> torch.Tensor:
    """Mirror direction for the view ray (0, 0, -1): d = r - 2 (r.n) n."""
    r = torch.tensor([0.0, 0.0, -1.0], dtype=n.dtype, device=n.device)
    return r - 2.0 * (n @ r)[..., None] * n


def _lobe_integral(envmaps: list[torch.Tensor], height: int, axes: torch.Tensor, lobe) -> list[torch.Tensor]:
    """sum_d L(d) w(d) dw / sum_d w(d) dw with w = lobe(axes . d), a normalised filter,
    for several maps at once (the weights, the expensive part, are shared)."""
    device = axes.device
    small = torch.cat([resize_envmap(e, height).reshape(-1, 3) for e in envmaps], dim=-1).to(torch.float32)
    dirs = equirect_directions(height, device=device, dtype=torch.float32).reshape(-1, 3)
    dw = solid_angles(height, device=device, dtype=torch.float32).reshape(-1)
    out = []
    for chunk in axes.to(torch.float32).split(_LOBE_CHUNK):  # bounds memory to chunk x texels
        weights = lobe(chunk @ dirs.T) * dw
        out.append((weights @ small) / weights.sum(-1, keepdim=True).clamp_min(1e-30))
    values = torch.cat(out) if out else axes.new_zeros(0, small.shape[-1])
    return list(values.split(3, dim=-1))


def render_probe_spheres(
    envmaps: list[torch.Tensor], material: Material, size: int = 128
) -> tuple[list[torch.Tensor], torch.Tensor]:
    """`render_probe_sphere` for several env maps sharing the filter weights."""
    if material not in MATERIALS:
        raise MetricsError(f"material must be one of {MATERIALS}, got {material!r}")
    for i, e in enumerate(envmaps):
        check_envmap(e, f"envmaps[{i}]")
    # Diffuse and matte filter maps area-downsampled straight from the input (for inputs
    # of 128 x 256 or a multiple of it the pixel edges nest, so this equals resizing to
    # 128 x 256 first); skipping the intermediate map saves most of the cost.
    device = envmaps[0].device
    n, mask = sphere_normals(size, device=device)
    normals = n[mask]
    if material == "mirror":
        d = _reflect_view(normals)
        values = [
            MIRROR_REFLECTANCE * sample_envmap(resize_envmap(e, EVAL_HEIGHT).to(torch.float64), d) for e in envmaps
        ]
    elif material == "diffuse":
        # normalised cosine filter = E(n) / pi; Lambertian radiance = albedo E / pi
        values = [
            DIFFUSE_ALBEDO * v for v in _lobe_integral(envmaps, DIFFUSE_MAP_HEIGHT, normals, lambda c: c.clamp_min(0.0))
        ]
    else:
        k = MATTE_PHONG_EXPONENT
        lobe = lambda c: c.clamp_min(0.0) ** k  # noqa: E731
        values = [
            MATTE_REFLECTANCE * v for v in _lobe_integral(envmaps, MATTE_MAP_HEIGHT, _reflect_view(normals), lobe)
        ]
    images = []
    for v in values:
        image = torch.zeros(size, size, 3, dtype=torch.float32, device=device)
        image[mask] = v.to(torch.float32)
        images.append(image)
    return images, mask


def render_probe_sphere(envmap: torch.Tensor, material: Material, size: int = 128) -> tuple[torch.Tensor, torch.Tensor]:
    """Image [size, size, 3] (float32, zero outside) and mask [size, size] of a probe sphere.

    The mirror looks the map up at 128 x 256; diffuse and matte filter it at 32 x 64 and
    64 x 128 (area-correct downsampling). See the module docstring for each model.
    """
    images, mask = render_probe_spheres([envmap], material, size)
    return images[0], mask


# ---------------------------------------------------------------------------------------
# Image metrics
# ---------------------------------------------------------------------------------------
def _masked(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    if pred.shape != gt.shape or pred.shape[-1] != 3:
        raise MetricsError(
            f"pred and gt must have the same shape [..., 3], got {tuple(pred.shape)} and {tuple(gt.shape)}"
        )
    if mask is None:
        mask = torch.ones(pred.shape[:-1], dtype=torch.bool, device=pred.device)
    if tuple(mask.shape) != tuple(pred.shape[:-1]):
        raise MetricsError(f"mask shape {tuple(mask.shape)} does not match image {tuple(pred.shape[:-1])}")
    if not bool(mask.any()):
        raise MetricsError("mask selects no pixels")
    p, g = pred[mask.bool()].to(torch.float64), gt[mask.bool()].to(torch.float64)
    for name, x in (("pred", p), ("gt", g)):
        if not bool(torch.isfinite(x).all()):
            raise MetricsError(f"{name} contains non-finite values inside the mask")
    return p, g


def si_rmse(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """Scale-invariant RMSE: min over alpha of RMSE(alpha pred, gt), alpha = sum p g / sum p p
    in closed form (alpha = 0 for an all-zero prediction)."""
    p, g = _masked(pred, gt, mask)
    pp = (p * p).sum()
    alpha = (p * g).sum() / pp if pp > 0 else torch.zeros((), dtype=p.dtype)
    return float(torch.sqrt(((alpha * p - g) ** 2).sum(-1).mean()))


def angular_error_deg(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """Mean angle in degrees between pred and gt RGB vectors over the mask.

    Two black pixels agree (0 deg); a black pixel against a non-black one counts as 90 deg
    (the reference code silently scores it 0)."""
    p, g = _masked(pred, gt, mask)
    np_, ng = p.norm(dim=-1), g.norm(dim=-1)
    cos = (p * g).sum(-1) / (np_ * ng).clamp_min(1e-300)
    angle = torch.acos(cos.clamp(-1.0, 1.0))
    both_zero = (np_ == 0) & (ng == 0)
    one_zero = (np_ == 0) ^ (ng == 0)
    angle = torch.where(
        both_zero, torch.zeros_like(angle), torch.where(one_zero, torch.full_like(angle, math.pi / 2), angle)
    )
    return math.degrees(float(angle.mean()))


def _percentile_normalise(x: torch.Tensor) -> torch.Tensor:
    lo, hi = torch.quantile(x.reshape(-1), torch.tensor(NRMSE_PERCENTILES, dtype=x.dtype, device=x.device) / 100.0)
    span = hi - lo
    if not span > 1e-12 * max(float(hi.abs()), 1e-300):
        return torch.zeros_like(x)  # constant image: nothing to normalise
    return (x - lo) / span


def normalized_rmse(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """RMSE after mapping each image by its own 0.1th / 99.9th percentiles to [0, 1]."""
    p, g = _masked(pred, gt, mask)
    return float(torch.sqrt(((_percentile_normalise(p) - _percentile_normalise(g)) ** 2).sum(-1).mean()))


def three_sphere_metrics(
    pred_envmap: torch.Tensor, gt_envmap: torch.Tensor, size: int = 128
) -> dict[str, dict[str, float]]:
    """{diffuse, matte, mirror} x {si_rmse, angular_deg, nrmse} for two env maps."""
    check_envmap(pred_envmap, "pred_envmap")
    check_envmap(gt_envmap, "gt_envmap")
    out: dict[str, dict[str, float]] = {}
    for material in MATERIALS:
        (p, g), mask = render_probe_spheres([pred_envmap, gt_envmap], material, size)
        out[material] = {
            "si_rmse": si_rmse(p, g, mask),
            "angular_deg": angular_error_deg(p, g, mask),
            "nrmse": normalized_rmse(p, g, mask),
        }
    return out


# ---------------------------------------------------------------------------------------
# Observed-region correlation
# ---------------------------------------------------------------------------------------
OBSERVED_LOG_FLOOR = 1e-3  # relative to each image's mean luminance


def observed_region_correlation(envmap: torch.Tensor, photo_linear: torch.Tensor, rays: torch.Tensor,
                                mask: torch.Tensor | None = None) -> float:
    """Does an env map reproduce what the camera saw? Pearson correlation of log-luminance
    between the env map re-projected into the capturing camera and the linearised photo.

    envmap [h, 2h, 3] in the frame of `rays`; photo_linear [H, W, 3] (linear radiance at any
    exposure); rays [H, W, 3] each pixel's viewing direction from the env map's centre (the
    camera at the probe position: world-frame pixel rays). The map is sampled bilinearly
    along every ray (core.envmap.sample_envmap: wraps the seam, continuous at the poles).
    log(Y + eps), eps = OBSERVED_LOG_FLOOR x the image's mean luminance, so neither the
    photo's exposure nor the map's scale matters and near-black noise does not dominate.
    Correlation is undefined when either side is constant: scored 0 (nothing reproduced).
    `mask` [H, W] restricts the pixels (e.g. to exclude a region).
    """
    check_envmap(envmap, "envmap")
    if photo_linear.ndim != 3 or photo_linear.shape[-1] != 3 or tuple(rays.shape) != tuple(photo_linear.shape):
        raise MetricsError(
            f"photo_linear and rays must both be [H, W, 3], got {tuple(photo_linear.shape)} and {tuple(rays.shape)}"
        )
    pred = sample_envmap(envmap.to(torch.float64), rays.to(torch.float64))
    p, g = _masked(pred, photo_linear.to(torch.float64), mask)
    logs = []
    for x in (p, g):
        y = luminance(x).clamp_min(0.0)
        mean = float(y.mean())
        if mean <= 0.0:
            return 0.0
        logs.append(torch.log(y + OBSERVED_LOG_FLOOR * mean))
    a, b = (v - v.mean() for v in logs)
    sa, sb = float(a.norm()), float(b.norm())
    if sa <= 1e-9 * math.sqrt(a.numel()) or sb <= 1e-9 * math.sqrt(b.numel()):
        return 0.0
    return float((a * b).sum()) / (sa * sb)


# ---------------------------------------------------------------------------------------
# Temporal flicker
# ---------------------------------------------------------------------------------------
FLICKER_FLOOR = 1e-3  # relative to the sequence's mean luminance


def temporal_flicker(sequence: torch.Tensor) -> float:
    """Mean absolute frame-to-frame change of log-luminance, [T, H, W, 3] -> float.

    flicker = mean over t, pixels of |log(Y_{t+1} + eps) - log(Y_t + eps)|, which is the
    relative change for small changes (0.01 = 1 % per frame). eps = 1e-3 x the mean
    luminance of the whole sequence, so noise in near-black pixels does not dominate and a
    global brightness scale does not change the value. A single frame or an all-black
    sequence has flicker 0.
    """
    if sequence.ndim < 2 or sequence.shape[-1] != 3:
        raise MetricsError(f"sequence must be [T, ..., 3], got {tuple(sequence.shape)}")
    if not bool(torch.isfinite(sequence).all()):
        raise MetricsError("sequence contains non-finite values")
    if sequence.shape[0] < 2:
        return 0.0
    y = luminance(sequence.to(torch.float64)).clamp_min(0.0)
    mean = float(y.mean())
    if mean <= 0.0:
        return 0.0
    log_y = torch.log(y + FLICKER_FLOOR * mean)
    return float((log_y[1:] - log_y[:-1]).abs().mean())
