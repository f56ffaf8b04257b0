"""Surfaces a moving camera saw while the light changed: each point's radiance at every time.

A moving camera sees a surface only at the times it looks at it. Held at those readings, a wall
seen before a lamp switched on would stay dark after it; given the room's average change, a
wall beside the lamp would brighten as little as the far corner. Light is additive and a
switch's share of a surface's light falls off smoothly across the room (distance to the source,
the walls' orientation), so each surface cell v gets the model

    log Y_v(t) = a_v + b_v G(t)

G: the room's course (log luminance per frame, 0 at the first), from every cell seen at two
times (log Y_vf = a_v + G_f, solved by alternating medians, robust to the cells a switch
changes far more than the rest: a stitcher's exposure balance, here the light's);
b_v: how strongly the cell follows the room (1: as the room, > 1 near the source that changed,
< 1 far from it), fitted where the cell was seen at times the room's light differed, shrunk
towards what the nearest such cells say in proportion to how much the cell's own readings
span (a cell seen at one moment takes its neighbours' b; one seen across the whole change
takes its own); a_v: the cell's level given its b. The cell keeps its mean chromaticity.
Where no cell was seen across a change, b = 1: the room's course, the best that can be said.
"""
from __future__ import annotations

import torch

from core.envmap import voxel_cells
from core.exposure import luminance

LOG_FLOOR = 1e-6  # luminance floor (linear) before logs: a black reading is very dark, not -inf
NEIGHBOURS = 8  # cells whose b a poorly seen cell borrows
MEDIAN_ROUNDS = 6  # alternations of the room course's fixed-effects fit
FACTOR_ROUNDS = 3  # alternations of the course and the cells' sensitivities
MIN_SENSITIVITY = 0.2  # cells that barely follow the room do not tell its course (a division by b)
CHUNK = 2048  # cells per distance block (bounds the [chunk, cells] distance matrix)


