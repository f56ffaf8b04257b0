"""Photometric rotation tracking: frames of a camera turning about one spot, registered by
their pixels where features are too few (a room scan's blank ceiling, a studio's smooth walls).

Two views from one centre are related by the homography K R K^-1 whatever the depth, and an
auto-exposure scales a frame's linear radiance by one number, so its tone-mapped values
(core.conventions: LDR = (2^ev L)^(1/GAMMA)) by another. So frame j, looked up through the
rotation, must reproduce frame i's values up to one factor (the exposure step):
    Y_j(pi(R_ij b)) = exp(g_ij / GAMMA) Y_i(b),     Y = luma of the LDR frame
over the pixels that neither clipped nor sank into the black in either frame (compared in the
frames' own LDR units, where 8-bit and compression noise is about even, not in log units, where
it grows without bound in the dark). `align_pair` minimises a robust (pseudo-Huber) cost of
that residual over R_ij (3 numbers) and g_ij (1),
coarse to fine over an image pyramid: at the coarsest level a grid of rotations around each
starting guess is scored at once (the basin of a direct method is a few pixels; a scan turns
20-35 deg between frames), the best few are refined (Gauss-Newton on every level), and the one
with the lowest cost that keeps tracking.direct.min_overlap of the frame in view wins. The offsets g_ij are the
exposure steps a panorama stitcher estimates from the overlaps; `exposure_from_offsets` solves
them for every frame.

`track_rotation_direct(frames, intrinsics)` places every frame: consecutive pairs, searched
first within tracking.direct.near_span_deg of the camera coasting at its last angular velocity (a camera has
inertia) and of any rotation the features offer, over the full grid only when that does not
fix the rotation (whose answer is kept only if cheaper and either as good as the clip's usual
pair or explaining as much of the frame's texture: `_better_of`); then pairs the first pass
says overlap but are far apart in time (a scan's rings see each other's edges: loop
closures), and rotation averaging over all accepted pairs (robust least squares on the rotation
vectors of the pair residuals, weighted by what each pair fixes), so the chain's drift is
shared out; with `refine_focal` the averaging also fits the
focal length's error, which only the loop closures can tell (`_self_calibrate`). A pair is
accepted when its cost is within tracking.direct.max_pair_cost; the track starts at the first frame of the
largest set the trusted pairs connect (frames before it are dropped), and a frame after it that
no trusted pair fixes is placed by the motion prior and named in the stats.
"""
from __future__ import annotations

import copy
import heapq
import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from core.camera import Intrinsics
from core.conventions import GAMMA
from core.tracking.config import DirectConfig, tracking_config
from core.tracking.geometry import matrix_to_rotvec, rotation_angle_deg, rotvec_to_matrix

GRID_DTYPE = torch.float32  # the grid search's precision: it only ranks candidates (align_pair)


def _knobs() -> DirectConfig:
    return tracking_config().direct


@dataclass
class DirectPair:
    i: int
    j: int
    R: np.ndarray  # [3, 3] bearing in frame i -> bearing in frame j (R_j^T R_i for c2w rotations)
    log_gain: float  # g_ij: frame j's log radiance minus frame i's (natural log) where both see the same
    cost: float  # mean robust cost over the overlap at the finest level
    overlap: float  # share of frame i's usable pixels that frame j shows usable
    # [3, 3] information of the rotation (inverse covariance, rad^-2) about frame j's axes: what
    # the pixels' gradients pin down (a blank ceiling pins down nothing, one edge one direction)
    info: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    score: float = math.inf  # `_score` at the finest level: the evidence against R over frame i's texture

    @property
    def matched(self) -> bool:
        """The frames agree under the rotation (cost and overlap); how much that fixes is `info`."""
        return self.cost <= _knobs().max_pair_cost and self.overlap >= _knobs().min_overlap

    @property
    def trusted(self) -> bool:
        """Matched, and the rotation pinned down in every direction to within tracking.direct.max_pair_sigma_deg."""
        sigma = math.radians(_knobs().max_pair_sigma_deg)
        return self.matched and float(np.linalg.eigvalsh(self.info)[0]) >= sigma ** -2


@dataclass
class DirectTrack:
    rotations: np.ndarray  # [K, 3, 3] c2w rotations of the kept frames (kept[0] has I)
    kept: list[int]
    dropped: list[int]
    pairs: list[DirectPair]
    stats: dict = field(default_factory=dict)
    focal_scale: float = 1.0  # the focal length registered with over the one the loop closures fit (1: not fitted)


