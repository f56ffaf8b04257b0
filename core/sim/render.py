"""Ground-truth rendering: camera frames, env maps at any (x, t), and a radiance function.

Frames, env maps and `radiance` all go through the same `trace` (ray cast + shading), so
the env map at a probe is exactly what the scene's geometry and emitters say.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from core.camera import Camera
from core.conventions import equirect_directions, frame_time
from core.sim.cost import CostReport
from core.sim.lamp_pixels import envmap_lamp_pixels, frame_lamp_pixels
from core.sim.raycast import MIRROR, MISS, Hit, SceneGeometry, cast
from core.sim.shading import ShadingContext, shade
from core.sim.spec import SceneSpec, SceneSpecError
from core.sim.state import camera_at, frame_of_time, light_state

MAX_MIRROR_BOUNCES = 4


class ProbeError(SceneSpecError):
    """A probe position is outside the room or inside furniture."""


@dataclass
class FrameRender:
    hdr: torch.Tensor  # [H, W, 3] float32 linear radiance
    depth: torch.Tensor  # [H, W] float32 planar metres, NaN where no surface
    camera: Camera
    cost: CostReport = field(default_factory=CostReport)


def geometry(spec: SceneSpec) -> SceneGeometry:
    return SceneGeometry.from_spec(spec)  # a few tiny tensors: cheaper to rebuild than to cache


def context(spec: SceneSpec, frame: float, cost: CostReport | None = None) -> ShadingContext:
    cost = cost if cost is not None else CostReport()
    with cost.track("schedules"):
        lights = light_state(spec, frame)
    return ShadingContext(spec=spec, geom=geometry(spec), lights=lights, cost=cost)


@dataclass
class TraceResult:
    radiance: torch.Tensor  # [N, 3]
    t: torch.Tensor  # [N] distance to the first hit (mirror surface included), inf on a miss
    first_kind: torch.Tensor  # [N] kind of the first hit


def trace(ctx: ShadingContext, o: torch.Tensor, d: torch.Tensor, mirrors=None) -> TraceResult:
    """Radiance arriving at o [N, 3] or [3] from unit directions d [N, 3], in chunks.

    `mirrors` = (centers [K, 3], radii [K]) adds perfect mirror spheres; rays reflect off
    them up to MAX_MIRROR_BOUNCES times (then see black)."""
    chunk = ctx.spec.quality.chunk_rays
    o = o.expand_as(d) if o.dim() == 1 else o
    parts = [_trace_chunk(ctx, o[i : i + chunk], d[i : i + chunk], mirrors) for i in range(0, len(d), chunk)]
    if not parts:
        return TraceResult(torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, dtype=torch.long))
    return TraceResult(*(torch.cat(x) for x in zip(*((p.radiance, p.t, p.first_kind) for p in parts))))


def _trace_chunk(ctx, o, d, mirrors) -> TraceResult:
    with ctx.cost.track("primary"):
        hit = cast(ctx.geom, ctx.lights, o, d, mirrors)
        ctx.cost.count("primary", len(d))
    first_t, first_kind = hit.t.clone(), hit.kind.clone()
    out = torch.zeros(len(d), 3)
    live = torch.arange(len(d))
    for bounce in range(MAX_MIRROR_BOUNCES + 1):
        on_mirror = hit.kind == MIRROR
        done = ~on_mirror
        if done.any():
            out[live[done]] = shade(ctx, o[done], d[done], _subset(hit, done))
        if not on_mirror.any() or bounce == MAX_MIRROR_BOUNCES:
            break
        p = hit.point(o, d)[on_mirror]
        n = hit.normal[on_mirror]
        dm = d[on_mirror]
        r = dm - 2.0 * (dm * n).sum(-1, keepdim=True) * n
        o, d, live = p + 1e-4 * n, r / r.norm(dim=-1, keepdim=True), live[on_mirror]
        with ctx.cost.track("primary"):
            hit = cast(ctx.geom, ctx.lights, o, d, mirrors)
            ctx.cost.count("primary", len(d))
    return TraceResult(out, first_t, first_kind)


def _subset(hit: Hit, mask: torch.Tensor) -> Hit:
    return Hit(t=hit.t[mask], kind=hit.kind[mask], index=hit.index[mask], normal=hit.normal[mask])


def render_frame(scene: SceneSpec, frame_index: int, mirrors=None) -> FrameRender:
    """HDR radiance and planar depth of frame `frame_index` (optionally with mirror spheres)."""
    if not 0 <= frame_index < scene.frames:
        raise SceneSpecError(f"frame_index {frame_index} outside 0..{scene.frames - 1}")
    cost = CostReport()
    with cost.track("camera_motion"):
        camera = camera_at(scene, frame_index)
    ctx = context(scene, frame_index, cost)
    return render_view(ctx, camera, mirrors)


def render_view(ctx: ShadingContext, camera: Camera, mirrors=None) -> FrameRender:
    k = camera.intrinsics
    origin, dirs = camera.pixel_rays()
    d = dirs.reshape(-1, 3)
    res = trace(ctx, origin, d, mirrors)
    if mirrors is None:  # mirror renders (training export) keep one sample per pixel
        with ctx.cost.track("lamp_pixels"):
            for index, value in frame_lamp_pixels(ctx, camera, trace):
                res.radiance[index] = value
    forward = -camera.c2w[:3, 2].to(torch.float32)
    depth = res.t * (d @ forward)
    depth = torch.where(torch.isfinite(res.t) & (res.first_kind != MISS), depth, torch.full_like(depth, float("nan")))
    return FrameRender(
        hdr=res.radiance.reshape(k.height, k.width, 3),
        depth=depth.reshape(k.height, k.width),
        camera=camera,
        cost=ctx.cost,
    )


def check_probe(scene: SceneSpec, x) -> torch.Tensor:
    """Probe position as a float32 [3] tensor; raises ProbeError outside free space."""
    p = torch.as_tensor(x, dtype=torch.float32).reshape(-1, 3)
    if not torch.isfinite(p).all():
        raise ProbeError(f"probe position must be finite, got {p.tolist()}")
    geom = geometry(scene)
    if not bool(geom.inside_room(p).all()):
        raise ProbeError(f"probe x={p.tolist()} is outside the room")
    if bool(geom.inside_furniture(p).any()):
        raise ProbeError(f"probe x={p.tolist()} is inside furniture")
    return p


def render_envmap(scene: SceneSpec, x, t: float, height: int = 64, cost: CostReport | None = None) -> torch.Tensor:
    """Ground-truth HDR env map [height, 2*height, 3] at world point x and time t (seconds),
    in core.conventions' equirect layout (d = direction light arrives from)."""
    if height < 1:
        raise SceneSpecError(f"envmap height must be >= 1, got {height}")
    p = check_probe(scene, x)[0]
    ctx = context(scene, frame_of_time(scene, t), cost)
    d = equirect_directions(height).reshape(-1, 3)
    env = trace(ctx, p, d).radiance
    with ctx.cost.track("lamp_pixels"):
        for index, value in envmap_lamp_pixels(ctx, p, height, trace):
            env[index] = value
    return env.reshape(height, 2 * height, 3)


