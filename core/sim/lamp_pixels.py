"""Area-correct pixels around small lamps.

A lamp smaller than a pixel falls between pixel-centre rays and would vanish from a frame
or a ground-truth env map (or land as one full-radiance pixel). So every pixel whose
footprint can touch a lamp is re-estimated as the area-weighted mean radiance over it:

* the pixel's own s x s sub-samples, minus those inside a lamp's cone, stand for the
  background (weights: solid angle for env maps, image area for frames);
* a stratified set of rays inside each lamp's cone (half-angle asin(R / D)) stands for
  the lamp; each carries the cone's solid angle / n (converted to image area for frames)
  and lands in the pixel its direction falls in. Rays that an occluder blocks see the
  occluder, so partly hidden lamps come out right.

Each pixel is the weight-normalised sum, so a uniform pixel stays exact and a lamp's
power (radiance x solid angle) is kept at any resolution. Only pixels near lamps are
touched; all lamps are handled together so neighbouring lamps do not overwrite each other.
"""
from __future__ import annotations

import math

import torch

from core.camera import Camera
from core.conventions import (
    direction_to_equirect_pixel,
    equirect_directions,
    pixel_to_camera_ray,
    theta_phi_to_direction,
)
from core.sim.shading import ShadingContext, tangent_frame

SUBSAMPLES = 4  # per pixel side, for the background part of a refined pixel
CONE_SAMPLES = 16  # per side of the stratified grid inside each lamp's cone


def _lamp_cones(ctx: ShadingContext, origin: torch.Tensor):
    """Directions [L, 3], half-angles [L] and cosines of the lamps seen from `origin`
    (lamps that are off or contain the origin are dropped)."""
    lights = ctx.lights
    v = lights.lamp_center - origin
    dist = v.norm(dim=-1)
    keep = (dist > lights.lamp_radius) & (lights.lamp_radiance.amax(-1) > 0)
    v, dist, radius = v[keep], dist[keep], lights.lamp_radius[keep]
    alpha = torch.asin((radius / dist).clamp(max=1.0))
    return v / dist[:, None], alpha


def _cone_rays(axis: torch.Tensor, alpha: torch.Tensor):
    """Stratified uniform directions [L * n, 3] inside cones, and each ray's solid angle [L * n]."""
    k = CONE_SAMPLES
    a = (torch.arange(k, dtype=torch.float64) + 0.5) / k
    u1, u2 = torch.meshgrid(a, a, indexing="ij")
    u1, u2 = u1.reshape(-1), u2.reshape(-1)
    cos_a = torch.cos(alpha.double())[:, None]
    cos_t = 1.0 - u1[None] * (1.0 - cos_a)  # uniform in solid angle
    sin_t = (1.0 - cos_t * cos_t).clamp_min(0.0).sqrt()
    phi = 2.0 * math.pi * u2[None]
    t1, t2 = tangent_frame(axis.double())
    d = (
        (sin_t * phi.cos())[..., None] * t1[:, None]
        + (sin_t * phi.sin())[..., None] * t2[:, None]
        + cos_t[..., None] * axis.double()[:, None]
    )
    omega = (2.0 * math.pi * (1.0 - cos_a)).expand(-1, k * k) / (k * k)
    return d.reshape(-1, 3).float(), omega.reshape(-1).float()


