"""Lambertian shading of ray hits: emission, direct light (+ shadows), one indirect bounce.

Outgoing radiance at a surface hit p with albedo a:

    L(p) = Le_surf(p) + a / pi * (E_direct(p) + E_indirect(p))

* E_direct sums over emitter primitives. Area emitters (ceiling panels, windows) are
  sampled with a fixed stratified k x k grid (scene seed), Cranley-Patterson rotated per
  shading point by a hash of its position (deterministic, no banding), with inverse-square
  falloff and both cosine terms. Lamps are uniform spheres of radiance Le and radius R:
  E = pi R^2 Le cos(theta) / D^2 (exact for an unoccluded sphere above the horizon), with
  one visibility ray to the centre.
* E_indirect (effect `indirect`) is ONE bounce gathered with K cosine-weighted rays:
  E_ind = pi / K * sum_k L1(hit_k), where L1 = Le_surf + a / pi * E_direct at the gather hit.
  Gather rays that hit an emitter primitive contribute 0 (it is already in E_direct).
  So a closed room of uniform surface emission Le and albedo a gives exactly Le (1 + a).
* Surface self-emission (room.surface_emission, for furnace tests) lights other surfaces
  only through the indirect gather.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from core.sim.cost import CostReport
from core.sim.raycast import FURNITURE, LAMP, PANEL, ROOM, SceneGeometry, cast, occluded
from core.sim.spec import SceneSpec
from core.sim.state import LightState

SURFACE_OFFSET = 5e-4  # metres: shading points are pushed off their surface along the normal


@dataclass
class ShadingContext:
    spec: SceneSpec
    geom: SceneGeometry
    lights: LightState
    cost: CostReport

    def has(self, effect: str) -> bool:
        return self.spec.has(effect)


def stratified_square(count: int, seed: int) -> torch.Tensor:
    """[k*k, 2] jittered stratified points in [0, 1)^2 with k = floor(sqrt(count)), from `seed`."""
    k = max(1, int(math.isqrt(count)))
    g = torch.Generator().manual_seed(int(seed) & 0x7FFFFFFF)
    jitter = torch.rand(k, k, 2, generator=g, dtype=torch.float64)
    i, j = torch.meshgrid(torch.arange(k, dtype=torch.float64), torch.arange(k, dtype=torch.float64), indexing="ij")
    pts = torch.stack(((i + jitter[..., 0]) / k, (j + jitter[..., 1]) / k), -1)
    return pts.reshape(-1, 2).to(torch.float32)


def position_hash(p: torch.Tensor) -> torch.Tensor:
    """[N, 2] pseudo-random offsets in [0, 1) that depend only on the position p [N, 3]."""
    p64 = p.to(torch.float64)
    a = torch.tensor([[12.9898, 78.233, 37.719], [39.3468, 11.135, 83.155]], dtype=torch.float64)
    h = torch.sin(p64 @ a.T) * 43758.5453
    return (h - torch.floor(h)).to(torch.float32)


def rotated_samples(base: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Cranley-Patterson rotation of a stratified set per point: [N, S, 2] in [0, 1)."""
    u = base[None] + position_hash(p)[:, None]
    return u - torch.floor(u)


