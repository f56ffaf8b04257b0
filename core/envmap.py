"""Equirectangular environment maps: solid angles, sampling, resizing, rotation, integrals.

An env map is a tensor [H, 2H, 3] (float32 by default) in the layout of core.conventions:
pixel centre (i, j) has theta = pi (i + 1/2) / H from +y and phi = 2 pi (j + 1/2) / W - pi,
and holds the radiance arriving FROM direction d. Every function here is device-agnostic
and differentiable with respect to the map (and, for `sample_envmap`, the direction).
"""
from __future__ import annotations

import functools
import math
from typing import Callable, NamedTuple

import torch

from core.conventions import (
    direction_to_equirect_pixel,
    equirect_directions,
    equirect_pixel_centres,
    equirect_width,
    theta_phi_to_direction,
)


class EnvmapError(ValueError):
    """An env map or an argument to an env map function is malformed."""


def check_envmap(envmap: torch.Tensor, name: str = "envmap") -> int:
    """Validate shape [H, 2H, 3] and floating dtype; return H."""
    if not isinstance(envmap, torch.Tensor):
        raise EnvmapError(f"{name} must be a torch.Tensor, got {type(envmap).__name__}")
    if envmap.ndim != 3 or envmap.shape[-1] != 3 or envmap.shape[1] != 2 * envmap.shape[0] or envmap.shape[0] < 1:
        raise EnvmapError(f"{name} must have shape [H, 2H, 3] with H >= 1, got {tuple(envmap.shape)}")
    if not envmap.is_floating_point():
        raise EnvmapError(f"{name} must be floating point, got {envmap.dtype}")
    return int(envmap.shape[0])


def _check_height(height: int, name: str = "height") -> int:
    if isinstance(height, bool) or int(height) != height or int(height) < 1:
        raise EnvmapError(f"{name} must be a positive integer, got {height!r}")
    return int(height)


# ---------------------------------------------------------------------------------------
# Solid angles and integrals
# ---------------------------------------------------------------------------------------
def _row_cos_edges(height: int) -> torch.Tensor:
    """cos(theta) at the H + 1 row edges, float64 (exact at the poles)."""
    edges = torch.arange(height + 1, dtype=torch.float64) * (math.pi / height)
    c = torch.cos(edges)
    c[0], c[-1] = 1.0, -1.0
    return c