def frame_luma(frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """LDR frames [T, H, W, 3] -> (luma [T, H, W] in the frames' own LDR units, usable mask
    [T, H, W] float: not clipped, not black)."""
    y = (0.2126 * frames[..., 0] + 0.7152 * frames[..., 1] + 0.0722 * frames[..., 2]).float()
    usable = (frames.amax(-1) < _knobs().bright_ldr) & (y > _knobs().dark_ldr)
    return y, usable.float()


def _level(l: torch.Tensor, v: torch.Tensor, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Area-downsampled log image and mask (a pixel is usable when all it covers was)."""
    H, W = l.shape
    if height >= H:
        return l.double(), v.double()
    size = (height, max(4, round(W * height / H)))
    a = F.interpolate(torch.stack([l * v, v])[None], size=size, mode="area")[0]
    return (a[0] / a[1].clamp_min(1e-6)).double(), (a[1] > 0.999).double()


def _pixel_bearings(h: int, w: int, k: Intrinsics) -> torch.Tensor:
    """Unit bearings [h, w, 3] of pixel centres for intrinsics k scaled to h x w (our camera frame)."""
    s = k.scaled(w, h)
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                          indexing="ij")
    d = torch.stack([(u - s.cx) / s.fx, -(v - s.cy) / s.fy, -torch.ones_like(u)], -1)
    return d / d.norm(dim=-1, keepdim=True)


def _skew(w: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(w[..., 0])
    return torch.stack([torch.stack([z, -w[..., 2], w[..., 1]], -1), torch.stack([w[..., 2], z, -w[..., 0]], -1),
                        torch.stack([-w[..., 1], w[..., 0], z], -1)], -2)


class _Level:
    """One pyramid level of a pair: frame i's usable bearings and log radiance, frame j's images."""

    def __init__(self, li, vi, lj, vj, k: Intrinsics, height: int):
        Li, Vi = _level(li, vi, height)
        Lj, Vj = _level(lj, vj, height)
        self.h, self.w = Li.shape
        self.k = k.scaled(self.w, self.h)
        # frame j's luma (edge-replicated) and mask (zero outside) under a one-pixel margin, as one
        # two-channel image: one lookup reads both, and a pixel inside the frame whose bilinear
        # taps reach past its edge reads the luma's edge and a mask below one, as separate
        # lookups with border and zero padding would
        self.image = torch.stack([F.pad(Lj[None, None], (1, 1, 1, 1), mode="replicate")[0, 0],
                                  F.pad(Vj, (1, 1, 1, 1))])[None]  # [1, 2, h + 2, w + 2]
        # bearing (our camera frame: looking down -z) -> (x, y, 1) x depth in grid_sample's
        # normalised coordinates of the margined image (align_corners=False: -1 and 1 are its outer edges)
        sk = self.k
        ax, ay = 2.0 / (self.w + 2), 2.0 / (self.h + 2)
        self.to_grid = torch.tensor([[ax * sk.fx, 0.0, -(ax * (sk.cx + 1.0) - 1.0)],
                                     [0.0, -ay * sk.fy, -(ay * (sk.cy + 1.0) - 1.0)],
                                     [0.0, 0.0, -1.0]], dtype=torch.float64)
        keep = Vi.reshape(-1) > 0.5
        self.bearings = _pixel_bearings(self.h, self.w, k).reshape(-1, 3)[keep]
        # a rotation whose turn of the optical axis (acos R[2, 2]) and the widest pixel's angle off
        # it (alpha) add up to less than acos(tracking.direct.min_depth) keeps every pixel in front of frame j
        alpha = math.acos(min(1.0, float((-self.bearings[:, 2]).min()))) if len(self.bearings) else 0.0
        self.cos_turn_all_ahead = math.cos(max(0.0, math.acos(_knobs().min_depth) - alpha))
        self.li = Li.reshape(-1)[keep]
        gy, gx = torch.gradient(Li)
        self.texture = torch.sqrt(gx * gx + gy * gy).reshape(-1)[keep]  # what a pixel can tell apart

    def to(self, dtype: torch.dtype) -> "_Level":
        """A copy with its images and pixels in `dtype`."""
        out = copy.copy(self)
        for name in ("image", "bearings", "li", "texture"):
            setattr(out, name, getattr(self, name).to(dtype))
        return out

    def residuals(self, R: torch.Tensor, gain: torch.Tensor):
        """(residuals [S, N], weights [S, N]: 1 where frame j shows the pixel usable) for rotations [S, 3, 3]."""
        # the rotation, the projection and the margined image's normalised coordinates as one 3 x 3
        # map per candidate, applied in planar layout: a scan's tracking is this lookup over
        # thousands of rotations, and elementwise work on interleaved [S, N, 2] costs several times
        # as much; a pixel past frame j's edge (or in its margin) reads a mask below one, and one
        # behind it is named by its depth where a candidate turns far enough to put one there (the
        # clamp would put one straight behind at the centre)
        q = torch.matmul(self.to_grid.to(R.dtype) @ R, self.bearings.T)  # [S, 3, N]
        grid = (q[:, :2] / q[:, 2:].clamp_min(1e-6)).transpose(1, 2)  # [S, N, 2], a view grid_sample reads as is
        lj, vj = F.grid_sample(self.image, grid[None], align_corners=False, padding_mode="zeros")[0]
        seen = vj > 0.999
        if bool((R[:, 2, 2] < self.cos_turn_all_ahead).any()):
            seen &= q[:, 2] > _knobs().min_depth
        return lj - torch.exp(gain.reshape(-1, 1)) * self.li[None], seen.to(vj.dtype)


def _robust(r: torch.Tensor) -> torch.Tensor:
    s = _knobs().robust_scale
    return s * s * (torch.sqrt(1.0 + (r / s) ** 2) - 1.0)


def _masked_median(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Per row [S]: the median of x over the entries with w > 0 (NaN where there is none)."""
    return torch.nanmedian(torch.where(w > 0, x, torch.full_like(x, math.nan)), dim=1).values


def _gain_estimate(lev: "_Level", R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per candidate rotation [S, 3, 3]: the log gain it implies (median of log(Y_j / Y_i) over its
    overlap), and its residuals and weights under that gain (one lookup: r = Y_j - e^g Y_i)."""
    r, w = lev.residuals(R, torch.zeros(R.shape[0], dtype=R.dtype))
    lj = r + lev.li[None]
    ratio = torch.log(lj.clamp_min(1e-3) / lev.li[None].clamp_min(1e-3))
    g = _masked_median(ratio, w).nan_to_num(0.0)
    return g, lj - torch.exp(g)[:, None] * lev.li[None], w


def _search_grid(start: np.ndarray, span: float | None = None, step: float | None = None,
                 roll_span: float | None = None) -> torch.Tensor:
    """Rotations [S, 3, 3] on a grid of turns (about frame j's axes) around `start`: yaw and pitch
    within +-span, roll within +-roll_span (default: span up to tracking.direct.roll_span_deg), `step` apart."""
    span = _knobs().search_span_deg if span is None else span
    step = _knobs().search_step_deg if step is None else step
    yaw = np.arange(-span, span + 1e-9, step)
    rs = min(span, _knobs().roll_span_deg) if roll_span is None else roll_span
    roll = np.arange(-rs, rs + 1e-9, step)
    a, b, c = np.meshgrid(np.radians(yaw), np.radians(yaw), np.radians(roll), indexing="ij")
    vec = np.stack([b.ravel(), a.ravel(), c.ravel()], -1)  # about x (pitch), y (yaw), z (roll)
    return torch.from_numpy(rotvec_to_matrix(vec) @ start)


def align_pair(li: torch.Tensor, vi: torch.Tensor, lj: torch.Tensor, vj: torch.Tensor, k: Intrinsics,
               starts: list[np.ndarray], i: int = 0, j: int = 1, search: bool = True,
               span: float | None = None, candidates: int | None = None,
               roll_span: float | None = None) -> DirectPair:
    """Register frame j against frame i (luma and masks [H, W] from `frame_luma`) from
    the starting rotations `starts` (bearing i -> bearing j); see the module docstring."""
    span = _knobs().search_span_deg if span is None else span
    candidates = _knobs().coarse_candidates if candidates is None else candidates
    starts = [_nearest_rotation(s) for s in starts]
    H = li.shape[0]
    heights = [h for h in _knobs().pyramid_heights if h < H] + [min(H, _knobs().pyramid_heights[-1])]
    levels = [_Level(li, vi, lj, vj, k, h) for h in dict.fromkeys(heights)]
    coarse = levels[0]
    if coarse.li.numel() < 8:
        return DirectPair(i, j, np.asarray(starts[0]), 0.0, math.inf, 0.0)
    cands = torch.cat([_search_grid(s, span, roll_span=roll_span) if search else torch.from_numpy(np.asarray(s)[None])
                       for s in starts])
    with torch.no_grad():
        # every grid rotation a few Gauss-Newton steps on the coarse level (each falls into the
        # basin it is in), then scored one level up (18 rows blur what tells candidates apart);
        # in single precision: this only ranks thousands of rotations, whose rounding (1e-7 of
        # an LDR value) is far below what tells them apart, at half the memory traffic of the
        # step that dominates a scan's tracking; the picked ones go on in double
        grid_level = coarse.to(GRID_DTYPE)
        g, _, _ = _gain_estimate(grid_level, cands.to(GRID_DTYPE))
        cands, g = _refine(grid_level, cands.to(GRID_DTYPE), g, _knobs().grid_iterations)
        scorer = levels[min(1, len(levels) - 1)].to(GRID_DTYPE)
        r, w = scorer.residuals(cands, g)
        score = _score(r, w, scorer.texture)
        mean_cost = (_robust(r) * w).sum(1) / w.sum(1).clamp_min(1.0)
        mean_cost = torch.where(w.mean(1) >= _knobs().min_overlap, mean_cost, torch.full_like(mean_cost, math.inf))
    # the coarse grid is a few degrees apart, where a right answer scores little better than a
    # wrong one: refine the best distinct candidates on the coarse level (by the score, and the
    # cheapest few), then the best of those through the pyramid
    picked = _pick_distinct(score, cands, candidates)
    picked = _pick_distinct(mean_cost, cands, candidates + max(1, candidates // 4), picked)
    if not picked:  # no rotation near the guesses keeps min_overlap of the frame in view: the pair does not match
        return DirectPair(i, j, np.asarray(starts[0]), 0.0, math.inf, 0.0)
    # successive halving: refine the survivors on each level, keep the best by the score and the
    # cheapest: the score (evidence over frame i's texture) favours a larger overlap, where a
    # smooth floor half-agrees with a wrong turn; the cost (the mean residual over the overlap)
    # is what the right turn brings down to the noise
    R = torch.from_numpy(np.stack([_nearest_rotation(x) for x in cands[picked].double().numpy()]))
    g = g[picked].double()
    survivors = _knobs().survivors
    keep_counts = [min(n, candidates) for n in survivors[: len(levels)]] + [1] * max(0, len(levels) - len(survivors))
    with torch.no_grad():
        for n, (lev, keep) in enumerate(zip(levels, keep_counts)):
            # a finer grid around each survivor: the coarse level's minima can sit a few degrees off
            if n == 1 and search:
                R = torch.cat([_search_grid(x.numpy(), _knobs().local_span_deg, _knobs().local_step_deg) for x in R])
                g, r, w = _gain_estimate(lev, R)
                best = _survivors(r, w, lev.texture, _knobs().local_candidates, R)
                R, g = R[best], g[best]
            R, g = _refine(lev, R, g, _knobs().gn_iterations[min(n, len(_knobs().gn_iterations) - 1)])
            r, w = lev.residuals(R, g)
            order = _survivors(r, w, lev.texture, keep, R)
            R, g, r, w = R[order], g[order], r[order], w[order]
    overlap = w.mean(1)
    cost = (_robust(r) * w).sum(1) / w.sum(1).clamp_min(1.0)
    score = _score(r, w, levels[-1].texture)
    # the cheapest survivor that keeps tracking.direct.min_overlap of the frame in view
    for c in sorted(range(R.shape[0]), key=lambda c: float(cost[c])):
        if float(overlap[c]) >= _knobs().min_overlap:
            Rc = R[c]
            return DirectPair(
                i,
                j,
                _nearest_rotation(Rc.numpy()),
                GAMMA * float(g[c]),
                float(cost[c]),
                float(overlap[c]),
                _information(levels[-1], Rc, float(g[c])),
                float(score[c]),
            )
    return DirectPair(i, j, _nearest_rotation(R[0].numpy()), GAMMA * float(g[0]), math.inf, 0.0)


def _pick_distinct(ranking: torch.Tensor, R: torch.Tensor, quota: int, picked: list[int] | None = None) -> list[int]:
    """`picked` extended, best `ranking` first (finite values only), by candidates whose rotations
    R [S, 3, 3] are more than tracking.direct.search_step_deg from every one picked, until `quota` are picked."""
    picked = list(picked or [])
    cos_min = math.cos(math.radians(_knobs().search_step_deg + 1e-6))

    def far(q: int) -> torch.Tensor:  # [S]: the angle to candidate q above the step (trace of R_q^T R)
        return ((R * R[q]).sum((1, 2)) - 1.0) / 2.0 < cos_min

    alive = torch.isfinite(ranking)
    for q in picked:
        alive &= far(q)
    for idx in torch.argsort(ranking).tolist():
        if len(picked) >= quota or not bool(torch.isfinite(ranking[idx])):
            break
        if alive[idx]:
            picked.append(idx)
            alive &= far(idx)
    return picked


def _survivors(r: torch.Tensor, w: torch.Tensor, texture: torch.Tensor, keep: int, R: torch.Tensor) -> torch.Tensor:
    """Indices of the `keep` best-scored distinct candidates (`_score`; rotations R [S, 3, 3] more
    than tracking.direct.search_step_deg apart), plus the cheapest one (mean robust residual over
    an overlap of at least tracking.direct.min_overlap) when it is not among them. Distinct: the
    finer grid round each survivor puts many near-copies of one basin at the top, and keeping
    only those would drop the right turn when a wrong basin scores a little better on a coarse
    level (a texture that repeats along the turn, such as a curtain's stripes)."""
    score = _score(r, w, texture)
    picked = _pick_distinct(score, R, keep)
    order = torch.tensor(picked) if picked else torch.argsort(score)[:keep]
    cost = (_robust(r) * w).sum(1) / w.sum(1).clamp_min(1.0)
    cost = torch.where(w.mean(1) >= _knobs().min_overlap, cost, torch.full_like(cost, math.inf))
    cheapest = int(torch.argmin(cost))
    if math.isfinite(float(cost[cheapest])) and cheapest not in order.tolist():
        order = torch.cat([order, torch.tensor([cheapest])])
    return order


def _information(lev: _Level, R: torch.Tensor, gain: float) -> np.ndarray:
    """Gauss-Newton information [3, 3] of the rotation (a turn about frame j's axes) from the
    overlap's pixels: sum of J J^T / sigma^2 over the inliers (|r| < 3 sigma), sigma the
    residuals' robust spread (at least tracking.direct.min_residual_sigma)."""
    # central differences a degree and a half wide: the slope of the cost over the range a wrong
    # registration would be off by, not at the optimum's pixel scale, where smooth shading and
    # compression noise look like information they do not carry
    step = math.radians(_knobs().info_step_deg)
    turns = torch.cat([torch.zeros(1, 3), step * torch.eye(3), -step * torch.eye(3)]).double()
    with torch.no_grad():
        rs, ws = lev.residuals(torch.matrix_exp(_skew(turns)) @ R, torch.full((7,), gain, dtype=torch.float64))
    r, wt = rs[0], ws[0] * ws[1:].prod(0)  # pixels in view for every probe
    if float(wt.sum()) < 8:
        return np.zeros((3, 3))
    J = ((rs[1:4] - rs[4:7]) / (2 * step)).T  # [N, 3]
    dg = -torch.exp(torch.tensor(gain, dtype=torch.float64)) * lev.li  # d r / d g
    ins = r[wt > 0]
    sigma = max(_knobs().min_residual_sigma, 1.4826 * float((ins - ins.median()).abs().median()))
    use = (wt > 0) & (r.abs() < 3 * sigma)
    Ju = torch.cat([J[use], dg[use][:, None]], 1)
    full = (Ju.T @ Ju).numpy() / sigma ** 2
    # the rotation's information with the gain marginalised (Schur complement): a turn across a
    # smooth ramp of brightness looks like an exposure step and fixes nothing
    return full[:3, :3] - np.outer(full[:3, 3], full[3, :3]) / max(full[3, 3], 1e-12)


def _spread(r: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Per candidate [S]: the robust spread (1.4826 MAD) of its residuals over its overlap (inf
    with fewer than 8 pixels)."""
    med = _masked_median(r, w)
    spread = 1.4826 * _masked_median((r - med[:, None]).abs(), w)
    return torch.where((w > 0).sum(1) >= 8, spread, torch.full_like(spread, math.inf)).nan_to_num(math.inf)


def _score(r: torch.Tensor, w: torch.Tensor, texture: torch.Tensor) -> torch.Tensor:
    """Per candidate [S] (lower is better): the evidence against it. Each pixel of frame i in the
    overlap counts by its texture (the luma gradient: a blank wall agrees with any rotation and
    says nothing), for the candidate where its residual is within tracking.direct.score_cap of what noise and a
    fraction of a pixel's misregistration leave there (sqrt(NOISE^2 + (SUBPIXEL x gradient)^2)),
    against it where beyond; the sum over frame i's texture. The right rotation explains what
    the two frames both show, however little that is; a wrong one leaves textured pixels
    unexplained or only overlaps blank ones."""
    tol2 = (_knobs().score_cap ** 2) * (_knobs().score_noise ** 2 + (_knobs().score_subpixel * texture[None]) ** 2)
    explained = (1.0 - r * r / tol2).clamp(min=0.0)
    vote = (w * texture[None] * (1.0 - 2.0 * explained)).sum(1) / texture.sum().clamp_min(1e-12)
    return torch.where(w.mean(1) >= _knobs().min_overlap, vote, torch.full_like(vote, math.inf))


def _refine(lev: _Level, R0: torch.Tensor, g0: torch.Tensor, iterations: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss-Newton (iteratively reweighted for the pseudo-Huber cost) over a turn about each of
    the rotations R0 [S, 3, 3] and its log gain g0 [S], all candidates at once on one level; the
    Jacobian by central differences (one batched lookup of 7 probes per candidate), steps of at
    most tracking.direct.max_step_deg. Returns (R [S, 3, 3], g [S])."""
    S = R0.shape[0]
    step = 1e-3
    probes = torch.cat([torch.zeros(1, 3), step * torch.eye(3), -step * torch.eye(3)]).to(R0.dtype)  # [7, 3]
    turn_probes = torch.matrix_exp(_skew(probes))  # [7, 3, 3]
    R, g = R0.clone(), g0.clone().to(R0.dtype)
    for _ in range(iterations):
        Rp = (turn_probes[None] @ R[:, None]).reshape(-1, 3, 3)  # [S * 7, 3, 3]
        r, w = lev.residuals(Rp, g.repeat_interleave(7))
        r, w = r.reshape(S, 7, -1), w.reshape(S, 7, -1)
        common = w.prod(1)  # [S, N] pixels every probe sees
        r0 = r[:, 0]
        J = torch.stack([(r[:, 1 + a] - r[:, 4 + a]) / (2 * step) for a in range(3)]
                        + [-torch.exp(g)[:, None] * lev.li[None]], -1)  # [S, N, 4]
        irls = common / torch.sqrt(1.0 + (r0 / _knobs().robust_scale) ** 2)
        JtJ = torch.einsum("sn,sna,snb->sab", irls, J, J) + 1e-9 * torch.eye(4, dtype=R.dtype)
        Jtr = torch.einsum("sn,sna,sn->sa", irls, J, r0)
        # a candidate whose system is singular (in single precision the damping above is lost in
        # rounding where the overlap is a sliver) or whose step is not finite stays where it is
        step_, info = torch.linalg.solve_ex(JtJ, Jtr)
        delta = torch.where(((info == 0)[:, None] & torch.isfinite(step_)), -step_, torch.zeros_like(step_))  # [S, 4]
        turn = delta[:, :3]
        norm = turn.norm(dim=1, keepdim=True)
        limit = math.radians(_knobs().max_step_deg)
        turn = torch.where(norm > limit, turn * limit / norm.clamp_min(1e-12), turn)
        R = torch.matrix_exp(_skew(turn)) @ R
        g = g + delta[:, 3].clamp(-1.0, 1.0)
    return R, g


def exposure_from_offsets(pairs: list[DirectPair], frames: list[int]) -> np.ndarray:
    """Each frame's exposure in stops relative to frames[0], from the pairs' log gains (least
    squares over every trusted pair, weighted by overlap): ev_j - ev_i = g_ij / ln 2."""
    pos = {f: n for n, f in enumerate(frames)}
    rows = [p for p in pairs if p.trusted and p.i in pos and p.j in pos]
    if not rows:
        return np.zeros(len(frames))
    A = np.zeros((len(rows) + 1, len(frames)))
    b = np.zeros(len(rows) + 1)
    for n, p in enumerate(rows):
        w = math.sqrt(p.overlap)
        A[n, pos[p.j]], A[n, pos[p.i]], b[n] = w, -w, w * p.log_gain / math.log(2.0)
    A[-1, 0] = 1.0  # gauge: the first frame at 0
    return np.linalg.lstsq(A, b, rcond=None)[0]


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest M (SVD): products of rotations drift off SO(3) by rounding, and a
    start that is not a rotation hands its error on to everything chained from it."""
    u, _, vt = np.linalg.svd(np.asarray(M, np.float64))
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _coast(R: dict[int, np.ndarray], f: int) -> np.ndarray | None:
    """The relative rotation frame f-1 -> f if the camera kept its last turn, or None."""
    if f - 1 in R and f - 2 in R:
        return R[f - 1].T @ R[f - 2]  # bearing f-2 -> f-1, repeated
    return None


def track_rotation_direct(frames: torch.Tensor, k: Intrinsics, feature_pairs: dict | None = None,
                          refine_focal: bool = False) -> DirectTrack:
    """Rotations of every frame of a camera turning about one spot (module docstring).
    `feature_pairs` {(i, j): R bearing i -> j} are extra starting guesses from matched features.
    `refine_focal`: fit the focal length's error from the loop closures (`_self_calibrate`; use it
    when the intrinsics were assumed): `DirectTrack.focal_scale` = k.fx / the fitted focal."""
    l, v = frame_luma(frames)
    T = frames.shape[0]
    feature_pairs = feature_pairs or {}
    R: dict[int, np.ndarray] = {0: np.eye(3)}
    pairs: list[DirectPair] = []
    costs: list[float] = []  # of the trusted consecutive pairs so far
    for f in range(1, T):
        c = _coast(R, f)
        guesses = ([feature_pairs[(f - 1, f)]] if (f - 1, f) in feature_pairs else []) + [np.eye(3) if c is None else c]
        starts = guesses + ([np.eye(3)] if c is not None else [])
        # near the guesses first (a hand-held turn is smooth: the coast is rarely far off, and a
        # hand rolls little), the full grid from every start only when that does not pin the
        # rotation down (a direction change, a jolt)
        p = align_pair(l[f - 1], v[f - 1], l[f], v[f], k, guesses, f - 1, f, span=_knobs().near_span_deg,
                       candidates=_knobs().near_candidates, roll_span=_knobs().near_roll_span_deg)
        usual = float(np.median(costs)) if len(costs) >= 3 else math.inf
        if not p.trusted or p.cost > _knobs().near_cost_ratio * usual:
            # a smooth floor can agree with a wrong turn near a wrong guess (where the scan turns
            # from a tilt into a ring), at a cost well above the clip's usual: the full grid, and
            # the better answer of the two (`_better_of`)
            p = _better_of(p, align_pair(l[f - 1], v[f - 1], l[f], v[f], k, starts, f - 1, f), usual)
        if p.trusted and p.cost > _knobs().near_cost_ratio * usual and p.overlap < _knobs().weak_overlap:
            # the full grid gave nothing better either, and the two frames barely overlap (a
            # scan's jump between rings): a wrong basin fits a sliver of overlap as cheaply as the
            # right one, so the pair places nothing; the loop closures will
            p = replace(p, info=np.zeros((3, 3)))
        if p.trusted:
            costs.append(p.cost)
        pairs.append(p)
        # a pair that fixes the rotation places the frame; else the camera coasts on (a blank
        # wall fixes nothing: the averaging below weighs what each pair does fix)
        step = p.R if p.trusted or c is None else c
        R[f] = _nearest_rotation(R[f - 1] @ step.T)  # bearing_f = step bearing_{f-1}: R_f = R_{f-1} step^T
    chained = [p.j for p in pairs if p.trusted]
    axes = {f: R[f] @ np.array([0.0, 0.0, -1.0]) for f in R}
    knobs = _knobs()
    loops = [(a, b) for a in range(T) for b in range(a + knobs.loop_min_gap, T)
             if math.degrees(math.acos(float(np.clip(axes[a] @ axes[b], -1, 1)))) <= knobs.loop_max_axis_deg]
    loops = loops[:knobs.max_loop_pairs]
    for a, b in loops:
        pairs.append(align_pair(l[a], v[a], l[b], v[b], k, [R[b].T @ R[a]], a, b, span=_knobs().loop_span_deg,
                                candidates=_knobs().near_candidates, roll_span=_knobs().near_roll_span_deg))
    matched = [p for p in pairs if p.matched]
    # the track starts at the first frame of the largest set that trusted pairs connect: a first
    # frame no trusted pair reaches (a blank wall, a pair matched 45 deg off) would otherwise set
    # every frame's axes wrong; the frames before that start are dropped
    start = min(max((_placed(T, [p for p in matched if p.trusted], root) for root in range(T)), key=len))
    sub = [replace(p, i=p.i - start, j=p.j - start) for p in matched if p.i >= start and p.j >= start]
    chain = {f - start: R[f] for f in range(start, T)}
    Tk = T - start
    init = _spanning_tree(Tk, sub, chain)
    if refine_focal:
        rots, focal_scale, calibration = _self_calibrate(Tk, sub, init)
    else:
        rots, focal_scale, _ = _average_rotations(Tk, sub, init)
        calibration = {}
    placed = {f + start for f in _placed(Tk, [p for p in sub if p.trusted])}
    kept = list(range(start, T))
    stats = {"pairs": len(pairs), "matched_pairs": len(matched), "trusted_pairs": sum(p.trusted for p in pairs),
             "loop_pairs": len(loops), "loop_pairs_trusted": sum(p.trusted for p in pairs[T - 1:]),
             "chain_fixed": len(chained), "frames_fixed_by_pairs": len(placed), "first_frame": start,
             "frames_from_motion_prior": sorted(set(kept) - placed),
             "median_cost": float(np.median([p.cost for p in matched])) if matched else None, **calibration}
    return DirectTrack(rots, kept, list(range(start)), pairs, stats, focal_scale)


def _better_of(near: DirectPair, full: DirectPair, usual: float) -> DirectPair:
    """A consecutive pair's answer near its guesses or from the full grid (searched where the near
    one costs over tracking.direct.near_cost_ratio x the clip's `usual` pair cost, or is not trusted): the full
    grid's where the near one is not trusted, or where it is trusted and cheaper, and either fits
    as well as the clip's usual pair or explains at least as much of frame i's texture
    (`DirectPair.score`). Neither test alone decides: where a scan jumps between rings the right
    turn overlaps little and a smooth wall half-agrees with a wrong one over more of the frame
    (a right turn at 0.3x the usual cost may explain 40 % of the texture where the wrong near
    one at 3x explains 68 %), and a wrong basin keeping a sliver of blank overlap is cheaper
    than a right turn that fits worse than usual (95 deg off at 2.8x the usual cost explaining
    2 % of the texture, where the right turn at 5.8x explains 55 %)."""
    if not near.trusted:
        return full
    if full.trusted and full.cost < near.cost and (full.cost <= usual or full.score <= near.score):
        return full
    return near


def _spanning_tree(T: int, pairs: list[DirectPair], chain: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """Starting rotations for the averaging: grown from frame 0 along the matched pairs, the pair
    with the most information (its least certain direction) first (a maximum spanning tree), so
    a frame the chain only coasted past is placed by a loop closure where one reaches it; frames
    no pair reaches keep the chain's rotation relative to the last placed frame before them."""
    def strength(p: DirectPair) -> float:
        return float(np.linalg.eigvalsh(p.info)[0])

    links: dict[int, list[DirectPair]] = {}
    for p in pairs:
        links.setdefault(p.i, []).append(p)
        links.setdefault(p.j, []).append(p)
    R = {0: np.eye(3)}
    heap = [(-strength(p), n, p) for n, p in enumerate(links.get(0, []))]
    heapq.heapify(heap)
    count = len(heap)
    while heap:
        _, _, p = heapq.heappop(heap)
        if p.i in R and p.j in R:
            continue
        new = p.j if p.i in R else p.i
        R[new] = _nearest_rotation(R[p.i] @ p.R.T) if new == p.j else _nearest_rotation(R[p.j] @ p.R)
        for q in links.get(new, []):
            if not (q.i in R and q.j in R):
                count += 1
                heapq.heappush(heap, (-strength(q), count, q))
    for f in range(1, T):
        if f not in R:
            R[f] = _nearest_rotation(R[f - 1] @ chain[f - 1].T @ chain[f])
    return R


def _placed(T: int, pairs: list[DirectPair], root: int = 0) -> set[int]:
    """Frames connected to frame `root` by pairs that fix the rotation."""
    nbrs: dict[int, set[int]] = {}
    for p in pairs:
        nbrs.setdefault(p.i, set()).add(p.j)
        nbrs.setdefault(p.j, set()).add(p.i)
    seen, todo = {root}, [root]
    while todo:
        f = todo.pop()
        for g in nbrs.get(f, ()):
            if g not in seen:
                seen.add(g)
                todo.append(g)
    return seen


def _average_rotations(T: int, pairs: list[DirectPair], init: dict[int, np.ndarray],
                       fit_focal: bool = False) -> tuple[np.ndarray, float, float]:
    """c2w rotations [T, 3, 3] (frame 0 fixed at I) minimising, robustly, each pair's disagreement
    e_ij = rotvec(R_j^T R_i meas_ij^T) weighted by its information (e^T info e), plus a motion
    prior: consecutive turns differ by about tracking.direct.motion_sigma_deg (what keeps frames that no pair
    fixes on the camera's path). Returns (rotations, focal scale, robust cost).

    `fit_focal`: also fit s = f / f_true, the error of the focal length f the pairs were registered
    with. A turn across the view moves pixels by about f_true x angle, so a pair registered with
    f measures the turn's components across the view (its rotation vector's x and y) as 1/s times
    the truth, and its roll as it is; the pairs are taken as exp(diag(s, s, 1) rotvec) of what
    they measured. Consecutive pairs alone fit any s; loop closures (a ring that
    comes round, rings that see each other) fit one: the stitcher's self-calibration."""
    base = np.stack([init[f] for f in range(T)])
    if T < 2:
        return base, 1.0, 0.0
    meas_vec = matrix_to_rotvec(np.stack([p.R for p in pairs])) if pairs else np.zeros((0, 3))
    ia, ib = np.array([p.i for p in pairs], int), np.array([p.j for p in pairs], int)
    L = np.stack([_sqrt_info(p.info) for p in pairs]) if pairs else np.zeros((0, 3, 3))
    prior = 1.0 / math.radians(_knobs().motion_sigma_deg)
    n_rot = 3 * (T - 1)

    def rots(x):
        return np.concatenate([np.eye(3)[None], rotvec_to_matrix(x[:n_rot].reshape(-1, 3)) @ base[1:]])

    def residuals(x):
        Rk = rots(x)
        out = []
        if len(pairs):
            scale = math.exp(x[n_rot]) if fit_focal else 1.0
            meas = rotvec_to_matrix(meas_vec * np.array([scale, scale, 1.0]))
            pred = np.transpose(Rk[ib], (0, 2, 1)) @ Rk[ia]  # R_j^T R_i
            e = matrix_to_rotvec(pred @ np.transpose(meas, (0, 2, 1)))
            out.append(np.einsum("nji,nj->ni", L, e).ravel())
        turn = matrix_to_rotvec(np.transpose(Rk[:-1], (0, 2, 1)) @ Rk[1:])  # each frame's turn, in its own axes
        out.append(prior * (turn[1:] - turn[:-1]).ravel())
        return np.concatenate(out)

    n_pair = 3 * len(pairs)
    sparsity = lil_matrix((n_pair + 3 * max(0, T - 2), n_rot + int(fit_focal)), dtype=int)
    for n, (a, b) in enumerate(zip(ia, ib)):
        for q in (a, b):
            if q > 0:
                sparsity[3 * n:3 * n + 3, 3 * (q - 1):3 * q] = 1
        if fit_focal:
            sparsity[3 * n:3 * n + 3, n_rot] = 1
    for f in range(T - 2):
        for q in (f, f + 1, f + 2):
            if q > 0:
                sparsity[n_pair + 3 * f:n_pair + 3 * f + 3, 3 * (q - 1):3 * q] = 1
    x0 = np.zeros(n_rot + int(fit_focal))
    bounds = (-np.inf, np.inf)
    if fit_focal:  # log s within the range of focal errors a phone's assumed field of view makes
        lo, hi = np.full(x0.size, -np.inf), np.full(x0.size, np.inf)
        lo[n_rot], hi[n_rot] = -_knobs().max_log_focal_scale, _knobs().max_log_focal_scale
        bounds = (lo, hi)
    sol = least_squares(residuals, x0, jac_sparsity=sparsity, loss="soft_l1", f_scale=3.0, max_nfev=100,
                        bounds=bounds)
    return rots(sol.x), math.exp(sol.x[n_rot]) if fit_focal else 1.0, float(sol.cost)


def _self_calibrate(T: int, pairs: list[DirectPair], init: dict[int, np.ndarray]) -> tuple[np.ndarray, float, dict]:
    """(rotations, focal scale s, stats): the averaging with the focal scale fitted, kept when it
    explains the pairs better than the focal they were registered with by more than one free
    parameter does by chance (the drop in robust cost over the fitted cost per degree of freedom
    beyond tracking.direct.focal_fit_chi2, the chi-square of one parameter at p = 0.001); else s = 1."""
    fixed, _, cost_fixed = _average_rotations(T, pairs, init)
    fitted, s, cost_fit = _average_rotations(T, pairs, init, fit_focal=True)
    dof = max(1, 3 * len(pairs) - 3 * (T - 1) - 1)
    gain = (cost_fixed - cost_fit) / max(cost_fit / dof, 1e-12)
    keep = gain > _knobs().focal_fit_chi2
    stats = {"focal_scale_fitted": round(s, 5), "focal_fit_gain": round(gain, 2), "focal_scale_applied": keep}
    return (fitted, s, stats) if keep else (fixed, 1.0, stats)


def _sqrt_info(info: np.ndarray) -> np.ndarray:
    """L with L L^T = info (info symmetric positive semi-definite; null directions stay null)."""
    vals, vecs = np.linalg.eigh(0.5 * (info + info.T))
    return vecs * np.sqrt(np.clip(vals, 0.0, None))[None]


def pair_angle_errors(track: DirectTrack) -> list[float]:
    """Per trusted pair, the angle (deg) between its measurement and what the final rotations say."""
    pos = {f: n for n, f in enumerate(track.kept)}
    out = []
    for p in track.pairs:
        if p.trusted and p.i in pos and p.j in pos:
            Ri, Rj = track.rotations[pos[p.i]], track.rotations[pos[p.j]]
            out.append(rotation_angle_deg(p.R.T @ (Rj.T @ Ri)))
    return out
