"""How a chrome ball is placed, rendered, composited and unwrapped.

A chrome ball is a perfect mirror sphere (centre c, radius R, world metres) seen by a
pinhole camera (core.camera.Camera). Everything here is perspective-exact:

* Rendering casts the camera ray r (unit, world) through every pixel sample inside the
  ball's projected bounding box, intersects it with the sphere exactly, and reflects it
  about the normal n: d = r - 2 (r.n) n. d is the direction light ARRIVES FROM at the
  probe (core.conventions). Following the paper, radiance is looked up at the ball
  CENTRE for direction d (probe-centre approximation): L(c, d), not L(hit point, d).
* Several balls are rendered together; for each sample the nearest ball wins, so balls
  occlude each other correctly. Coverage is anti-aliased by supersampling.
* Unwrapping (ball image -> env map) solves the reflection law exactly for every env-map
  direction instead of DiffusionLight's orthographic approximation, which distorts the
  centre of the map.

Geometry is computed in float64 (it carries no gradient); radiance stays in the caller's
dtype so the render is differentiable w.r.t. radiance.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Union

import torch

from core.camera import Camera
from core.conventions import OPENCV_TO_OURS, equirect_directions, pixel_to_camera_ray, valid_depth_mask
from core.envmap import equirect_stencil, pad_poles

RadianceFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

# Samples per pixel side are raised for small balls so that a ball always gets roughly
# this many samples across its projected minor diameter (sub-pixel balls stay visible
# with the right total coverage); capped to bound the cost of tiny balls.
_MIN_SAMPLES_ACROSS = 8.0
_MAX_SUPERSAMPLE = 64


class BallPlacementError(ValueError):
    """A chrome ball cannot be placed or rendered (bad depth, behind the camera, ...)."""


# ---------------------------------------------------------------------------------------
# Placement
# ---------------------------------------------------------------------------------------
def _focal(camera: Camera) -> float:
    k = camera.intrinsics
    return math.sqrt(k.fx * k.fy)  # one focal length for (rarely) non-square pixels


def _to_camera(camera: Camera, points: torch.Tensor) -> torch.Tensor:
    """World points [..., 3] -> camera frame, float64, on the points' device (CUDA too)."""
    return camera.world_to_camera(points.to(torch.float64))


def _planar_depth(camera: Camera, points: torch.Tensor) -> torch.Tensor:
    return -_to_camera(camera, points)[..., 2]


def ball_radius(camera: Camera, center_world, diameter_fraction: float = 0.25) -> float:
    """World radius R that makes the ball's projected diameter `diameter_fraction * min(H, W)` px.

    A sphere of radius R whose centre has planar depth z projects to an ellipse whose
    minor semi-axis (perpendicular to the direction from the principal point) is
    b = f R / sqrt(z^2 - R^2) exactly, for any position in the frame (on the optical axis
    the ellipse is a circle of that radius). Solving b = p for p = fraction * min(H, W) / 2:

        R = z p / sqrt(f^2 + p^2),   f = sqrt(fx fy).
    """
    if not (math.isfinite(diameter_fraction) and diameter_fraction > 0):
        raise BallPlacementError(f"diameter_fraction must be finite and > 0, got {diameter_fraction}")
    center = torch.as_tensor(center_world, dtype=torch.float64).reshape(3)
    if not torch.isfinite(center).all():
        raise BallPlacementError(f"ball centre must be finite, got {center.tolist()}")
    z = float(_planar_depth(camera, center))
    if not z > 0:
        raise BallPlacementError(f"ball centre is behind the camera (planar depth {z:.4g} <= 0)")
    k = camera.intrinsics
    p = 0.5 * diameter_fraction * min(k.width, k.height)
    f = _focal(camera)
    return z * p / math.sqrt(f * f + p * p)


def place_probe(camera: Camera, pixel_uv, depth: float, diameter_fraction: float = 0.25) -> tuple[torch.Tensor, float]:
    """Centre [3] (float32, world) on the ray through continuous pixel (u, v) at planar
    `depth`, and the radius from `ball_radius`."""
    uv = torch.as_tensor(pixel_uv, dtype=torch.float64).reshape(-1)
    if uv.numel() != 2 or not torch.isfinite(uv).all():
        raise BallPlacementError(f"pixel_uv must be two finite numbers, got {pixel_uv}")
    depth_t = torch.as_tensor(float(depth), dtype=torch.float64)
    if not bool(valid_depth_mask(depth_t)):
        raise BallPlacementError(f"depth must be finite and > 0, got {float(depth)}")
    k = camera.intrinsics
    ray = pixel_to_camera_ray(uv[0], uv[1], k.fx, k.fy, k.cx, k.cy)  # z = -1: planar depth 1
    center = camera.c2w[:3, :3] @ (ray * depth_t) + camera.c2w[:3, 3]
    radius = ball_radius(camera, center, diameter_fraction)
    return center.to(torch.float32), radius