def solid_angles(height: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """Exact solid angle [H, 2H] of every pixel: (2 pi / W)(cos theta_top - cos theta_bottom).

    Computed in float64, so the sum is 4 pi to float64 precision before the cast.
    """
    height = _check_height(height)
    width = equirect_width(height)
    c = _row_cos_edges(height)
    per_row = (2.0 * math.pi / width) * (c[:-1] - c[1:])
    return per_row[:, None].expand(height, width).to(device=device, dtype=dtype).contiguous()


def integrate(envmap: torch.Tensor) -> torch.Tensor:
    """Integral of radiance over the sphere, [3] (float64 accumulation, returned in envmap dtype)."""
    h = check_envmap(envmap)
    w = solid_angles(h, device=envmap.device, dtype=torch.float64)
    return (envmap.to(torch.float64) * w[..., None]).sum(dim=(0, 1)).to(envmap.dtype)


def irradiance(envmap: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """Irradiance E(n) = integral of L(d) max(0, n.d) dd for unit normals [..., 3] -> [..., 3].

    A brute-force quadrature over the pixel centres (exact solid angles); use
    core.sh.sh_irradiance for the band-limited fast version.
    """
    h = check_envmap(envmap)
    dirs = equirect_directions(h, device=envmap.device, dtype=torch.float64).reshape(-1, 3)
    weighted = (envmap.to(torch.float64) * solid_angles(h, device=envmap.device, dtype=torch.float64)[..., None])
    n = normal.to(device=envmap.device, dtype=torch.float64).reshape(-1, 3)
    flat = weighted.reshape(-1, 3)
    block = max(1, (1 << 24) // dirs.shape[0])  # bound the [block, HW] cosine matrix to ~128 MB
    e = torch.cat([(chunk @ dirs.T).clamp_min(0.0) @ flat for chunk in n.split(block)]) if n.shape[0] else n
    return e.reshape(*normal.shape[:-1], 3).to(envmap.dtype)


# ---------------------------------------------------------------------------------------
# Construction
# ---------------------------------------------------------------------------------------
def envmap_from_function(
    fn: Callable[[torch.Tensor], torch.Tensor], height: int, device=None, dtype=torch.float32
) -> torch.Tensor:
    """Evaluate `fn(d [H, 2H, 3]) -> [H, 2H, 3] or [H, 2H]` at the pixel centres.

    A scalar result is broadcast to the three channels (grey radiance).
    """
    height = _check_height(height)
    d = equirect_directions(height, device=device, dtype=dtype)
    out = torch.as_tensor(fn(d), device=device)
    if out.shape == d.shape[:-1]:
        out = out[..., None].expand(*d.shape[:-1], 3)
    if out.shape != d.shape:
        raise EnvmapError(f"fn must return shape {tuple(d.shape)} or {tuple(d.shape[:-1])}, got {tuple(out.shape)}")
    return out.to(dtype).contiguous()


def mirror_envmap(envmap: torch.Tensor, axis: str) -> torch.Tensor:
    """Env map seen through a mirror of one world axis: result(d) = envmap(d with `axis` negated).

    Exact column permutations (no resampling). Used to convert to left-handed or
    x-flipped consumers (Unity: axis="z"; three.js CubeTexture: axis="x"; see docs/conventions.md).
    x -> phi becomes -phi; z -> phi becomes pi - phi; y -> rows flip.
    """
    check_envmap(envmap)
    w = envmap.shape[1]
    if axis == "y":
        return envmap.flip(0)
    if axis == "x":
        # column j has phi_j = 2 pi (j + 1/2)/W - pi; -phi_j is column W - 1 - j
        return envmap.flip(1)
    if axis == "z":
        # pi - phi_j is column (W/2 - 1 - j) mod W: flip then roll by half a turn
        return torch.roll(envmap.flip(1), shifts=w // 2, dims=1)
    raise EnvmapError(f"axis must be 'x', 'y' or 'z', got {axis!r}")


# ---------------------------------------------------------------------------------------
# Sampling
# ---------------------------------------------------------------------------------------
class EquirectTaps(NamedTuple):
    """Bilinear taps of directions on the pole-padded layout of `pad_poles`.

    upper_row: padded row above the direction (0 = north pole row, 1..H = map rows,
    H + 1 = south pole row; the lower tap is upper_row + 1), long; row_weight: weight of the
    lower row; col0 / col1: left / right column (wrapped at the seam), long; col_weight:
    weight of col1. Between the first (last) row centre and the pole the value blends
    towards the pole row, so sampling is continuous everywhere, poles included.
    """

    upper_row: torch.Tensor
    row_weight: torch.Tensor
    col0: torch.Tensor
    col1: torch.Tensor
    col_weight: torch.Tensor


def equirect_taps(d: torch.Tensor, height: int) -> EquirectTaps:
    """The taps of directions d [..., 3] (finite; need not be unit) on an h x 2h map."""
    return pixel_taps(*direction_to_equirect_pixel(d, int(height)), height)


def pixel_taps(row: torch.Tensor, col: torch.Tensor, height: int) -> EquirectTaps:
    """The taps of continuous pixel coordinates (conventions.direction_to_equirect_pixel) on an h x 2h map."""
    h, w = int(height), equirect_width(height)
    row = row.clamp(-0.5, h - 0.5)
    in_top, in_bottom = row < 0.0, row > h - 1
    r0 = torch.floor(row).clamp(0, max(h - 2, 0))
    t_row = row - r0
    upper = r0 + 1  # padded index of the upper row
    # polar caps: between the pole (at row -1/2 / H - 1/2) and the nearest row centre
    upper = torch.where(in_top, torch.zeros_like(upper), upper)
    t_row = torch.where(in_top, (row + 0.5) / 0.5, t_row)
    upper = torch.where(in_bottom, torch.full_like(upper, h), upper)
    t_row = torch.where(in_bottom, (row - (h - 1)) / 0.5, t_row)
    c0f = torch.floor(col)
    c0 = c0f.long().remainder(w)
    return EquirectTaps(upper.long(), t_row, c0, (c0 + 1).remainder(w), col - c0f)


def pad_poles(maps: torch.Tensor) -> torch.Tensor:
    """[M, h, w, C] -> [M, (h + 2) * w, C] with a pole row (the mean of the first / last row)
    above and below: the layout `equirect_taps` and `equirect_stencil` index."""
    top = maps[:, :1].mean(dim=2, keepdim=True).expand(-1, 1, maps.shape[2], -1)
    bottom = maps[:, -1:].mean(dim=2, keepdim=True).expand(-1, 1, maps.shape[2], -1)
    return torch.cat((top, maps, bottom), dim=1).reshape(maps.shape[0], -1, maps.shape[-1])


def equirect_stencil(d: torch.Tensor, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """`sample_envmap` as a gather: (texel index into the padded layout [N, 4] long, weight
    [N, 4]) for unit directions d [N, 3], so one call can read a different map per row."""
    return taps_stencil(equirect_taps(d, height), height, d.dtype)


def taps_stencil(taps: EquirectTaps, height: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """`equirect_stencil` of taps already found (`pixel_taps`)."""
    w = equirect_width(height)
    upper, t_row, c0, c1, t_col = taps
    index = torch.stack((upper * w + c0, upper * w + c1, (upper + 1) * w + c0, (upper + 1) * w + c1), dim=-1)
    weight = torch.stack(
        ((1 - t_row) * (1 - t_col), (1 - t_row) * t_col, t_row * (1 - t_col), t_row * t_col), dim=-1
    )
    return index, weight.to(dtype)


def sample_envmap(envmap: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Bilinear radiance lookup for directions d [..., 3] (need not be unit) -> [..., 3].

    Columns wrap around the phi = +-pi seam. Rows are interpolated between pixel-centre
    rows; between the first (last) row centre and the pole, the value blends linearly
    towards the mean of that row, which is the only pole value that does not depend on
    phi. So sampling is continuous everywhere, including exactly at the poles.
    A zero direction is treated as +y (finite). Non-finite directions give NaN.
    """
    h = check_envmap(envmap)
    w = envmap.shape[1]
    if d.shape[-1] != 3:
        raise EnvmapError(f"directions must have shape [..., 3], got {tuple(d.shape)}")
    finite = torch.isfinite(d).all(dim=-1)
    d_safe = torch.where(finite[..., None], d, torch.zeros_like(d))
    lo_i, t_row, c0, c1, t_col = equirect_taps(d_safe.to(torch.promote_types(d.dtype, torch.float32)), h)
    hi_i = lo_i + 1
    padded = pad_poles(envmap[None])[0]
    t_row = t_row[..., None].to(envmap.dtype)
    t_col = t_col[..., None].to(envmap.dtype)

    def at(r, c):
        return padded[r * w + c]

    upper = at(lo_i, c0) * (1 - t_col) + at(lo_i, c1) * t_col
    lower = at(hi_i, c0) * (1 - t_col) + at(hi_i, c1) * t_col
    out = upper * (1 - t_row) + lower * t_row
    return torch.where(finite[..., None], out, torch.full_like(out, float("nan")))


# ---------------------------------------------------------------------------------------
# Resizing and rotation
# ---------------------------------------------------------------------------------------
def _overlap_matrix(out_edges: torch.Tensor, in_edges: torch.Tensor) -> torch.Tensor:
    """Overlap lengths [n_out, n_in] between two partitions of the same interval (increasing edges)."""
    lo = torch.maximum(out_edges[:-1, None], in_edges[None, :-1])
    hi = torch.minimum(out_edges[1:, None], in_edges[None, 1:])
    return (hi - lo).clamp_min(0.0)


def _area_downsample(envmap: torch.Tensor, height: int) -> torch.Tensor:
    """Each output pixel = solid-angle-weighted mean of the input area it covers.

    Separable in (1 - cos theta) and phi, so the integral of L dw is preserved exactly
    (up to float64 rounding) for any ratio of heights, not only integer ones.
    """
    h_in, w_in = envmap.shape[0], envmap.shape[1]
    w_out = equirect_width(height)
    if h_in % height == 0:  # integer factor: sum k x k blocks of L dw (same result, O(pixels))
        k = h_in // height
        omega_in = solid_angles(h_in, device=envmap.device, dtype=torch.float64)
        weighted = (envmap.to(torch.float64) * omega_in[..., None]).reshape(height, k, w_out, k, -1).sum(dim=(1, 3))
        omega_out = solid_angles(height, device=envmap.device, dtype=torch.float64)
        return (weighted / omega_out[..., None]).to(envmap.dtype)
    rows = _overlap_matrix(1.0 - _row_cos_edges(height), 1.0 - _row_cos_edges(h_in))  # cos-measure overlaps
    rows = rows / rows.sum(dim=1, keepdim=True)
    cols = _overlap_matrix(
        torch.linspace(0.0, 1.0, w_out + 1, dtype=torch.float64),
        torch.linspace(0.0, 1.0, w_in + 1, dtype=torch.float64),
    )
    cols = cols / cols.sum(dim=1, keepdim=True)
    rows, cols = rows.to(envmap.device), cols.to(envmap.device)
    x = envmap.to(torch.float64)
    out = torch.einsum("oi,ijc,pj->opc", rows, x, cols)
    return out.to(envmap.dtype)


def resize_envmap(envmap: torch.Tensor, height: int) -> torch.Tensor:
    """Resize to [height, 2 height, 3].

    Downsampling is area-correct (preserves the integral of L dw and never skips a small
    bright source); upsampling is bilinear via `sample_envmap` at the new pixel centres.
    """
    h = check_envmap(envmap)
    height = _check_height(height)
    if height == h:
        return envmap.clone()
    if height < h:
        return _area_downsample(envmap, height)
    d = equirect_directions(height, device=envmap.device, dtype=torch.float64)
    return sample_envmap(envmap, d).to(envmap.dtype)


@functools.lru_cache(maxsize=32)  # tiny (O(height) each); heights are client-chosen, so bounded
def separable_taps(h: int, height: int) -> EquirectTaps:
    """Taps that sample an h-row map (pole rows padded, `pad_poles`) bilinearly at the pixel
    centres of a `height`-row map: `sample_envmap`'s rule, which on equirect grids is
    separable (a row's taps depend only on its polar angle, a column's only on its azimuth).
    (upper_row, row_weight) are per output row [H], (col0, col1, col_weight) per column [W]."""
    theta, phi = equirect_pixel_centres(height, dtype=torch.float64)  # [H, 1], [1, W]
    r = equirect_taps(theta_phi_to_direction(theta[:, 0], phi[0, :1].expand(height)), h)  # one column
    c = equirect_taps(theta_phi_to_direction(theta[:1, 0].expand(phi.shape[1]), phi[0]), h)  # one row
    return EquirectTaps(r.upper_row, r.row_weight.float(), c.col0, c.col1, c.col_weight.float())


def upsample_envmaps(maps: torch.Tensor, height: int) -> torch.Tensor:
    """[P, h, 2h, C] -> [P, height, 2 height, C] (height >= h), bilinear exactly as
    `resize_envmap` upsamples, as two 2-tap blends (rows, then columns) instead of a 4-tap
    gather per output pixel: ~10x faster on batches of maps."""
    p, h = maps.shape[0], maps.shape[1]
    if height == h:
        return maps
    upper, t_row, c0, c1, t_col = separable_taps(h, int(height))
    padded = pad_poles(maps).reshape(p, h + 2, -1, maps.shape[-1]).to(torch.float32)
    tall = torch.lerp(padded.index_select(1, upper), padded.index_select(1, upper + 1), t_row[None, :, None, None])
    return torch.lerp(tall.index_select(2, c0), tall.index_select(2, c1), t_col[None, None, :, None])


def rotate_envmap(envmap: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Rotate the lighting by the 3x3 world rotation R: result(d) = envmap(R^T d).

    So a light that arrived from direction s arrives from R s afterwards (the scene is
    rotated by R, the probe's frame stays). To express a map given in a probe/camera frame
    in the world frame, pass that frame's camera-to-world rotation.
    Resampling is bilinear, so a rotation that is not a multiple of the pixel grid blurs by
    up to one pixel.
    """
    h = check_envmap(envmap)
    R = torch.as_tensor(R, dtype=torch.float64, device=envmap.device)
    if R.shape != (3, 3):
        raise EnvmapError(f"R must be 3x3, got {tuple(R.shape)}")
    if not torch.isfinite(R).all() or not torch.allclose(
        R @ R.T, torch.eye(3, dtype=torch.float64, device=R.device), atol=1e-4
    ):
        raise EnvmapError("R must be a finite orthonormal 3x3 matrix")
    d = equirect_directions(h, device=envmap.device, dtype=torch.float64)
    src = d @ R  # row-vector form of R^T d
    return sample_envmap(envmap, src).to(envmap.dtype)


# ---------------------------------------------------------------------------------------
# Splatting points
# ---------------------------------------------------------------------------------------
SPLAT_Z_TOLERANCE = 0.1  # relative: points within 10 % of the nearest distance share a pixel
SPLAT_MIN_DISTANCE = 1e-3  # metres; points closer than this to a centre are skipped


def splat_points(points: torch.Tensor, colors: torch.Tensor, centers: torch.Tensor,
                 height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Z-buffered splat of coloured points into equirect maps seen from `centers` [N, 3].

    points [P, 3] (finite), colors [P, 3] or [N, P, 3] (per centre). Each point lands in the
    pixel of its direction from the centre; per pixel, the points within SPLAT_Z_TOLERANCE of
    the nearest one's distance are averaged (a z-buffer by distance: a wall behind a table does
    not bleed through it). Returns radiance [N, h, 2h, C] (0 where nothing landed) and the
    seen mask [N, h, 2h]. A centre's maps do not depend on the other centres."""
    h, w = int(height), equirect_width(height)
    n = centers.shape[0]
    rel = points[None, :, :] - centers[:, None, :].to(points.dtype)  # [N, P, 3]
    dist = rel.norm(dim=-1)
    col = colors if colors.dim() == 3 else colors[None].expand(n, -1, -1)
    row, colf = direction_to_equirect_pixel(rel, h)
    r = row.round().long().clamp(0, h - 1)
    c = colf.round().long().remainder(w)
    # Points a pixel does not take go to one spare bin past the maps (cut off at the end)
    # rather than being selected out: the boolean selection took about half the splat's time.
    bins = n * h * w
    key = torch.arange(n, device=points.device)[:, None] * (h * w) + r * w + c
    key = torch.where(dist > SPLAT_MIN_DISTANCE, key, bins).reshape(-1)
    dist, col = dist.reshape(-1), col.reshape(-1, col.shape[-1])
    nearest = torch.full((bins + 1,), float("inf"), dtype=dist.dtype, device=points.device).scatter_reduce(
        0, key, dist, reduce="amin")
    key = torch.where(dist <= nearest[key] * (1.0 + SPLAT_Z_TOLERANCE), key, bins)
    acc = torch.zeros(bins + 1, col.shape[-1], dtype=col.dtype, device=points.device).index_add(0, key, col)[:bins]
    cnt = torch.zeros(bins + 1, dtype=col.dtype, device=points.device).index_add(
        0, key, torch.ones_like(dist, dtype=col.dtype)
    )[:bins]
    env = (acc / cnt.clamp_min(1.0)[:, None]).reshape(n, h, w, -1)
    return env, (cnt > 0).reshape(n, h, w)


VOXEL_GROWTH = 1.25  # voxel_merge: the voxel grows by this factor until the points fit


def voxel_cells(points: torch.Tensor, max_points: int) -> tuple[torch.Tensor, int]:
    """(cell index [N] of each point, number of cells): the voxel grid of `voxel_merge`, the cell
    the smallest (x VOXEL_GROWTH steps from 1/1024 of the extent) that leaves at most `max_points`
    cells occupied."""
    lo = points.amin(0)
    extent = float((points.amax(0) - lo).amax().clamp_min(1e-6))
    size = extent / 1024
    while True:
        cells = torch.floor((points - lo) / size).long()
        n = int(cells.amax()) + 1
        key = (cells[:, 0] * n + cells[:, 1]) * n + cells[:, 2]
        _, inverse = torch.unique(key, return_inverse=True)
        count = int(inverse.amax()) + 1
        if count <= max_points:
            return inverse, count
        size *= VOXEL_GROWTH


def voxel_merge(points: torch.Tensor, colors: torch.Tensor, max_points: int) -> tuple[torch.Tensor, torch.Tensor]:
    """At most `max_points` points: the mean position and colour of the points in each cell of a
    voxel grid (`voxel_cells`). Points that already fit are returned as they are."""
    if points.shape[0] <= max_points:
        return points, colors
    inverse, count = voxel_cells(points, max_points)
    weight = torch.zeros(count, dtype=points.dtype).index_add(0, inverse, torch.ones_like(inverse, dtype=points.dtype))
    merged_points = torch.zeros(count, 3, dtype=points.dtype).index_add(0, inverse, points) / weight[:, None]
    merged_colors = torch.zeros(count, *colors.shape[1:], dtype=colors.dtype).index_add(0, inverse, colors)
    return merged_points, merged_colors / weight.reshape(-1, *([1] * (colors.dim() - 1)))