def radiance(
    scene: SceneSpec, x: torch.Tensor, t: torch.Tensor, d: torch.Tensor, cost: CostReport | None = None
) -> torch.Tensor:
    """Ground-truth radiance [B, 3] arriving at x [B, 3] (metres) at time t [B] (seconds)
    from directions d [B, 3] (need not be unit). Points outside free space, zero or
    non-finite directions and non-finite times get 0."""
    x = torch.as_tensor(x, dtype=torch.float32).reshape(-1, 3)
    d = torch.as_tensor(d, dtype=torch.float32).reshape(-1, 3)
    t = torch.as_tensor(t, dtype=torch.float64).reshape(-1).expand(len(x))
    norm = d.norm(dim=-1, keepdim=True)
    d = d / norm.clamp_min(1e-12)
    out = torch.zeros(len(x), 3)
    geom = geometry(scene)
    free = (
        geom.inside_room(x)
        & ~geom.inside_furniture(x)
        & torch.isfinite(norm[:, 0])
        & (norm[:, 0] > 1e-12)
        & torch.isfinite(t)
    )
    for tv in torch.unique(t):
        sel = (t == tv) & free
        if sel.any():
            ctx = context(scene, frame_of_time(scene, float(tv)), cost)
            out[sel] = trace(ctx, x[sel], d[sel]).radiance
    return out


def frame_times(scene: SceneSpec) -> list[float]:
    return [frame_time(i, scene.fps) for i in range(scene.frames)]


def radiance_fn(scene: SceneSpec):
    """A closure fn(x[B,3], t[B], d[B,3]) -> [B,3] (the form KnownRadiancePrior takes)."""

    def fn(x, t, d):
        return radiance(scene, x, t, d)

    return fn


__all__ = [
    "FrameRender",
    "ProbeError",
    "check_probe",
    "frame_times",
    "geometry",
    "radiance",
    "radiance_fn",
    "render_envmap",
    "render_frame",
    "render_view",
    "trace",
]