# ---------------------------------------------------------------------------------------
# Ray casting
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BallRays:
    """Pixel samples that hit a ball (after mutual occlusion), M of them."""

    pixel_index: torch.Tensor  # [M] long, flat index row * W + col
    ball_index: torch.Tensor  # [M] long
    direction: torch.Tensor  # [M, 3] float32 unit, world: direction light arrives from
    sample_weight: torch.Tensor  # [M] float32, 1 / samples per pixel of that ball
    depth: torch.Tensor  # [M] float32 planar depth of the hit point
    normal: torch.Tensor  # [M, 3] float32 unit sphere normal at the hit point
    height: int
    width: int
    num_balls: int


def _check_balls(camera: Camera, centers, radii) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """float64 centres [N, 3], radii [N], centre planar depths [N]; raises on bad balls."""
    centers = torch.as_tensor(centers).to(torch.float64)
    radii = torch.as_tensor(radii).to(device=centers.device, dtype=torch.float64).reshape(-1)
    if centers.ndim != 2 or centers.shape[1] != 3 or centers.shape[0] != radii.shape[0]:
        raise BallPlacementError(
            f"centers must be [N, 3] and radii [N], got {tuple(centers.shape)} and {tuple(radii.shape)}"
        )
    for i in range(centers.shape[0]):
        if not (torch.isfinite(centers[i]).all() and torch.isfinite(radii[i]) and radii[i] > 0):
            raise BallPlacementError(
                f"ball {i}: centre and radius must be finite with radius > 0, got {centers[i].tolist()}, "
                f"{float(radii[i])}"
            )
    z = _planar_depth(camera, centers)
    for i in range(centers.shape[0]):
        # z > R keeps the whole sphere in front of the camera plane: bounded projection
        if not z[i] > radii[i] * (1.0 + 1e-9):
            raise BallPlacementError(
                f"ball {i} is behind the camera or crosses the camera plane "
                f"(centre planar depth {float(z[i]):.4g}, radius {float(radii[i]):.4g})"
            )
    return centers, radii, z


