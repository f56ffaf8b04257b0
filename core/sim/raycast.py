"""Vectorised ray casting against every primitive of a small scene at once.

Primitives: the room (interior of a union of overlapping boxes, hit from inside), solid
furniture boxes (hit from outside), one-sided emitter rectangles, lamp spheres and,
for the training export, mirror spheres. Rays are processed as [N] batches against all
M primitives of a kind ([N, M] tensors); the scenes have tens of primitives.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from core.sim.spec import SceneSpec
from core.sim.state import LightState

EPS_T = 1e-4  # minimum hit distance (metres): rays start on surfaces
INSIDE_TOL = 1e-5  # a point this far inside a room box counts as inside it
TINY = 1e-12

# Hit kinds
MISS, ROOM, FURNITURE, PANEL, LAMP, MIRROR = 0, 1, 2, 3, 4, 5


@dataclass(frozen=True)
class SceneGeometry:
    """The static geometry of a scene, as float32 tensors."""

    room_lo: torch.Tensor  # [R, 3]
    room_hi: torch.Tensor  # [R, 3]
    room_face_albedo: torch.Tensor  # [6, 3] faces -x, +x, -y (floor), +y (ceiling), -z, +z
    surface_emission: torch.Tensor  # [3] self-emission of room and furniture surfaces
    box_lo: torch.Tensor  # [F, 3]
    box_hi: torch.Tensor  # [F, 3]
    box_albedo: torch.Tensor  # [F, 3]

    @classmethod
    def from_spec(cls, spec: SceneSpec) -> "SceneGeometry":
        f32 = torch.float32
        a = spec.room.albedo
        return cls(
            room_lo=torch.tensor([b.lo for b in spec.room.boxes], dtype=f32),
            room_hi=torch.tensor([b.hi for b in spec.room.boxes], dtype=f32),
            room_face_albedo=torch.tensor([a.walls, a.walls, a.floor, a.ceiling, a.walls, a.walls], dtype=f32),
            surface_emission=torch.tensor(spec.room.surface_emission, dtype=f32),
            box_lo=torch.tensor([f.box.lo for f in spec.furniture], dtype=f32).reshape(-1, 3),
            box_hi=torch.tensor([f.box.hi for f in spec.furniture], dtype=f32).reshape(-1, 3),
            box_albedo=torch.tensor([f.albedo for f in spec.furniture], dtype=f32).reshape(-1, 3),
        )

    def inside_room(self, p: torch.Tensor, margin: float = INSIDE_TOL) -> torch.Tensor:
        """[N] True where p [N, 3] is inside the room union (by at least `margin`)."""
        inside = ((p[:, None] > self.room_lo + margin) & (p[:, None] < self.room_hi - margin)).all(-1)
        return inside.any(-1)

    def inside_furniture(self, p: torch.Tensor, margin: float = 0.0) -> torch.Tensor:
        """[N] True where p is inside (or within `margin` of) a furniture box."""
        if len(self.box_lo) == 0:
            return torch.zeros(len(p), dtype=torch.bool)
        return ((p[:, None] > self.box_lo - margin) & (p[:, None] < self.box_hi + margin)).all(-1).any(-1)

    def distance_to_furniture(self, p: torch.Tensor) -> torch.Tensor:
        """[N] Euclidean distance from p to the nearest furniture box (0 inside); inf without furniture."""
        if len(self.box_lo) == 0:
            return torch.full((len(p),), float("inf"))
        q = torch.maximum(self.box_lo - p[:, None], p[:, None] - self.box_hi).clamp_min(0.0)
        return q.norm(dim=-1).min(-1).values

    def distance_to_room_walls(self, p: torch.Tensor) -> torch.Tensor:
        """[N] lower bound of the distance from an inside point to the room boundary
        (exact for one box; for a union, the largest per-box clearance of the boxes holding p)."""
        clear = torch.minimum(p[:, None] - self.room_lo, self.room_hi - p[:, None]).min(-1).values  # [N, R]
        return clear.max(-1).values


@dataclass
class Hit:
    t: torch.Tensor  # [N] distance along the unit ray, inf on a miss
    kind: torch.Tensor  # [N] long, one of MISS..MIRROR
    index: torch.Tensor  # [N] long, primitive index within its kind (room: face index 0..5)
    normal: torch.Tensor  # [N, 3] surface normal facing the ray's origin side

    def point(self, o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        t = torch.where(torch.isfinite(self.t), self.t, torch.zeros_like(self.t))
        return o + t[:, None] * d


def _safe_inv(d: torch.Tensor) -> torch.Tensor:
    # keeps slab tests finite for axis-parallel rays (0 * inf would be NaN)
    d = torch.where(d.abs() < TINY, torch.full_like(d, TINY), d)
    return 1.0 / d


def _slabs(o, inv, lo, hi):
    """[N, M, 3] per-axis entry and exit distances of rays against boxes."""
    t1 = (lo[None] - o[:, None]) * inv[:, None]
    t2 = (hi[None] - o[:, None]) * inv[:, None]
    return torch.minimum(t1, t2), torch.maximum(t1, t2)


def _axis_normal(axis: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Normal along `axis` pointing against the ray direction d."""
    n = torch.zeros_like(d)
    comp = d.gather(1, axis[:, None]).squeeze(1)
    n.scatter_(1, axis[:, None], torch.where(comp > 0, -1.0, 1.0)[:, None].to(d.dtype))
    return n