def _inside_any_cone(d: torch.Tensor, axis: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    return ((d @ axis.T) >= torch.cos(alpha)[None]).any(-1)


def _weighted_pixels(ctx, origin, trace_fn, pixel, d, w, candidates):
    """Trace rays d (landing in flat `pixel` with weight w) and return the weighted mean
    radiance of each candidate pixel."""
    keep = torch.isin(pixel, candidates)
    pixel, d, w = pixel[keep], d[keep], w[keep]
    rad = trace_fn(ctx, origin, d).radiance
    slot = torch.searchsorted(candidates, pixel)
    num = torch.zeros(len(candidates), 3).index_add_(0, slot, rad * w[:, None])
    den = torch.zeros(len(candidates)).index_add_(0, slot, w)
    return candidates, num / den.clamp_min(1e-30)[:, None]


def _subpixel_offsets(s: int) -> torch.Tensor:
    return (torch.arange(s, dtype=torch.float64) + 0.5) / s


def subpixel_rays(camera: Camera, pixels: torch.Tensor, s: int) -> torch.Tensor:
    """Unit world directions [P * s * s, 3] (float32) of the s x s stratified sub-samples of
    flat pixel indices `pixels` [P], pixel-major, then sub-row, then sub-column."""
    k = camera.intrinsics
    a = _subpixel_offsets(s)
    rows, cols = (pixels // k.width).double(), (pixels % k.width).double()
    uu = (cols[:, None, None] + a[None, None, :]).expand(-1, s, s)
    vv = (rows[:, None, None] + a[None, :, None]).expand(-1, s, s)
    ray = pixel_to_camera_ray(uu, vv, k.fx, k.fy, k.cx, k.cy) @ camera.c2w[:3, :3].T
    return (ray / ray.norm(dim=-1, keepdim=True)).float().reshape(-1, 3)


def envmap_lamp_pixels(
    ctx: ShadingContext, probe: torch.Tensor, height: int, trace_fn
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """[(flat pixel indices, mean radiance [P, 3])] for env-map pixels near lit lamps."""
    axis, alpha = _lamp_cones(ctx, probe)
    if len(axis) == 0:
        return []
    width = 2 * height
    pix_angle = math.pi / height
    centres = equirect_directions(height).reshape(-1, 3)
    near = ((centres @ axis.T) >= torch.cos((alpha + pix_angle).clamp(max=math.pi))[None]).any(-1)
    candidates = torch.nonzero(near).squeeze(1)  # sorted
    s = SUBSAMPLES
    a = _subpixel_offsets(s)
    i, j = (candidates // width).double(), (candidates % width).double()
    theta = math.pi * (i[:, None, None] + a[None, :, None]) / height
    phi = 2 * math.pi * (j[:, None, None] + a[None, None, :]) / width - math.pi
    theta, phi = torch.broadcast_tensors(theta, phi)
    d_sub = theta_phi_to_direction(theta, phi).float().reshape(-1, 3)
    w_sub = (torch.sin(theta) * (math.pi / height / s) * (2 * math.pi / width / s)).float().reshape(-1)
    pix_sub = candidates.repeat_interleave(s * s)
    outside = ~_inside_any_cone(d_sub, axis, alpha)
    d_cone, w_cone = _cone_rays(axis, alpha)
    row, col = direction_to_equirect_pixel(d_cone, height)
    r_idx = row.round().long().clamp(0, height - 1)
    c_idx = col.round().long() % width
    pix_cone = r_idx * width + c_idx
    return [
        _weighted_pixels(
            ctx,
            probe,
            trace_fn,
            torch.cat([pix_sub[outside], pix_cone]),
            torch.cat([d_sub[outside], d_cone]),
            torch.cat([w_sub[outside], w_cone]),
            candidates,
        )
    ]


def frame_lamp_pixels(ctx: ShadingContext, camera: Camera, trace_fn) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """[(flat pixel indices, mean radiance [P, 3])] for image pixels near lit lamps."""
    origin = camera.position.to(torch.float32)
    axis, alpha = _lamp_cones(ctx, origin)
    if len(axis) == 0:
        return []
    k = camera.intrinsics
    rot = camera.c2w[:3, :3].to(torch.float32)
    forward = -rot[:, 2]
    f = max(k.fx, k.fy)
    boxes = []
    for ax, al in zip(axis, alpha):
        cos_c = float(ax @ forward)
        if cos_c <= math.sin(float(al)) + 1e-6:
            continue  # behind the camera or crossing its plane
        u, v, _ = camera.project((origin + ax).double()[None])
        reach = f * math.tan(float(al)) / cos_c**2 * 1.5 + 1.5
        boxes.append((float(u[0]), float(v[0]), reach))
    mask = torch.zeros(k.height, k.width, dtype=torch.bool)
    for u, v, reach in boxes:
        c0, c1 = max(0, math.floor(u - reach)), min(k.width, math.ceil(u + reach))
        r0, r1 = max(0, math.floor(v - reach)), min(k.height, math.ceil(v + reach))
        if c0 < c1 and r0 < r1:
            mask[r0:r1, c0:c1] = True
    candidates = torch.nonzero(mask.reshape(-1)).squeeze(1)
    if len(candidates) == 0:
        return []
    s = SUBSAMPLES
    d_sub = subpixel_rays(camera, candidates, s)
    w_sub = torch.full((len(d_sub),), 1.0 / (s * s))
    pix_sub = candidates.repeat_interleave(s * s)
    outside = ~_inside_any_cone(d_sub, axis, alpha)
    d_cone, omega = _cone_rays(axis, alpha)
    cos_t = d_cone @ forward
    front = cos_t > 1e-6
    d_cone, omega, cos_t = d_cone[front], omega[front], cos_t[front]
    u, v, _ = camera.project((origin + d_cone).double())
    inside = (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    d_cone, omega, cos_t, u, v = d_cone[inside], omega[inside], cos_t[inside], u[inside], v[inside]
    pix_cone = v.floor().long() * k.width + u.floor().long()
    w_cone = omega * (k.fx * k.fy) / cos_t**3  # solid angle -> image area (pixels^2)
    return [
        _weighted_pixels(
            ctx,
            origin,
            trace_fn,
            torch.cat([pix_sub[outside], pix_cone]),
            torch.cat([d_sub[outside], d_cone]),
            torch.cat([w_sub[outside], w_cone]),
            candidates,
        )
    ]