def _projected_boxes(camera: Camera, centers: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """Exact image bounding boxes [N, 4] (u_min, u_max, v_min, v_max) of the spheres.

    The outline of a sphere is a conic whose dual is C* = K (c c^T - R^2 I) K^T
    (c in an x-right, y-down, z-forward camera frame). A vertical line u = u0, i.e.
    l = (1, 0, -u0), is tangent when l^T C* l = 0: C*22 u0^2 - 2 C*02 u0 + C*00 = 0.
    """
    k = camera.intrinsics
    c = _to_camera(camera, centers)
    c = c @ OPENCV_TO_OURS[:3, :3].to(c)  # its own inverse: ours -> OpenCV
    K = k.matrix(torch.float64).to(c.device)
    eye = torch.eye(3, dtype=c.dtype, device=c.device)
    M = c[:, :, None] * c[:, None, :] - (radii**2)[:, None, None] * eye
    Cs = K @ M @ K.T

    def roots(b, a0):
        a2 = Cs[:, 2, 2]
        half = torch.sqrt((b * b - a0 * a2).clamp_min(0.0))
        return (b - half) / a2, (b + half) / a2

    u0, u1 = roots(Cs[:, 0, 2], Cs[:, 0, 0])
    v0, v1 = roots(Cs[:, 1, 2], Cs[:, 1, 1])
    return torch.stack((u0, u1, v0, v1), dim=-1)


def _minor_diameter_px(camera: Camera, radii: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Projected minor diameter 2 f R / sqrt(z^2 - R^2) in pixels (see ball_radius)."""
    return 2.0 * _focal(camera) * radii / torch.sqrt(z * z - radii * radii)


def _ball_samples(
    box: torch.Tensor, s: int, pad: int, height: int, width: int, device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Flat pixel index, u and v of the s x s stratified samples of every pixel in a box."""
    c0 = max(int(math.floor(float(box[0]))) - pad, 0)
    c1 = min(int(math.ceil(float(box[1]))) + pad, width)
    r0 = max(int(math.floor(float(box[2]))) - pad, 0)
    r1 = min(int(math.ceil(float(box[3]))) + pad, height)
    if c1 <= c0 or r1 <= r0:
        empty = torch.zeros(0, dtype=torch.float64, device=device)
        return empty.long(), empty, empty
    offs = (torch.arange(s, dtype=torch.float64, device=device) + 0.5) / s
    rows = torch.arange(r0, r1, dtype=torch.float64, device=device)
    cols = torch.arange(c0, c1, dtype=torch.float64, device=device)
    r, c, oy, ox = torch.meshgrid(rows, cols, offs, offs, indexing="ij")
    pix = (r * width + c).reshape(-1).long()
    return pix, (c + ox).reshape(-1), (r + oy).reshape(-1)


def ball_reflection_rays(camera: Camera, centers, radii, supersample: int = 2, pad: int = 1) -> BallRays:
    """Cast pixel samples at N balls; return the samples that hit, with reflected directions.

    Only pixels inside each ball's exact projected bounding box (plus `pad`) are sampled.
    Each ball uses s x s stratified samples per pixel, s = max(supersample, enough for
    ~8 samples across the ball), so sub-pixel balls keep their area. Every sample ray is
    intersected with all balls and kept only for the nearest one (mutual occlusion).
    """
    if supersample < 1 or pad < 0:
        raise BallPlacementError(f"supersample must be >= 1 and pad >= 0, got {supersample}, {pad}")
    centers, radii, z = _check_balls(camera, centers, radii)
    k = camera.intrinsics
    H, W, N = k.height, k.width, centers.shape[0]
    device = centers.device
    if N == 0:
        e = torch.zeros(0, dtype=torch.float32, device=device)
        return BallRays(e.long(), e.long(), e.view(0, 3), e, e, e.view(0, 3), H, W, 0)
    boxes = _projected_boxes(camera, centers, radii)
    across = _minor_diameter_px(camera, radii, z)

    pix_l, u_l, v_l, ball_l, w_l = [], [], [], [], []
    for b in range(N):
        s = int(min(max(supersample, math.ceil(_MIN_SAMPLES_ACROSS / max(float(across[b]), 1e-12))), _MAX_SUPERSAMPLE))
        pix, u, v = _ball_samples(boxes[b], s, pad, H, W, device)
        pix_l.append(pix)
        u_l.append(u)
        v_l.append(v)
        ball_l.append(torch.full_like(pix, b))
        w_l.append(torch.full(pix.shape, 1.0 / (s * s), dtype=torch.float64, device=device))
    pix, u, v = torch.cat(pix_l), torch.cat(u_l), torch.cat(v_l)
    ball, weight = torch.cat(ball_l), torch.cat(w_l)

    rot = camera.c2w[:3, :3].to(device)
    origin = camera.position.to(device)
    r = pixel_to_camera_ray(u, v, k.fx, k.fy, k.cx, k.cy) @ rot.T
    r = r / r.norm(dim=-1, keepdim=True)

    # Ray-sphere against every ball. disc = R^2 - |perpendicular offset|^2 avoids the
    # cancellation of b^2 - (|oc|^2 - R^2) for distant balls.
    oc = origin - centers  # [N, 3]
    bdot = r @ oc.T  # [M, N]
    perp = oc[None, :, :] - bdot[..., None] * r[:, None, :]
    disc = radii[None, :] ** 2 - (perp * perp).sum(-1)
    hit = disc >= 0
    t_all = torch.where(hit, -bdot - torch.sqrt(disc.clamp_min(0.0)), torch.full_like(disc, math.inf))
    nearest = t_all.argmin(dim=1)
    own = t_all.gather(1, ball[:, None])[:, 0]
    keep = torch.isfinite(own) & (nearest == ball)
    pix, ball, weight, r, t = pix[keep], ball[keep], weight[keep], r[keep], own[keep]

    c = centers[ball]
    n = origin + t[:, None] * r - c
    n = n / n.norm(dim=-1, keepdim=True)
    d = r - 2.0 * (r * n).sum(-1, keepdim=True) * n
    d = d / d.norm(dim=-1, keepdim=True)
    forward = -rot[:, 2]
    depth = t * (r @ forward)
    f32 = torch.float32
    return BallRays(pix, ball, d.to(f32), weight.to(f32), depth.to(f32), n.to(f32), H, W, N)


# ---------------------------------------------------------------------------------------
# Rendering and compositing
# ---------------------------------------------------------------------------------------
@dataclass
class BallLayer:
    """Rendered balls, ready to composite over a frame."""

    radiance: torch.Tensor  # [H, W, 3] coverage-weighted (premultiplied) ball radiance
    coverage: torch.Tensor  # [N, H, W] anti-aliased coverage, occlusion applied, sum <= 1
    depth: torch.Tensor  # [H, W] planar depth of the nearest ball sample, +inf where none

    @property
    def total_coverage(self) -> torch.Tensor:
        return self.coverage.sum(0)


def _envmap_radiance(envmaps: torch.Tensor) -> RadianceFn:
    """`sample_envmap` of each sample's own ball map, as one gather (core.envmap's stencil)."""
    height = envmaps.shape[1]
    padded = pad_poles(envmaps)  # [N, texels, C]

    def fn(directions: torch.Tensor, ball_index: torch.Tensor) -> torch.Tensor:
        index, weight = equirect_stencil(directions.to(envmaps.device), height)
        texels = padded[ball_index.to(envmaps.device)[:, None], index]  # [M, 4, C]
        return (texels * weight.to(envmaps.dtype)[..., None]).sum(1)

    return fn


def render_balls(
    camera: Camera,
    centers,
    radii,
    radiance: Union[RadianceFn, torch.Tensor],
    supersample: int = 2,
    rays: BallRays | None = None,
) -> BallLayer:
    """Render N mirror balls. `radiance` is fn(directions [M, 3], ball_index [M]) -> [M, 3]
    (the field queried at each ball's centre) or env maps [N, h, 2h, 3], one per ball.
    Pass precomputed `rays` to reuse the geometry across steps."""
    if rays is None:
        rays = ball_reflection_rays(camera, centers, radii, supersample=supersample)
    if torch.is_tensor(radiance):
        if radiance.ndim != 4 or radiance.shape[0] != rays.num_balls or radiance.shape[2] != 2 * radiance.shape[1]:
            raise BallPlacementError(f"env maps must be [N={rays.num_balls}, h, 2h, 3], got {tuple(radiance.shape)}")
        fn = _envmap_radiance(radiance)
        dtype, device = radiance.dtype, radiance.device
    else:
        fn = radiance
        dtype, device = torch.float32, rays.direction.device
    H, W, N = rays.height, rays.width, rays.num_balls
    HW = H * W
    if rays.pixel_index.numel() > 0:
        L = fn(rays.direction, rays.ball_index)
        dtype, device = L.dtype, L.device
    else:
        L = torch.zeros(0, 3, dtype=dtype, device=device)
    pix = rays.pixel_index.to(device)
    w = rays.sample_weight.to(device=device, dtype=dtype)
    premult = torch.zeros(HW, 3, dtype=dtype, device=device).index_add(0, pix, L * w[:, None])
    coverage = (
        torch.zeros(N * HW, dtype=dtype, device=device)
        .index_add(0, rays.ball_index.to(device) * HW + pix, w)
        .view(N, HW)
    )
    # balls with different sample grids can overshoot 1 by a sample at shared edges
    norm = 1.0 / coverage.sum(0).clamp_min(1.0)
    depth = torch.full((HW,), math.inf, dtype=torch.float32, device=device)
    depth = depth.scatter_reduce(0, pix, rays.depth.to(device), reduce="amin")
    return BallLayer((premult * norm[:, None]).view(H, W, 3), (coverage * norm).view(N, H, W), depth.view(H, W))


def composite(frame: torch.Tensor, layer: BallLayer) -> torch.Tensor:
    """frame * (1 - sum coverage) + premultiplied ball radiance (HDR; tone map afterwards)."""
    return frame * (1.0 - layer.total_coverage)[..., None] + layer.radiance


def composite_depth(scene_depth: torch.Tensor, layer: BallLayer) -> torch.Tensor:
    """Scene depth with the balls in it (the ControlNet depth condition).

    Where a ball covers more than half a pixel, the result is the nearer of scene and ball
    depth, or the ball depth if the scene depth is invalid (non-finite or <= 0)."""
    ball = layer.depth.to(scene_depth.dtype)
    covered = layer.total_coverage.to(scene_depth.device) > 0.5
    valid = valid_depth_mask(scene_depth)
    nearer = torch.where(valid, torch.minimum(scene_depth, ball), ball)
    return torch.where(covered, nearer, scene_depth)


# ---------------------------------------------------------------------------------------
# Unwrapping: ball image -> env map
# ---------------------------------------------------------------------------------------
def _normalize(x: torch.Tensor) -> torch.Tensor:
    return x / x.norm(dim=-1, keepdim=True).clamp_min(1e-300)


def _bilinear(image: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Sample image [H, W, C] at continuous pixel coordinates (u, v) (pixel centres at +0.5)."""
    H, W = image.shape[:2]
    x, y = (u - 0.5).clamp(0, W - 1), (v - 0.5).clamp(0, H - 1)
    x0, y0 = x.floor().long().clamp(0, W - 1), y.floor().long().clamp(0, H - 1)
    x1, y1 = (x0 + 1).clamp(max=W - 1), (y0 + 1).clamp(max=H - 1)
    fx, fy = (x - x0).to(image.dtype)[..., None], (y - y0).to(image.dtype)[..., None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def unwrap_ball(
    image: torch.Tensor,
    camera: Camera,
    center,
    radius: float,
    height: int,
    iterations: int = 24,
    min_incidence_cos: float = 0.05,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Perspective-exact inverse of the render: ball image [H, W, 3] -> (env map [h, 2h, 3], valid [h, 2h]).

    For each env-map direction d we need the sphere point p = c + R n whose camera ray
    r = (p - o)/|p - o| reflects into d. The reflection law makes n bisect the direction
    to the camera v = -r and d: n = normalize(d + v). v depends on p, so we iterate
    n <- normalize(d + v(c + R n)) from the orthographic guess v = normalize(o - c). The
    map contracts with factor about (R/|o - c|) / (2 cos i) (i = incidence angle), so it
    converges to machine precision in a few iterations except at grazing incidence.

    `valid` is False where the ball does not show d: back-facing or grazing solutions
    with cos(incidence) < `min_incidence_cos` (the cone of directions behind the ball, and
    the rim ring where one pixel spans tens of degrees of the map), unconverged solutions, hit points outside
    the frame, and hit points whose bilinear footprint is not fully covered by the ball
    (so no background pixel leaks in).
    """
    k = camera.intrinsics
    if tuple(image.shape[:2]) != (k.height, k.width):
        raise BallPlacementError(f"image is {tuple(image.shape[:2])}, camera expects {(k.height, k.width)}")
    centers, radii, _ = _check_balls(camera, torch.as_tensor(center).reshape(1, 3), [float(radius)])
    c, R = centers[0], radii[0]
    device = c.device
    o = camera.position.to(device)
    d = equirect_directions(height, dtype=torch.float64, device=device)
    v = _normalize(o - c).expand_as(d)
    for _ in range(iterations):
        n = _normalize(d + v)
        p = c + R * n
        v = _normalize(o - p)
    n = _normalize(d + v)
    p = c + R * n
    v = _normalize(o - p)
    r = -v
    reflected = r - 2.0 * (r * n).sum(-1, keepdim=True) * n
    converged = (reflected * d).sum(-1) > 1.0 - 1e-9
    facing = (n * v).sum(-1) > min_incidence_cos

    u_px, v_px, _ = camera.project(p)
    u_px, v_px = torch.nan_to_num(u_px), torch.nan_to_num(v_px)
    inside = (u_px >= 0.5) & (u_px <= k.width - 0.5) & (v_px >= 0.5) & (v_px <= k.height - 0.5)

    rays = ball_reflection_rays(camera, centers, radii)
    coverage = torch.zeros(k.height * k.width, dtype=torch.float64, device=device)
    coverage = coverage.index_add(0, rays.pixel_index, rays.sample_weight.to(torch.float64))
    full = (coverage > 1.0 - 1e-6).view(k.height, k.width)
    x0 = (u_px - 0.5).floor().long().clamp(0, k.width - 1)
    y0 = (v_px - 0.5).floor().long().clamp(0, k.height - 1)
    x1, y1 = (x0 + 1).clamp(max=k.width - 1), (y0 + 1).clamp(max=k.height - 1)
    taps = full[y0, x0] & full[y0, x1] & full[y1, x0] & full[y1, x1]

    valid = converged & facing & inside & taps
    env = _bilinear(image, u_px, v_px)
    env = torch.where(valid[..., None], env, torch.zeros_like(env))
    return env, valid