def room_exit(geom: SceneGeometry, o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Distance and axis at which rays starting inside the room union leave it.

    For a union, a ray leaving one box may still be inside another: advance to the farthest
    exit among the boxes that contain the current point until no box contains it (at most
    R rounds). Rays starting outside the room get t = inf.
    """
    _, tmax = _slabs(o, _safe_inv(d), geom.room_lo, geom.room_hi)
    t_far, ax_far = tmax.min(-1)  # [N, R]
    t = torch.zeros(len(o), dtype=o.dtype)
    axis = torch.zeros(len(o), dtype=torch.long)
    started = geom.inside_room(o, margin=-INSIDE_TOL)
    for _ in range(len(geom.room_lo)):
        p = o + t[:, None] * d
        inside = ((p[:, None] > geom.room_lo + INSIDE_TOL) & (p[:, None] < geom.room_hi - INSIDE_TOL)).all(-1)
        if _ == 0:
            inside = inside | ((p[:, None] > geom.room_lo - INSIDE_TOL) & (p[:, None] < geom.room_hi + INSIDE_TOL)).all(-1)
        cand = torch.where(inside, t_far, torch.full_like(t_far, -1.0))
        best, which = cand.max(-1)
        advance = best > t
        if not advance.any():
            break
        t = torch.where(advance, best, t)
        axis = torch.where(advance, ax_far.gather(1, which[:, None]).squeeze(1), axis)
    t = torch.where(started & (t > 0), t, torch.full_like(t, float("inf")))
    return t, axis


def _furniture(geom, o, inv):
    if len(geom.box_lo) == 0:
        n = len(o)
        return torch.full((n,), float("inf")), torch.zeros(n, dtype=torch.long), torch.zeros(n, dtype=torch.long)
    tmin, tmax = _slabs(o, inv, geom.box_lo, geom.box_hi)
    t_near, ax_near = tmin.max(-1)
    t_far = tmax.min(-1).values
    ok = (t_near <= t_far) & (t_near > EPS_T)
    t_near = torch.where(ok, t_near, torch.full_like(t_near, float("inf")))
    t, idx = t_near.min(-1)
    return t, idx, ax_near.gather(1, idx[:, None]).squeeze(1)


def _rects(lights: LightState, o, d):
    n = len(o)
    if len(lights.rect_center) == 0:
        return torch.full((n,), float("inf")), torch.zeros(n, dtype=torch.long)
    ax = lights.rect_axis
    c = lights.rect_center
    o_ax, d_ax = o[:, ax], d[:, ax]  # [N, E]
    d_ax_safe = torch.where(d_ax.abs() < TINY, torch.full_like(d_ax, TINY), d_ax)
    c_ax = c.gather(1, ax[:, None]).squeeze(1)  # [E] plane offsets
    t = (c_ax[None] - o_ax) / d_ax_safe
    p = o[:, None] + t[..., None] * d[:, None]
    within = ((p - c[None]).abs() <= lights.rect_half[None] + 1e-4).all(-1)
    front = d_ax * lights.rect_sign[None] < 0  # travelling against the emitting side
    ok = within & front & (t > EPS_T)
    t = torch.where(ok, t, torch.full_like(t, float("inf")))
    return t.min(-1)


def sphere_hits(center: torch.Tensor, radius: torch.Tensor, o: torch.Tensor, d: torch.Tensor):
    """Nearest hit distance [N] and index [N] of rays against spheres hit from outside."""
    n = len(o)
    if len(center) == 0:
        return torch.full((n,), float("inf")), torch.zeros(n, dtype=torch.long)
    oc = center[None] - o[:, None]  # [N, S, 3]
    b = (oc * d[:, None]).sum(-1)
    # distance^2 from the centre to the ray line, computed stably (no b^2 - |oc|^2 cancellation)
    perp = oc - b[..., None] * d[:, None]
    disc = radius[None] ** 2 - (perp * perp).sum(-1)
    t = b - torch.sqrt(disc.clamp_min(0.0))
    ok = (disc >= 0) & (t > EPS_T)
    t = torch.where(ok, t, torch.full_like(t, float("inf")))
    return t.min(-1)


def cast(geom: SceneGeometry, lights: LightState, o: torch.Tensor, d: torch.Tensor, mirrors=None) -> Hit:
    """First hit of rays o [N, 3] (or [3]), unit d [N, 3] against the whole scene.

    `mirrors` = (centers [K, 3], radii [K]) adds mirror spheres (training export)."""
    o = o.expand_as(d) if o.dim() == 1 else o
    inv = _safe_inv(d)
    n = len(d)
    t_room, ax_room = room_exit(geom, o, d)
    t_box, i_box, ax_box = _furniture(geom, o, inv)
    t_rect, i_rect = _rects(lights, o, d)
    t_lamp, i_lamp = sphere_hits(lights.lamp_center, lights.lamp_radius, o, d)
    cands = [t_room, t_box, t_rect, t_lamp]
    if mirrors is not None:
        t_mir, i_mir = sphere_hits(mirrors[0], mirrors[1], o, d)
        cands.append(t_mir)
    t_all = torch.stack(cands, -1)
    t, which = t_all.min(-1)
    kind = torch.where(torch.isfinite(t), which + 1, torch.full_like(which, MISS))
    room_face = ax_room * 2 + (d.gather(1, ax_room[:, None]).squeeze(1) > 0).long()
    index = torch.zeros(n, dtype=torch.long)
    index = torch.where(kind == ROOM, room_face, index)
    index = torch.where(kind == FURNITURE, i_box, index)
    index = torch.where(kind == PANEL, i_rect, index)
    index = torch.where(kind == LAMP, i_lamp, index)
    normal = torch.zeros_like(d)
    normal = torch.where((kind == ROOM)[:, None], _axis_normal(ax_room, d), normal)
    normal = torch.where((kind == FURNITURE)[:, None], _axis_normal(ax_box, d), normal)
    if len(lights.rect_center):
        normal = torch.where((kind == PANEL)[:, None], lights.rect_normal[i_rect], normal)
    p = o + torch.where(torch.isfinite(t), t, torch.zeros_like(t))[:, None] * d
    if len(lights.lamp_center):
        sn = p - lights.lamp_center[i_lamp]
        normal = torch.where((kind == LAMP)[:, None], sn / sn.norm(dim=-1, keepdim=True).clamp_min(TINY), normal)
    if mirrors is not None:
        index = torch.where(kind == MIRROR, i_mir, index)
        sn = p - mirrors[0][i_mir] if len(mirrors[0]) else torch.zeros_like(p)
        normal = torch.where((kind == MIRROR)[:, None], sn / sn.norm(dim=-1, keepdim=True).clamp_min(TINY), normal)
    return Hit(t=t, kind=kind, index=index, normal=normal)


def occluded(geom: SceneGeometry, o: torch.Tensor, d: torch.Tensor, t_max: torch.Tensor) -> torch.Tensor:
    """[N] True where a segment o + s d, s in (EPS_T, t_max), is blocked by furniture or
    (for a non-convex room) by the room's walls. Emitters do not cast shadows."""
    blocked = torch.zeros(len(d), dtype=torch.bool)
    if len(geom.box_lo):
        t_box = _furniture(geom, o, _safe_inv(d))[0]
        blocked |= t_box < t_max - EPS_T
    if len(geom.room_lo) > 1:  # a single box is convex: a segment between inside points stays inside
        t_room = room_exit(geom, o, d)[0]
        blocked |= t_room < t_max - EPS_T
    return blocked
