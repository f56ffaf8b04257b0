"""Area-correct pixels around small lamps.

A lamp smaller than a pixel falls between pixel-centre rays and would vanish from a frame
or a ground-truth env map (or land as one full-radiance pixel). Pixels whose footprint can
touch a lamp are therefore re-rendered with s x s sub-samples and averaged (env maps
weight sub-samples by solid angle), so a pixel holds the mean radiance over its area and
a lamp's energy is right at any resolution. Only a handful of pixels per lamp are refined.
"""
from __future__ import annotations

import math

import torch

from core.camera import Camera
from core.conventions import theta_phi_to_direction
from core.sim.shading import ShadingContext

MAX_SUBSAMPLES = 24  # per pixel side
SAMPLES_ACROSS_LAMP = 4  # sub-samples across a lamp's angular diameter


def _subsample_count(pixel_size: float, lamp_size: float) -> int:
    return int(min(MAX_SUBSAMPLES, max(2, math.ceil(SAMPLES_ACROSS_LAMP * pixel_size / max(lamp_size, 1e-12)))))


def envmap_lamp_pixels(ctx: ShadingContext, probe: torch.Tensor, height: int, trace_fn) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """[(flat pixel indices, mean radiance [P, 3])] for the pixels near each lit lamp."""
    from core.conventions import equirect_directions

    lights = ctx.lights
    out = []
    if len(lights.lamp_center) == 0:
        return out
    centres = equirect_directions(height).reshape(-1, 3)
    pix_angle = math.pi / height
    width = 2 * height
    for c, r in zip(lights.lamp_center, lights.lamp_radius):
        v = c - probe
        dist = float(v.norm())
        if dist <= float(r):
            continue
        alpha = math.asin(float(r) / dist)
        cos_sep = centres @ (v / dist)
        near = torch.nonzero(cos_sep >= math.cos(min(math.pi, alpha + pix_angle))).squeeze(1)
        if len(near) == 0:
            continue
        s = _subsample_count(pix_angle, 2 * alpha)
        i, j = near // width, near % width
        a = (torch.arange(s, dtype=torch.float64) + 0.5) / s
        theta = math.pi * (i[:, None, None].double() + a[None, :, None]) / height  # [P, s, 1]
        phi = 2 * math.pi * (j[:, None, None].double() + a[None, None, :]) / width - math.pi  # [P, 1, s]
        theta, phi = torch.broadcast_tensors(theta, phi)
        d = theta_phi_to_direction(theta, phi).to(torch.float32).reshape(-1, 3)
        w = torch.sin(theta).reshape(len(near), s * s).to(torch.float32)
        w = w / w.sum(1, keepdim=True).clamp_min(1e-30)
        rad = trace_fn(ctx, probe, d).radiance.reshape(len(near), s * s, 3)
        out.append((near, (rad * w[..., None]).sum(1)))
    return out


def frame_lamp_pixels(ctx: ShadingContext, camera: Camera, trace_fn) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """[(flat pixel indices, mean radiance [P, 3])] for pixels near each lamp's projection."""
    lights = ctx.lights
    out = []
    if len(lights.lamp_center) == 0:
        return out
    k = camera.intrinsics
    u, v, z = camera.project(lights.lamp_center.to(torch.float64))
    rot = camera.c2w[:3, :3]
    origin = camera.position.to(torch.float32)
    for ui, vi, zi, r in zip(u.tolist(), v.tolist(), z.tolist(), lights.lamp_radius.tolist()):
        if zi <= r:
            continue  # behind (or around) the camera
        r_px = max(k.fx, k.fy) * r / math.sqrt(max(zi * zi - r * r, 1e-12))
        reach = r_px * 1.5 + 1.0  # margin for the off-axis stretch of the projected disc
        c0, c1 = max(0, int(math.floor(ui - reach))), min(k.width, int(math.ceil(ui + reach)))
        r0, r1 = max(0, int(math.floor(vi - reach))), min(k.height, int(math.ceil(vi + reach)))
        if c0 >= c1 or r0 >= r1:
            continue
        s = _subsample_count(1.0, 2 * r_px)
        rows, cols = torch.meshgrid(torch.arange(r0, r1), torch.arange(c0, c1), indexing="ij")
        rows, cols = rows.reshape(-1), cols.reshape(-1)
        a = (torch.arange(s, dtype=torch.float64) + 0.5) / s
        uu = (cols[:, None, None].double() + a[None, None, :]).expand(-1, s, s)
        vv = (rows[:, None, None].double() + a[None, :, None]).expand(-1, s, s)
        ray = torch.stack(((uu - k.cx) / k.fx, -(vv - k.cy) / k.fy, -torch.ones_like(uu)), -1) @ rot.T
        d = (ray / ray.norm(dim=-1, keepdim=True)).to(torch.float32).reshape(-1, 3)
        rad = trace_fn(ctx, origin, d).radiance.reshape(len(rows), s * s, 3).mean(1)
        out.append((rows * k.width + cols, rad))
    return out
