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
20-35 deg between frames), the best few are refined (L-BFGS on every level), and the one with
the lowest cost that keeps MIN_OVERLAP of the frame in view wins. The offsets g_ij are the
exposure steps a panorama stitcher estimates from the overlaps; `exposure_from_offsets` solves
them for every frame.

`track_rotation_direct(frames, intrinsics)` places every frame: consecutive pairs, started
from the camera coasting at its last angular velocity (a camera has inertia) and from any
rotation the features offer; then pairs the first pass says overlap but are far apart in time
(a scan's rings see each other's edges: loop closures), and rotation averaging over all
accepted pairs (robust least squares on the rotation vectors of the pair residuals), so the
chain's drift is shared out. A pair is accepted when its cost is within MAX_PAIR_COST; a frame
no accepted pair reaches is dropped.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from core.camera import Intrinsics
from core.conventions import GAMMA
from core.tracking.geometry import matrix_to_rotvec, rotation_angle_deg, rotvec_to_matrix

PYRAMID_HEIGHTS = (18, 36, 72)  # rows per level, coarse to fine (capped at the frame's own)
SEARCH_STEP_DEG = 5.0  # the coarse grid's spacing around a starting guess
SEARCH_SPAN_DEG = 30.0  # ... and its half-width in yaw and pitch (roll: +-ROLL_SPAN_DEG)
ROLL_SPAN_DEG = 15.0
COARSE_CANDIDATES = 6  # distinct best grid rotations refined on the coarse level
SURVIVORS = [6, 3, 2]  # candidates kept after each level (coarse to fine)
LBFGS_ITERATIONS = 20
ROBUST_SCALE = 0.05  # LDR units: pseudo-Huber scale of the residual
# Candidates are compared by a capped cost per pixel in units of the residual noise (_score): an
# explained pixel costs about 1, an unexplained one SCORE_CAP^2, one frame j does not show
# OUTSIDE_COST; a wrong rotation can neither leave pixels unexplained nor push the frames apart
# until nothing is left to disagree.
SCORE_CAP = 3.0
OUTSIDE_COST = 4.0
MIN_SCORE_SIGMA = 0.002  # LDR units: the noise floor the score assumes
MIN_OVERLAP = 0.15  # share of frame i's usable pixels frame j must show
MAX_PAIR_COST = 0.0015  # mean robust cost over the overlap above which a pair is not trusted
MAX_PAIR_SIGMA_DEG = 1.0  # a pair fixes the rotation when its least certain direction is within this
INFO_STEP_DEG = 1.5  # the differences the information is measured over
MIN_RESIDUAL_SIGMA = 0.004  # LDR units: the floor of a pair's residual noise (8-bit, compression)
MOTION_SIGMA_DEG = 5.0  # prior: a frame's turn differs from the previous frame's by about this much
DARK_LDR, BRIGHT_LDR = 0.03, 0.97  # usable pixels: neither sunk into the black nor clipped
LOOP_MAX_AXIS_DEG = 40.0  # frames whose optical axes are this close are tried as loop closures
LOOP_MIN_GAP = 3  # ... when at least this many frames apart (neighbours are already paired)
MAX_LOOP_PAIRS = 120


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

    @property
    def matched(self) -> bool:
        """The frames agree under the rotation (cost and overlap); how much that fixes is `info`."""
        return self.cost <= MAX_PAIR_COST and self.overlap >= MIN_OVERLAP

    @property
    def trusted(self) -> bool:
        """Matched, and the rotation pinned down in every direction to within MAX_PAIR_SIGMA_DEG."""
        return self.matched and float(np.linalg.eigvalsh(self.info)[0]) >= math.radians(MAX_PAIR_SIGMA_DEG) ** -2


@dataclass
class DirectTrack:
    rotations: np.ndarray  # [K, 3, 3] c2w rotations of the kept frames (kept[0] has I)
    kept: list[int]
    dropped: list[int]
    pairs: list[DirectPair]
    stats: dict = field(default_factory=dict)