def tangent_frame(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Orthonormal tangents of unit normals [N, 3] (Duff et al. 2017, branchless)."""
    x, y, z = n.unbind(-1)
    s = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (s + z)
    b = x * y * a
    t1 = torch.stack((1.0 + s * x * x * a, s * b, -s * x), -1)
    t2 = torch.stack((b, s + y * y * a, -y), -1)
    return t1, t2


def surface_albedo(geom: SceneGeometry, kind: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    albedo = torch.zeros(len(kind), 3)
    room = kind == ROOM
    albedo[room] = geom.room_face_albedo[index[room]]
    furn = kind == FURNITURE
    if furn.any():
        albedo[furn] = geom.box_albedo[index[furn]]
    return albedo


def _shadowed(
    ctx: ShadingContext, p: torch.Tensor, w: torch.Tensor, dist: torch.Tensor, active: torch.Tensor
) -> torch.Tensor:
    """[N, S] visibility (1 visible) of segments p -> p + dist * w where `active`."""
    vis = torch.ones_like(dist)
    if not ctx.has("shadows") or not active.any():
        return vis
    with ctx.cost.track("shadows"):
        po = p[:, None].expand_as(w)[active]
        blocked = occluded(ctx.geom, po, w[active], dist[active])
        ctx.cost.count("shadows", int(active.sum()))
        vis[active] = (~blocked).to(vis.dtype)
    return vis


def direct_irradiance(ctx: ShadingContext, p: torch.Tensor, n: torch.Tensor, area_samples: int) -> torch.Tensor:
    """Irradiance [N, 3] at points p (already offset) with unit normals n, from all emitters."""
    lights = ctx.lights
    e_total = torch.zeros(len(p), 3)
    base = stratified_square(area_samples, ctx.spec.seed * 7919 + 17)
    uv = rotated_samples(base, p) * 2.0 - 1.0  # [N, S, 2] in [-1, 1)
    s = uv.shape[1]
    for i in range(len(lights.rect_center)):
        radiance = lights.rect_radiance[i]
        if not bool((radiance > 0).any()):
            continue
        axis = int(lights.rect_axis[i])
        u_ax, v_ax = [a for a in range(3) if a != axis]
        half = lights.rect_half[i]
        q = lights.rect_center[i].expand(len(p), s, 3).clone()
        q[..., u_ax] += uv[..., 0] * half[u_ax]
        q[..., v_ax] += uv[..., 1] * half[v_ax]
        w = q - p[:, None]
        r2 = (w * w).sum(-1).clamp_min(1e-8)
        r = r2.sqrt()
        w = w / r[..., None]
        cos_p = (w * n[:, None]).sum(-1).clamp_min(0.0)
        cos_e = (-w[..., axis] * lights.rect_sign[i]).clamp_min(0.0)
        area = 4.0 * float(half[u_ax] * half[v_ax])
        g = cos_p * cos_e / r2 * (area / s)
        g = g * _shadowed(ctx, p, w, r, g > 0)
        e_total += g.sum(1)[:, None] * radiance
    for i in range(len(lights.lamp_center)):
        radiance = lights.lamp_radiance[i]
        if not bool((radiance > 0).any()):
            continue
        radius = lights.lamp_radius[i]
        w = lights.lamp_center[i][None] - p
        dist = w.norm(dim=-1).clamp_min(float(radius))
        w = w / dist[:, None]
        cos_p = (w * n).sum(-1).clamp_min(0.0)
        g = math.pi * radius**2 * cos_p / dist**2
        vis = _shadowed(ctx, p, w[:, None], (dist - radius)[:, None], (g > 0)[:, None])[:, 0]
        e_total += (g * vis)[:, None] * radiance
    return e_total


def cosine_directions(n: torch.Tensor, p: torch.Tensor, count: int, seed: int) -> torch.Tensor:
    """[N, K, 3] cosine-weighted unit directions about normals n (stratified, rotated per point)."""
    u = rotated_samples(stratified_square(count, seed * 104729 + 3), p)
    r = u[..., 0].sqrt()
    phi = 2.0 * math.pi * u[..., 1]
    local_z = (1.0 - u[..., 0]).clamp_min(0.0).sqrt()
    t1, t2 = tangent_frame(n)
    d = (
        (r * phi.cos())[..., None] * t1[:, None]
        + (r * phi.sin())[..., None] * t2[:, None]
        + local_z[..., None] * n[:, None]
    )
    return d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def indirect_irradiance(ctx: ShadingContext, p: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """One-bounce irradiance [N, 3]: pi * mean radiance (direct-lit only) seen by gather rays."""
    q = ctx.spec.quality
    dirs = cosine_directions(n, p, q.indirect_samples, ctx.spec.seed)
    k = dirs.shape[1]
    o = p[:, None].expand_as(dirs).reshape(-1, 3)
    d = dirs.reshape(-1, 3)
    hit = cast(ctx.geom, ctx.lights, o, d)
    ctx.cost.count("indirect", len(d))
    surf = (hit.kind == ROOM) | (hit.kind == FURNITURE)
    l1 = torch.zeros(len(d), 3)
    if surf.any():
        kind, index, normal = hit.kind[surf], hit.index[surf], hit.normal[surf]
        ps = o[surf] + hit.t[surf, None] * d[surf] + SURFACE_OFFSET * normal
        if ctx.has("emission"):
            l1[surf] += ctx.geom.surface_emission
        if ctx.has("direct"):
            e = direct_irradiance(ctx, ps, normal, q.indirect_area_samples)
            l1[surf] += surface_albedo(ctx.geom, kind, index) / math.pi * e
    return math.pi * l1.reshape(-1, k, 3).mean(1)


def shade(ctx: ShadingContext, o: torch.Tensor, d: torch.Tensor, hit) -> torch.Tensor:
    """Radiance [N, 3] arriving at the ray origins along -d, i.e. leaving the hits towards o."""
    n = len(d)
    out = torch.zeros(n, 3)
    if ctx.has("emission"):
        with ctx.cost.track("emission"):
            lights = ctx.lights
            panel = hit.kind == PANEL
            if panel.any():
                out[panel] = lights.rect_radiance[hit.index[panel]]
            lamp = hit.kind == LAMP
            if lamp.any():
                out[lamp] = lights.lamp_radiance[hit.index[lamp]]
    surf = (hit.kind == ROOM) | (hit.kind == FURNITURE)
    if not surf.any():
        return out
    if ctx.has("emission"):
        out[surf] += ctx.geom.surface_emission
    if not (ctx.has("direct") or ctx.has("indirect")):
        return out
    normal = hit.normal[surf]
    p = o.expand_as(d)[surf] + hit.t[surf, None] * d[surf] + SURFACE_OFFSET * normal
    albedo = surface_albedo(ctx.geom, hit.kind[surf], hit.index[surf])
    e = torch.zeros(len(p), 3)
    if ctx.has("direct"):
        with ctx.cost.track("direct"):
            e += direct_irradiance(ctx, p, normal, ctx.spec.quality.area_samples)
    if ctx.has("indirect"):
        with ctx.cost.track("indirect"):
            e += indirect_irradiance(ctx, p, normal)
    out[surf] += albedo / math.pi * e
    return out