def surface_course(points: torch.Tensor, colors: torch.Tensor, view: torch.Tensor, view_times: torch.Tensor,
                   knot_times: torch.Tensor, max_points: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(cell positions [M, 3], radiance at the knots [M, K, 3]) from readings of points [N, 3]
    with linear colours [N, 3] in views `view` [N] (long, 0..V-1) taken at `view_times` [V]
    seconds, at `knot_times` [K] seconds; M <= max_points cells (core.envmap.voxel_cells)."""
    points, colors = points.double(), colors.double().clamp_min(0.0)
    cell, M = voxel_cells(points, max_points)
    V = int(view_times.shape[0])
    pos = torch.zeros(M, 3, dtype=torch.float64).index_add(0, cell, points)
    count = torch.zeros(M, dtype=torch.float64).index_add(0, cell, torch.ones_like(cell, dtype=torch.float64))
    pos = pos / count[:, None]
    lum = luminance(colors).clamp_min(LOG_FLOOR)
    chroma = torch.zeros(M, 3, dtype=torch.float64).index_add(0, cell, colors)
    chroma = chroma / luminance(chroma).clamp_min(LOG_FLOOR)[:, None]
    # one reading per (cell, view): the mean luminance of the cell's points in that view
    key = cell * V + view
    pair, inverse = torch.unique(key, return_inverse=True)
    n = torch.zeros(pair.shape[0], dtype=torch.float64).index_add(0, inverse, torch.ones_like(lum))
    y = torch.log(torch.zeros(pair.shape[0], dtype=torch.float64).index_add(0, inverse, lum) / n)
    c, f = pair // V, pair % V
    course = _room_course(y, c, f, M, V)
    b, a = _sensitivities(y, c, course[f], pos, M)
    for _ in range(FACTOR_ROUNDS):  # the course as the cells' own sensitivities say, then theirs again
        course = _refined_course(y, c, f, a, b, course)
        b, a = _sensitivities(y, c, course[f], pos, M)
    g = _at_times(course, view_times.double(), knot_times.double())  # [K]
    lum_k = torch.exp(a[:, None] + b[:, None] * g[None])  # [M, K]
    return pos.float(), (chroma[:, None, :] * lum_k[..., None]).float()


def _room_course(y: torch.Tensor, c: torch.Tensor, f: torch.Tensor, M: int, V: int) -> torch.Tensor:
    """G [V] (G_0 = 0) of log Y_cf = a_c + G_f by alternating medians; views no cell ties to the
    others take their neighbours' values in time order (the nearest earlier, else later)."""
    G = torch.zeros(V, dtype=torch.float64)
    a = torch.zeros(M, dtype=torch.float64)
    for _ in range(MEDIAN_ROUNDS):
        a = _group_median(y - G[f], c, M)
        G = _group_median(y - a[c], f, V)
        G = G - G[0] if torch.isfinite(G[0]) else G - G[torch.isfinite(G)][0]
    # a view sharing no cell with another has no course of its own: its G only offsets its own cells
    shared = torch.zeros(M, dtype=torch.float64).index_add(0, c, torch.ones_like(y)) > 1
    tied = torch.zeros(V, dtype=torch.bool)
    tied[f[shared[c]]] = True
    G = torch.where(tied & torch.isfinite(G), G, torch.nan)
    if not bool(torch.isfinite(G).any()):
        return torch.zeros(V, dtype=torch.float64)
    last = None
    for v in range(V):  # hold forwards, then backwards for a leading gap
        if torch.isfinite(G[v]):
            last = G[v]
        elif last is not None:
            G[v] = last
    first = G[torch.isfinite(G)][0]
    return torch.where(torch.isfinite(G), G, first)


def _refined_course(y, c, f, a, b, course: torch.Tensor) -> torch.Tensor:
    """G [V] given the cells' a and b: per view, the median of (y - a) / b over its cells seen in
    other views too (a view that shows only the walls beside a lamp reads the room's course
    through their larger b, so the course does not wander with what the camera looks at), anchored
    at G_0 = 0; views without such cells keep theirs."""
    V = course.shape[0]
    M = a.shape[0]
    seen = torch.zeros(M, dtype=torch.float64).index_add(0, c, torch.ones_like(y))
    use = (seen[c] > 1) & (b[c] >= MIN_SENSITIVITY)
    if not bool(use.any()):
        return course
    G = _group_median((y[use] - a[c[use]]) / b[c[use]], f[use], V)
    G = torch.where(torch.isfinite(G), G, course)
    return G - G[0]


def _group_median(values: torch.Tensor, group: torch.Tensor, count: int) -> torch.Tensor:
    """Median of `values` per group index (NaN for an empty group)."""
    order = torch.argsort(values, stable=True)
    order = order[torch.argsort(group[order], stable=True)]  # by group, values sorted within
    g, v = group[order], values[order]
    sizes = torch.zeros(count, dtype=torch.long).index_add(0, g, torch.ones_like(g))
    starts = torch.cumsum(sizes, 0) - sizes
    mid = starts + (sizes - 1).clamp_min(0) // 2
    mid2 = starts + sizes // 2
    out = 0.5 * (v[mid.clamp(max=v.numel() - 1)] + v[mid2.clamp(max=v.numel() - 1)])
    return torch.where(sizes > 0, out, torch.full_like(out, float("nan")))


def _sensitivities(y: torch.Tensor, c: torch.Tensor, g: torch.Tensor, pos: torch.Tensor, M: int):
    """(b [M], a [M]) of log Y = a + b G per cell (module docstring): the cell's own regression on
    the room's course where its readings span it, shrunk towards its informative neighbours'."""
    ones = torch.ones_like(y)
    n = torch.zeros(M, dtype=torch.float64).index_add(0, c, ones)
    g_mean = torch.zeros(M, dtype=torch.float64).index_add(0, c, g) / n
    y_mean = torch.zeros(M, dtype=torch.float64).index_add(0, c, y) / n
    dg = g - g_mean[c]
    info = torch.zeros(M, dtype=torch.float64).index_add(0, c, dg * dg)  # sum of squares of the course it saw
    cov = torch.zeros(M, dtype=torch.float64).index_add(0, c, dg * (y - y_mean[c]))
    own = torch.where(info > 0, cov / info.clamp_min(1e-30), torch.ones_like(info))
    # the information one cell seen across the whole clip's change holds: the scale of the shrinkage
    scale = float(((g - g.mean()) ** 2).mean())
    if scale <= 1e-12:  # the room's light did not change where cells were seen twice: b = 1 everywhere
        return torch.ones(M, dtype=torch.float64), y_mean
    prior = _neighbour_mean(own, info, pos, scale)
    b = ((info * own + scale * prior) / (info + scale)).clamp(0.0, 20.0)
    return b, y_mean - b * g_mean


def _neighbour_mean(own: torch.Tensor, info: torch.Tensor, pos: torch.Tensor, scale: float) -> torch.Tensor:
    """Per cell, the information- and inverse-distance-weighted mean b of its NEIGHBOURS nearest
    informative cells (those seen across at least a tenth of the room's change); 1 without any."""
    informative = torch.nonzero(info >= 0.1 * scale).reshape(-1)
    if informative.numel() == 0:
        return torch.ones_like(own)
    src, w_info, b_src = pos[informative], info[informative], own[informative]
    k = min(NEIGHBOURS, informative.numel())
    out = torch.empty_like(own)
    for s in range(0, pos.shape[0], CHUNK):
        d = torch.cdist(pos[s:s + CHUNK], src)
        dist, idx = torch.topk(d, k, largest=False)
        w = w_info[idx] / (dist + 0.05)  # 5 cm: a cell's own entry does not take all the weight
        out[s:s + CHUNK] = (w * b_src[idx]).sum(1) / w.sum(1)
    return out


def _at_times(course: torch.Tensor, view_times: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
    """The course [V] at `times` [K]: linear between the views' times, held beyond them."""
    order = torch.argsort(view_times)
    vt, vc = view_times[order], course[order]
    if vt.numel() == 1:
        return vc.expand(times.shape[0]).clone()
    j = torch.searchsorted(vt, times).clamp(1, vt.numel() - 1)
    t0, t1 = vt[j - 1], vt[j]
    w = ((times - t0) / (t1 - t0).clamp_min(1e-12)).clamp(0.0, 1.0)
    return vc[j - 1] + w * (vc[j] - vc[j - 1])
