"""The room as a box: ray casting, the documented assumption, and fitting from sparse points.

A `RoomBox` is an oriented box: `axes` [3, 3] has the box axes as COLUMNS in world
coordinates (a rotation), and `lo`, `hi` [3] bound the room along those axes (metres, box
coordinates q = axesᵀ p). Cameras sit inside it; a ray leaves the box at the nearest
positive crossing of its six faces, which gives every frame a planar depth map that is
consistent across frames (a world-fixed room, not one that turns with the camera).

`fit_room(points, camera_centres)` replaces the fixed assumption when tracking produced
3D points: RANSAC planes in the cloud, grouped into a Manhattan frame (up = the plane normal
nearest to the first camera's +y), faces at the outermost supported plane along each axis,
else at a high percentile of the points, else (a side nothing was seen on) at the assumed
room's distance from the cameras. `fit.sources` says which rule placed each face.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from core.camera import Camera
from core.conventions import pixel_to_camera_ray

# The documented assumption (docs/engine.md): a 5 x 3 x 4 m room in front of a camera at its
# origin looking along -z, 1.5 m above the floor; the wall behind it 1 m away (only cameras
# that turn ever see it).
ASSUMED_HALF_WIDTH_M = 2.5
ASSUMED_FLOOR_BELOW_M = 1.5
ASSUMED_CEILING_ABOVE_M = 1.5
ASSUMED_BACK_M = 4.0
ASSUMED_BEHIND_M = 1.0

FACE_NAMES = (("-x", "+x"), ("floor", "ceiling"), ("-z", "+z"))


class RoomFitError(ValueError):
    """Too few points to fit a room."""


@dataclass(frozen=True)
class RoomBox:
    axes: torch.Tensor  # [3, 3] float64, columns = box axes in world coordinates
    lo: torch.Tensor  # [3] float64, box coordinates
    hi: torch.Tensor  # [3] float64

    def __post_init__(self):
        for name in ("axes", "lo", "hi"):
            object.__setattr__(self, name, torch.as_tensor(getattr(self, name), dtype=torch.float64))
        if not bool((self.hi > self.lo).all()):
            raise RoomFitError(
                f"room box needs lo < hi on every axis, got lo={self.lo.tolist()}, hi={self.hi.tolist()}"
            )

    @property
    def size(self) -> torch.Tensor:
        return self.hi - self.lo

    def contains(self, p: torch.Tensor, margin: float = 0.0) -> torch.Tensor:
        q = p.to(torch.float64) @ self.axes
        return ((q > self.lo + margin) & (q < self.hi - margin)).all(-1)

    def exit_distance(self, origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """Ray parameter s at which o + s d leaves the box ([...]; NaN if o is outside).
        `d` need not be unit: s is in units of |d| (planar depth for z = -1 camera rays)."""
        o = origins.to(torch.float64) @ self.axes
        d = directions.to(torch.float64) @ self.axes
        bound = torch.where(d > 0, self.hi, self.lo)
        safe = torch.where(d.abs() > 1e-15, d, torch.full_like(d, 1e-15))
        s = torch.where(d.abs() > 1e-15, (bound - o) / safe, torch.full_like(d, math.inf)).amin(-1)
        inside = ((o >= self.lo) & (o <= self.hi)).all(-1)
        return torch.where(inside & (s >= 0), s, torch.full_like(s, math.nan))

    def depth(self, camera: Camera) -> torch.Tensor:
        """Planar depth [H, W] float32 of the box seen by `camera` (NaN if it is outside)."""
        k = camera.intrinsics
        v, u = torch.meshgrid(torch.arange(k.height, dtype=torch.float64) + 0.5,
                              torch.arange(k.width, dtype=torch.float64) + 0.5, indexing="ij")
        ray = pixel_to_camera_ray(u, v, k.fx, k.fy, k.cx, k.cy)  # z = -1: s is planar depth
        world = ray @ camera.c2w[:3, :3].T
        return self.exit_distance(camera.position.expand_as(world), world).float()

    def as_dict(self) -> dict:
        return {"axes": self.axes.tolist(), "lo": self.lo.tolist(), "hi": self.hi.tolist(),
                "size_m": [round(float(x), 4) for x in self.size]}


def box_depth(box: RoomBox, cameras: list[Camera]) -> torch.Tensor:
    """Planar depth [K, H, W] float32 of `box` seen by each camera; pixels of a camera outside
    the box take the median of the valid ones (2 m when none is valid)."""
    depth = torch.stack([box.depth(c) for c in cameras])
    if not bool(torch.isfinite(depth).all()):
        fill = depth[torch.isfinite(depth)].median() if torch.isfinite(depth).any() else torch.tensor(2.0)
        depth = torch.where(torch.isfinite(depth), depth, fill)
    return depth


def room_from_dict(doc: dict) -> RoomBox:
    """The box a capture's metadata recorded (`RoomBox.as_dict`, or a RoomFit's with the box's
    keys): raises RoomFitError on a malformed one."""
    try:
        return RoomBox(torch.tensor(doc["axes"], dtype=torch.float64).reshape(3, 3),
                       torch.tensor(doc["lo"], dtype=torch.float64).reshape(3),
                       torch.tensor(doc["hi"], dtype=torch.float64).reshape(3))
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise RoomFitError(f"not a room box record: {exc}") from None


def assumed_room(scale: float = 1.0, first_camera: torch.Tensor | None = None) -> RoomBox:
    """The documented box room around the first camera, `scale` x metres. Without
    `first_camera` (c2w) that camera is the world origin looking along -z (world = its frame,
    as when poses were tracked); with it, the box stands upright in the world (+y up, as given
    poses' worlds are) in front of that camera's heading."""
    lo = torch.tensor([-ASSUMED_HALF_WIDTH_M, -ASSUMED_FLOOR_BELOW_M, -ASSUMED_BACK_M], dtype=torch.float64) * scale
    hi = torch.tensor([ASSUMED_HALF_WIDTH_M, ASSUMED_CEILING_ABOVE_M, ASSUMED_BEHIND_M], dtype=torch.float64) * scale
    if first_camera is None:
        return RoomBox(torch.eye(3, dtype=torch.float64), lo, hi)
    c2w = torch.as_tensor(first_camera, dtype=torch.float64)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    back = c2w[:3, 2] - (c2w[:3, 2] @ up) * up  # the camera's +z (behind it), made horizontal
    if float(back.norm()) < 1e-6:  # looking straight up or down: its y axis sets the heading
        back = -(c2w[:3, 1] - (c2w[:3, 1] @ up) * up) * torch.sign(c2w[1, 2])
    back = back / back.norm()
    axes = torch.stack((torch.linalg.cross(up, back), up, back), dim=1)
    offset = c2w[:3, 3] @ axes
    return RoomBox(axes, lo + offset, hi + offset)


# ---------------------------------------------------------------------------------------
# Fitting
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Plane:
    normal: np.ndarray  # unit [3]
    offset: float  # n . p = offset
    inliers: int


@dataclass
class RoomFit:
    box: RoomBox
    planes: list[Plane]
    sources: dict[str, str] = field(default_factory=dict)  # face name -> "plane" | "points" | "assumed"
    floor_found: bool = False

    def as_dict(self) -> dict:
        return {**self.box.as_dict(), "faces": dict(self.sources), "planes": len(self.planes),
                "floor_found": self.floor_found}


def _fit_plane(pts: np.ndarray) -> tuple[np.ndarray, float]:
    c = pts.mean(0)
    n = np.linalg.svd(pts - c, full_matrices=False)[2][-1]
    return n, float(n @ c)


def ransac_planes(points: np.ndarray, threshold: float, min_inliers: int, max_planes: int = 6,
                  iterations: int = 300, seed: int = 0) -> list[Plane]:
    """Sequential RANSAC: the best plane, its inliers removed, repeat while one has support."""
    rng = np.random.default_rng(seed)
    remaining = np.asarray(points, np.float64)
    planes: list[Plane] = []
    while len(planes) < max_planes and len(remaining) >= max(min_inliers, 3):
        best, best_count = None, 0
        for _ in range(iterations):
            s = remaining[rng.choice(len(remaining), 3, replace=False)]
            n = np.cross(s[1] - s[0], s[2] - s[0])
            norm = np.linalg.norm(n)
            if norm < 1e-12:
                continue
            n /= norm
            count = int((np.abs(remaining @ n - n @ s[0]) < threshold).sum())
            if count > best_count:
                best, best_count = (n, float(n @ s[0])), count
        if best is None or best_count < min_inliers:
            break
        mask = np.abs(remaining @ best[0] - best[1]) < threshold
        n, d = _fit_plane(remaining[mask])
        mask = np.abs(remaining @ n - d) < threshold
        planes.append(Plane(n, d, int(mask.sum())))
        remaining = remaining[~mask]
    return planes


def _manhattan_axes(planes: list[Plane], up_hint: np.ndarray, tol_deg: float = 15.0) -> np.ndarray:
    """Box axes [3, 3] (columns x, y=up, z) from the plane normals; the camera frame when none help."""
    cos_tol = math.cos(math.radians(tol_deg))
    up = up_hint / np.linalg.norm(up_hint)
    horizontal = [p for p in planes if abs(p.normal @ up) >= cos_tol]
    if horizontal:  # floor or ceiling: refine up with the best-supported one
        best = max(horizontal, key=lambda p: p.inliers)
        up = best.normal * np.sign(best.normal @ up)
    walls = [p for p in planes if abs(p.normal @ up) <= math.sin(math.radians(tol_deg))]
    if walls:
        wall = max(walls, key=lambda p: p.inliers).normal
    else:
        wall = np.array([0.0, 0.0, 1.0])  # the first camera's viewing axis
    w1 = wall - (wall @ up) * up
    if np.linalg.norm(w1) < 1e-6:
        w1 = np.array([0.0, 0.0, 1.0]) - up[2] * up
    w1 /= np.linalg.norm(w1)
    w2 = np.cross(up, w1)
    # box z = the horizontal axis nearest the first camera's z (so face names read naturally)
    z = w1 if abs(w1[2]) >= abs(w2[2]) else w2
    if z[2] < 0:
        z = -z
    x = np.cross(up, z)
    return np.stack((x / np.linalg.norm(x), up, z), axis=1)


def fit_room(points, camera_centres, *, scale_hint: float | None = None, percentile: float = 98.0,
             plane_threshold: float | None = None, min_points: int = 30) -> RoomFit:
    """Fit a Manhattan box to sparse points [N, 3] around cameras [C, 3] (same units).

    `scale_hint` = metres per unit of the cloud when known (for the assumed distance of a
    side nothing was seen on); by default the cloud's own scale stands in for it.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(1)]
    cams = np.asarray(camera_centres, np.float64).reshape(-1, 3)
    if len(pts) < min_points:
        raise RoomFitError(f"{len(pts)} points, need at least {min_points} to fit a room")
    extent = float(np.median(np.linalg.norm(pts - cams[0], axis=1)))
    thr = plane_threshold if plane_threshold is not None else 0.02 * extent
    planes = ransac_planes(pts, thr, min_inliers=max(10, len(pts) // 20))
    axes = _manhattan_axes(planes, np.array([0.0, 1.0, 0.0]))
    q, qc = pts @ axes, cams @ axes
    unit = scale_hint if scale_hint is not None else extent / ASSUMED_BACK_M  # cloud units per metre-ish
    default = np.array([[ASSUMED_HALF_WIDTH_M, ASSUMED_HALF_WIDTH_M], [ASSUMED_FLOOR_BELOW_M, ASSUMED_CEILING_ABOVE_M],
                        [ASSUMED_BACK_M, ASSUMED_BEHIND_M]]) * unit
    cos_tol = math.cos(math.radians(15.0))
    lo, hi, sources = np.zeros(3), np.zeros(3), {}
    floor_found = False
    for a in range(3):
        for side, sign in ((0, -1.0), (1, 1.0)):
            name = FACE_NAMES[a][side]
            cam_edge = qc[:, a].min() if sign < 0 else qc[:, a].max()
            # planes perpendicular to this axis, beyond every camera on this side
            offs = [
                p.offset * float(np.sign(p.normal @ axes[:, a]))
                for p in planes
                if abs(p.normal @ axes[:, a]) >= cos_tol
            ]
            offs = [o for o in offs if (o - cam_edge) * sign > 0]
            beyond = q[(q[:, a] - cam_edge) * sign > 0, a]
            if offs:
                value, src = (min(offs) if sign < 0 else max(offs)), "plane"
                if a == 1 and sign < 0:
                    floor_found = True
            elif len(beyond) >= max(5, len(q) // 50):
                value, src = float(np.percentile(beyond, percentile if sign > 0 else 100 - percentile)), "points"
            else:
                value, src = cam_edge + sign * default[a, side], "assumed"
            (hi if sign > 0 else lo)[a] = value
            sources[name] = src
    # cameras must be inside: push faces out by a small margin if needed
    margin = 0.05 * unit
    lo = np.minimum(lo, qc.min(0) - margin)
    hi = np.maximum(hi, qc.max(0) + margin)
    return RoomFit(
        RoomBox(torch.from_numpy(axes), torch.from_numpy(lo), torch.from_numpy(hi)), planes, sources, floor_found
    )