def frame_luma(frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """LDR frames [T, H, W, 3] -> (luma [T, H, W] in the frames' own LDR units, usable mask
    [T, H, W] float: not clipped, not black)."""
    y = (0.2126 * frames[..., 0] + 0.7152 * frames[..., 1] + 0.0722 * frames[..., 2]).float()
    usable = (frames.amax(-1) < BRIGHT_LDR) & (y > DARK_LDR)
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
        self.Lj, self.Vj = _level(lj, vj, height)
        self.h, self.w = Li.shape
        self.k = k.scaled(self.w, self.h)
        keep = Vi.reshape(-1) > 0.5
        self.bearings = _pixel_bearings(self.h, self.w, k).reshape(-1, 3)[keep]
        self.li = Li.reshape(-1)[keep]

    def residuals(self, R: torch.Tensor, gain: torch.Tensor):
        """(residuals [S, N], weights [S, N]: 1 where frame j shows the pixel usable) for rotations [S, 3, 3]."""
        d = torch.einsum("sij,nj->sni", R, self.bearings)
        z = (-d[..., 2]).clamp_min(1e-6)
        u = self.k.fx * d[..., 0] / z + self.k.cx
        v = -self.k.fy * d[..., 1] / z + self.k.cy
        grid = torch.stack([2.0 * u / self.w - 1.0, 2.0 * v / self.h - 1.0], -1)[:, None]  # [S, 1, N, 2]
        S = R.shape[0]
        lj = F.grid_sample(self.Lj.expand(S, 1, self.h, self.w), grid, align_corners=False, padding_mode="border")[:, 0, 0]
        vj = F.grid_sample(self.Vj.expand(S, 1, self.h, self.w), grid, align_corners=False, padding_mode="zeros")[:, 0, 0]
        inside = (d[..., 2] < -0.1) & (u > 0) & (u < self.w) & (v > 0) & (v < self.h)
        weight = torch.where(inside & (vj > 0.999), torch.ones_like(vj), torch.zeros_like(vj))
        return lj - torch.exp(gain.reshape(-1, 1)) * self.li[None], weight


def _robust(r: torch.Tensor) -> torch.Tensor:
    s = ROBUST_SCALE
    return s * s * (torch.sqrt(1.0 + (r / s) ** 2) - 1.0)


def _gain_estimate(lev: "_Level", R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per candidate rotation [S, 3, 3]: the log gain it implies (median of log(Y_j / Y_i) over its
    overlap), and its residuals and weights under that gain."""
    zero = torch.zeros(R.shape[0], dtype=torch.float64)
    r, w = lev.residuals(R, zero)
    ratio = torch.log((r + lev.li[None]).clamp_min(1e-3) / lev.li[None].clamp_min(1e-3))
    g = torch.zeros(R.shape[0], dtype=torch.float64)
    for s in range(R.shape[0]):
        vals = ratio[s][w[s] > 0]
        if vals.numel():
            g[s] = vals.median()
    r, w = lev.residuals(R, g)
    return g, r, w


def _search_grid(start: np.ndarray) -> torch.Tensor:
    """Rotations [S, 3, 3] on a grid of small turns (about frame j's axes) around `start`."""
    yaw = np.arange(-SEARCH_SPAN_DEG, SEARCH_SPAN_DEG + 1e-9, SEARCH_STEP_DEG)
    roll = np.arange(-ROLL_SPAN_DEG, ROLL_SPAN_DEG + 1e-9, SEARCH_STEP_DEG * 3)
    a, b, c = np.meshgrid(np.radians(yaw), np.radians(yaw), np.radians(roll), indexing="ij")
    vec = np.stack([b.ravel(), a.ravel(), c.ravel()], -1)  # about x (pitch), y (yaw), z (roll)
    return torch.from_numpy(rotvec_to_matrix(vec) @ start)


def align_pair(li: torch.Tensor, vi: torch.Tensor, lj: torch.Tensor, vj: torch.Tensor, k: Intrinsics,
               starts: list[np.ndarray], i: int = 0, j: int = 1, search: bool = True) -> DirectPair:
    """Register frame j against frame i (luma and masks [H, W] from `frame_luma`) from
    the starting rotations `starts` (bearing i -> bearing j); see the module docstring."""
    starts = [_nearest_rotation(s) for s in starts]
    H = li.shape[0]
    heights = [h for h in PYRAMID_HEIGHTS if h < H] + [min(H, PYRAMID_HEIGHTS[-1])]
    levels = [_Level(li, vi, lj, vj, k, h) for h in dict.fromkeys(heights)]
    coarse = levels[0]
    if coarse.li.numel() < 8:
        return DirectPair(i, j, np.asarray(starts[0]), 0.0, math.inf, 0.0)
    cands = torch.cat([_search_grid(s) if search else torch.from_numpy(np.asarray(s)[None]) for s in starts])
    with torch.no_grad():
        g, r, w = _gain_estimate(coarse, cands)
        cost = _score(r, w, _noise(r, w))
    # the coarse grid is a few degrees apart, where a right answer scores little better than a
    # wrong one: refine the best distinct candidates on the coarse level, then the best of those
    # through the pyramid
    picked: list[int] = []
    for idx in torch.argsort(cost).tolist():
        if all(rotation_angle_deg(cands[idx].numpy().T @ cands[q].numpy()) > 2 * SEARCH_STEP_DEG for q in picked):
            picked.append(idx)
        if len(picked) == COARSE_CANDIDATES:
            break
    # successive halving: refine the survivors on each level, keep the best by the penalised score
    survivors = [(cands[idx], float(g[idx])) for idx in picked]
    keep_counts = SURVIVORS[: len(levels)] + [1] * max(0, len(levels) - len(SURVIVORS))
    scored: list[tuple[float, torch.Tensor, float, torch.Tensor, torch.Tensor]] = []
    for lev, keep in zip(levels, keep_counts):
        fits = []
        for R0, gain0 in survivors:
            R, gain = _refine([lev], R0, gain0)
            with torch.no_grad():
                r, w = lev.residuals(R[None], torch.tensor([gain], dtype=torch.float64))
            fits.append((R, gain, r[0], w[0]))
        rs, ws = torch.stack([f[2] for f in fits]), torch.stack([f[3] for f in fits])
        sc = _score(rs, ws, _noise(rs, ws))
        scored = sorted(((float(c), *f) for c, f in zip(sc, fits)), key=lambda c: c[0])
        survivors = [(R, gain) for _, R, gain, _, _ in scored[:keep]]
    for _, R, gain, r, w in scored:
        n = float(w.sum())
        overlap = n / max(1, w.numel())
        if overlap >= MIN_OVERLAP:
            return DirectPair(i, j, _nearest_rotation(R.numpy()), GAMMA * gain, float((_robust(r) * w).sum()) / max(n, 1.0), overlap,
                              _information(levels[-1], R, gain))
    return DirectPair(i, j, scored[0][1].numpy(), GAMMA * scored[0][2], math.inf, 0.0)


def _information(lev: _Level, R: torch.Tensor, gain: float) -> np.ndarray:
    """Gauss-Newton information [3, 3] of the rotation (a turn about frame j's axes) from the
    overlap's pixels: sum of J J^T / sigma^2 over the inliers (|r| < 3 sigma), sigma the
    residuals' robust spread (at least MIN_RESIDUAL_SIGMA)."""
    # central differences a degree and a half wide: the slope of the cost over the range a wrong
    # registration would be off by, not at the optimum's pixel scale, where smooth shading and
    # compression noise look like information they do not carry
    step = math.radians(INFO_STEP_DEG)
    turns = torch.cat([torch.zeros(1, 3), step * torch.eye(3), -step * torch.eye(3)]).double()
    with torch.no_grad():
        rs, ws = lev.residuals(torch.matrix_exp(_skew(turns)) @ R, torch.full((7,), gain, dtype=torch.float64))
    r, wt = rs[0], ws[0] * ws[1:].prod(0)  # pixels in view for every probe
    if float(wt.sum()) < 8:
        return np.zeros((3, 3))
    J = ((rs[1:4] - rs[4:7]) / (2 * step)).T  # [N, 3]
    dg = -torch.exp(torch.tensor(gain, dtype=torch.float64)) * lev.li  # d r / d g
    ins = r[wt > 0]
    sigma = max(MIN_RESIDUAL_SIGMA, 1.4826 * float((ins - ins.median()).abs().median()))
    use = (wt > 0) & (r.abs() < 3 * sigma)
    Ju = torch.cat([J[use], dg[use][:, None]], 1)
    full = (Ju.T @ Ju).numpy() / sigma ** 2
    # the rotation's information with the gain marginalised (Schur complement): a turn across a
    # smooth ramp of brightness looks like an exposure step and fixes nothing
    return full[:3, :3] - np.outer(full[:3, 3], full[3, :3]) / max(full[3, 3], 1e-12)


def _spread(r: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Per candidate [S]: the robust spread (1.4826 MAD) of its residuals over its overlap."""
    out = torch.full((r.shape[0],), math.inf, dtype=r.dtype)
    for s in range(r.shape[0]):
        vals = r[s][w[s] > 0]
        if vals.numel() >= 8:
            out[s] = 1.4826 * (vals - vals.median()).abs().median()
    return out


def _noise(r: torch.Tensor, w: torch.Tensor) -> float:
    """The residual noise candidates are scored against: the smallest spread among those that
    keep MIN_OVERLAP in view (the right rotation's is the noise), at least MIN_SCORE_SIGMA."""
    ok = w.mean(1) >= MIN_OVERLAP
    spread = _spread(r, w)[ok]
    return max(MIN_SCORE_SIGMA, float(spread.min())) if spread.numel() else MIN_SCORE_SIGMA


def _score(r: torch.Tensor, w: torch.Tensor, sigma: float) -> torch.Tensor:
    """Per candidate [S], per pixel of frame i: min((r / sigma)^2, SCORE_CAP^2) over the overlap and
    OUTSIDE_COST for a pixel frame j does not show, `sigma` the smallest residual spread among the
    candidates compared (the right rotation's is the noise). Textured or blank, the right rotation
    explains its overlap at the noise level, where a wrong one leaves residuals of several sigma
    (capped: a pixel is either explained or not) or gives up pixels at OUTSIDE_COST each."""
    z = (r / sigma) ** 2
    score = ((z.clamp(max=SCORE_CAP ** 2) * w).sum(1) + OUTSIDE_COST * (1 - w).sum(1)) / w.shape[1]
    return torch.where(w.mean(1) >= MIN_OVERLAP, score, torch.full_like(score, math.inf))


def _refine(levels: list[_Level], R0: torch.Tensor, gain0: float) -> tuple[torch.Tensor, float]:
    """L-BFGS over a turn about R0 and the log gain, coarse to fine; the mean robust cost over the
    overlap (the overlap itself is held by starting close)."""
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    g = torch.tensor([gain0], dtype=torch.float64, requires_grad=True)
    for lev in levels:
        opt = torch.optim.LBFGS([w, g], lr=1.0, max_iter=LBFGS_ITERATIONS, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            R = torch.matrix_exp(_skew(w)) @ R0
            r, wt = lev.residuals(R[None], g)
            loss = (_robust(r) * wt).sum() / wt.sum().clamp_min(1.0)
            loss.backward()
            return loss

        opt.step(closure)
    with torch.no_grad():
        return torch.matrix_exp(_skew(w)) @ R0, float(g)


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


def track_rotation_direct(frames: torch.Tensor, k: Intrinsics, feature_pairs: dict | None = None) -> DirectTrack:
    """Rotations of every frame of a camera turning about one spot (module docstring).
    `feature_pairs` {(i, j): R bearing i -> j} are extra starting guesses from matched features."""
    l, v = frame_luma(frames)
    T = frames.shape[0]
    feature_pairs = feature_pairs or {}
    R: dict[int, np.ndarray] = {0: np.eye(3)}
    pairs: list[DirectPair] = []
    for f in range(1, T):
        starts = [np.eye(3)]
        if (c := _coast(R, f)) is not None:
            starts.insert(0, c)
        if (f - 1, f) in feature_pairs:
            starts.insert(0, feature_pairs[(f - 1, f)])
        p = align_pair(l[f - 1], v[f - 1], l[f], v[f], k, starts, f - 1, f)
        pairs.append(p)
        # a pair that fixes the rotation places the frame; else the camera coasts on (a blank
        # wall fixes nothing: the averaging below weighs what each pair does fix)
        step = p.R if p.trusted or c is None and p.matched else c
        R[f] = _nearest_rotation(R[f - 1] @ step.T)  # bearing_f = step bearing_{f-1}: R_f = R_{f-1} step^T
    chained = [p.j for p in pairs if p.trusted]
    axes = {f: R[f] @ np.array([0.0, 0.0, -1.0]) for f in R}
    loops = [(a, b) for a in range(T) for b in range(a + LOOP_MIN_GAP, T)
             if math.degrees(math.acos(float(np.clip(axes[a] @ axes[b], -1, 1)))) <= LOOP_MAX_AXIS_DEG][:MAX_LOOP_PAIRS]
    for a, b in loops:
        pairs.append(align_pair(l[a], v[a], l[b], v[b], k, [R[b].T @ R[a]], a, b, search=False))
    matched = [p for p in pairs if p.matched]
    rots = _average_rotations(T, matched, R)
    placed = _placed(T, [p for p in matched if p.trusted])
    stats = {"pairs": len(pairs), "matched_pairs": len(matched), "trusted_pairs": sum(p.trusted for p in pairs),
             "loop_pairs": len(loops), "loop_pairs_trusted": sum(p.trusted for p in pairs[T - 1:]),
             "chain_fixed": len(chained), "frames_fixed_by_pairs": len(placed),
             "frames_from_motion_prior": sorted(set(range(T)) - placed),
             "median_cost": float(np.median([p.cost for p in matched])) if matched else None}
    return DirectTrack(rots, list(range(T)), [], pairs, stats)


def _placed(T: int, pairs: list[DirectPair]) -> set[int]:
    """Frames connected to frame 0 by pairs that fix the rotation."""
    nbrs: dict[int, set[int]] = {}
    for p in pairs:
        nbrs.setdefault(p.i, set()).add(p.j)
        nbrs.setdefault(p.j, set()).add(p.i)
    seen, todo = {0}, [0]
    while todo:
        f = todo.pop()
        for g in nbrs.get(f, ()):
            if g not in seen:
                seen.add(g)
                todo.append(g)
    return seen


def _average_rotations(T: int, pairs: list[DirectPair], init: dict[int, np.ndarray]) -> np.ndarray:
    """c2w rotations [T, 3, 3] (frame 0 fixed at I) minimising, robustly, each pair's disagreement
    e_ij = rotvec(R_j^T R_i meas_ij^T) weighted by its information (e^T info e), plus a motion
    prior: consecutive turns differ by about MOTION_SIGMA_DEG (what keeps frames that no pair
    fixes on the camera's path)."""
    base = np.stack([init[f] for f in range(T)])
    if T < 2:
        return base
    meas = np.stack([p.R for p in pairs]) if pairs else np.zeros((0, 3, 3))
    ia, ib = np.array([p.i for p in pairs], int), np.array([p.j for p in pairs], int)
    L = np.stack([_sqrt_info(p.info) for p in pairs]) if pairs else np.zeros((0, 3, 3))
    prior = 1.0 / math.radians(MOTION_SIGMA_DEG)

    def rots(x):
        return np.concatenate([np.eye(3)[None], rotvec_to_matrix(x.reshape(-1, 3)) @ base[1:]])

    def residuals(x):
        Rk = rots(x)
        out = []
        if len(pairs):
            pred = np.transpose(Rk[ib], (0, 2, 1)) @ Rk[ia]  # R_j^T R_i
            e = matrix_to_rotvec(pred @ np.transpose(meas, (0, 2, 1)))
            out.append(np.einsum("nji,nj->ni", L, e).ravel())
        turn = matrix_to_rotvec(np.transpose(Rk[:-1], (0, 2, 1)) @ Rk[1:])  # each frame's turn, in its own axes
        out.append(prior * (turn[1:] - turn[:-1]).ravel())
        return np.concatenate(out)

    n_pair = 3 * len(pairs)
    sparsity = lil_matrix((n_pair + 3 * max(0, T - 2), 3 * (T - 1)), dtype=int)
    for n, (a, b) in enumerate(zip(ia, ib)):
        for q in (a, b):
            if q > 0:
                sparsity[3 * n:3 * n + 3, 3 * (q - 1):3 * q] = 1
    for f in range(T - 2):
        for q in (f, f + 1, f + 2):
            if q > 0:
                sparsity[n_pair + 3 * f:n_pair + 3 * f + 3, 3 * (q - 1):3 * q] = 1
    sol = least_squares(residuals, np.zeros(3 * (T - 1)), jac_sparsity=sparsity, loss="soft_l1", f_scale=3.0,
                        max_nfev=100)
    return rots(sol.x)


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
