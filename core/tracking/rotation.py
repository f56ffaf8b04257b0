"""Camera rotation for a pan from one spot (the common phone case): centre fixed.

With a camera that only turns, two views are related by the homography K R K⁻¹, so the
matched bearings b of frames i and j satisfy b_j = R_jᵀ R_i b_i with the c2w rotations R:
1. every scheduled pair: a relative rotation from matched bearings (2-point Kabsch inside
   RANSAC; inlier threshold INLIER_PX reprojected);
2. initial rotations by walking the maximum spanning tree of the pair graph (weights =
   inliers) from frame 0 (R_0 = I: world = first camera frame);
3. a small bundle adjustment (Brown & Lowe's panorama formulation: symmetric transfer error
   of every inlier match through the two rotations; scipy least_squares with the Jacobian's
   sparsity, twice: all RANSAC inliers, then those within INLIER_PX of the first solution —
   a Huber loss converged ~10x slower in scipy's trust region for the same answer), optionally refining the focal length too (self-calibration: a pan of
   more than ~15 deg fixes it).
Frames that no pair links to frame 0 are dropped and listed. Whether the rotation model
explains the motion is a model comparison (`parallax_evidence`, `RotationTrack.fits`): on the
matches an essential matrix explains, a pure rotation leaves residuals at the noise level as
the essential matrix does, while parallax from a moving centre leaves residuals that no
rotation removes (an absolute threshold is not enough: a sideways walk past one wall looks
like a turn to most features).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from core.camera import Intrinsics
from core.tracking.features import PairMatches
from core.tracking.geometry import bearings, kabsch, matrix_to_rotvec, project, rotvec_to_matrix

INLIER_PX = 2.0
MIN_INLIERS = 15
RANSAC_ITERATIONS = 200
BA_ROUNDS = 2
MAX_PAIR_OBSERVATIONS = 150
# The rotation model explains the motion when at least FIT_INLIER_SHARE of the matches are its
# inliers and its median residual is within FIT_RATIO of an essential matrix's on the same
# matches (parallax raises only the former), or below FIT_FLOOR_PX (pixels at the analysis
# resolution: translation too small to matter). Measured on panorama-room clips: pans 1.1-1.3x
# (H.264 included), a 1.3 m walk 4.8-10x.
FIT_RATIO = 2.0
FIT_FLOOR_PX = 0.3
FIT_INLIER_SHARE = 0.6


@dataclass
class RelativeRotation:
    i: int
    j: int
    R: np.ndarray  # R_j^T R_i (bearing of i -> bearing of j)
    xi: np.ndarray  # inlier pixels
    xj: np.ndarray
    matches: int


@dataclass
class RotationTrack:
    rotations: np.ndarray  # [K, 3, 3] c2w rotations of the kept frames (kept[0] has I)
    kept: list[int]
    dropped: list[int]
    focal: float  # analysis-resolution fx after refinement (= the input's when not refined)
    median_px: float
    rms_px: float
    inlier_share: float
    residuals: int
    pairs: int
    stats: dict = field(default_factory=dict)
    parallax_px: float = math.inf  # median rotation-model residual on the essential matrices' inliers
    epipolar_px: float = math.inf  # median essential-matrix (Sampson) residual on the same matches

    @property
    def fits(self) -> bool:
        explained = self.parallax_px <= max(FIT_FLOOR_PX, FIT_RATIO * self.epipolar_px)
        return explained and self.inlier_share >= FIT_INLIER_SHARE


def _batched_kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotations [S, 3, 3] minimising |b - R a|^2 for batches of unit vectors a, b [S, n, 3]."""
    u, _, vt = np.linalg.svd(np.einsum("sni,snj->sij", a, b))
    d = np.sign(np.linalg.det(np.einsum("sji,skj->sik", vt, u)))
    d[d == 0] = 1.0
    fix = np.broadcast_to(np.eye(3), (len(d), 3, 3)).copy()
    fix[:, 2, 2] = d
    return np.einsum("sji,sjk,slk->sil", vt, fix, u)


def relative_rotation(m: PairMatches, k: Intrinsics, seed: int = 0) -> RelativeRotation | None:
    if len(m) < MIN_INLIERS:
        return None
    bi, bj = bearings(m.xi, k), bearings(m.xj, k)
    rng = np.random.default_rng(seed)
    thr = INLIER_PX / k.fx  # angle (radians) ~ pixels / focal
    samples = np.stack([rng.choice(len(bi), 2, replace=False) for _ in range(RANSAC_ITERATIONS)])
    hyp = _batched_kabsch(bi[samples], bj[samples])  # [S, 3, 3]
    err = np.linalg.norm(bj[None] - np.einsum("sij,nj->sni", hyp, bi), axis=-1)
    best = err[int((err < thr).sum(1).argmax())] < thr
    if best.sum() < MIN_INLIERS:
        return None
    for _ in range(2):  # refit on inliers, re-select
        R = kabsch(bi[best], bj[best])
        best = np.linalg.norm(bj - bi @ R.T, axis=1) < thr
    if best.sum() < MIN_INLIERS:
        return None
    keep = np.flatnonzero(best)
    if len(keep) > MAX_PAIR_OBSERVATIONS:  # enough to constrain 6 numbers; bounds the BA's cost
        keep = keep[np.linspace(0, len(keep) - 1, MAX_PAIR_OBSERVATIONS).round().astype(int)]
    return RelativeRotation(m.i, m.j, R, m.xi[keep], m.xj[keep], len(m))


def _spanning_tree(n: int, rel: list[RelativeRotation]) -> tuple[dict[int, np.ndarray], list[int]]:
    """Initial rotations: Prim's maximum spanning tree from frame 0 over inlier counts."""
    R = {0: np.eye(3)}
    edges = sorted(rel, key=lambda r: -len(r.xi))
    grown = True
    while grown:
        grown = False
        for r in edges:
            if (r.i in R) == (r.j in R):
                continue
            if r.i in R:  # R_j = R_i R_rel^T
                R[r.j] = R[r.i] @ r.R.T
            else:  # R_i = R_j R_rel
                R[r.i] = R[r.j] @ r.R
            grown = True
            break
    return R, sorted(set(range(n)) - set(R))


@dataclass(frozen=True)
class _Observations:
    """Every inlier match in both directions, stacked: pixel xa in frame a predicts xb in b."""

    xa: np.ndarray  # [M, 2]
    xb: np.ndarray  # [M, 2]
    a: np.ndarray  # [M] positions in `kept`
    b: np.ndarray  # [M]

    @classmethod
    def build(cls, kept: list[int], rel: list[RelativeRotation]) -> "_Observations":
        pos = {f: n for n, f in enumerate(kept)}
        xa, xb, a, b = [], [], [], []
        for r in rel:
            for p, q, fa, fb in ((r.xi, r.xj, r.i, r.j), (r.xj, r.xi, r.j, r.i)):
                xa.append(p), xb.append(q)
                a.append(np.full(len(p), pos[fa])), b.append(np.full(len(p), pos[fb]))
        return cls(np.concatenate(xa), np.concatenate(xb), np.concatenate(a), np.concatenate(b))


def _unpack(params: np.ndarray, n_kept: int, k: Intrinsics, refine_focal: bool):
    rots = np.concatenate([np.eye(3)[None], rotvec_to_matrix(params[: 3 * (n_kept - 1)])])
    return rots, (float(np.exp(params[-1])) * k.fx if refine_focal else None)


def _residuals(params: np.ndarray, obs: _Observations, n_kept: int, k: Intrinsics, refine_focal: bool) -> np.ndarray:
    rots, focal = _unpack(params, n_kept, k, refine_focal)
    rel = np.einsum("mki,mkj->mij", rots[obs.b], rots[obs.a])  # R_b^T R_a per observation
    p = np.einsum("mij,mj->mi", rel, bearings(obs.xa, k, focal))
    uv, z = project(p, k, focal)
    res = uv - obs.xb
    res[z <= 0] = 1e3  # a match behind the other camera: as wrong as it gets
    return res.reshape(-1)


def _sparsity(obs: _Observations, n_kept: int, refine_focal: bool):
    cols = 3 * (n_kept - 1) + int(refine_focal)
    A = lil_matrix((2 * len(obs.a), cols), dtype=int)
    rows = np.arange(2 * len(obs.a))
    for frames in (obs.a, obs.b):
        f = np.repeat(frames, 2)
        for c in range(3):
            sel = f > 0
            A[rows[sel], 3 * (f[sel] - 1) + c] = 1
    if refine_focal:
        A[:, cols - 1] = 1
    return A


def estimate_rotations(pairs: list[PairMatches], n_frames: int, k: Intrinsics, refine_focal: bool = False,
                       max_nfev: int = 30) -> RotationTrack:
    rel = [r for r in (relative_rotation(m, k, seed=m.i * 1000 + m.j) for m in pairs) if r is not None]
    init, dropped = _spanning_tree(n_frames, rel)
    kept = sorted(init)
    rel = [r for r in rel if r.i in init and r.j in init]
    matches = sum(len(r.xi) for r in rel)
    if len(kept) < 2 or not rel:
        return RotationTrack(np.eye(3)[None], [0], dropped, k.fx, math.inf, math.inf, 0.0, 0, 0)
    x0 = matrix_to_rotvec(np.stack([init[f] for f in kept[1:]])).reshape(-1)
    if refine_focal:
        x0 = np.concatenate([x0, [0.0]])
    obs = _Observations.build(kept, rel)
    x, nfev = x0, 0
    for _ in range(BA_ROUNDS):  # least squares on the inliers, re-select, again
        sol = least_squares(_residuals, x, jac_sparsity=_sparsity(obs, len(kept), refine_focal), x_scale=1.0,
                            max_nfev=max_nfev, args=(obs, len(kept), k, refine_focal))
        x, nfev = sol.x, nfev + sol.nfev
        keep = np.linalg.norm(sol.fun.reshape(-1, 2), axis=1) < INLIER_PX
        if keep.all() or keep.sum() < MIN_INLIERS:
            break
        obs = _Observations(obs.xa[keep], obs.xb[keep], obs.a[keep], obs.b[keep])
    err = np.linalg.norm(_residuals(x, _Observations.build(kept, rel), len(kept), k, refine_focal).reshape(-1, 2), axis=1)
    inl = err < INLIER_PX
    rots, focal = _unpack(x, len(kept), k, refine_focal)
    focal = focal or k.fx
    inlier_share = float(inl.mean())  # of the RANSAC inliers the BA used, both directions
    track = RotationTrack(
        rotations=rots, kept=kept, dropped=dropped, focal=focal,
        median_px=float(np.median(err)), rms_px=float(np.sqrt(np.mean(err[inl] ** 2))) if inl.any() else math.inf,
        inlier_share=inlier_share, residuals=int(len(err)), pairs=len(rel),
        stats={"ba_evaluations": int(nfev), "matches": int(matches)},
    )
    track.parallax_px, track.epipolar_px = parallax_evidence(pairs, track, k)
    return track


def _sampson_px(E: np.ndarray, a: np.ndarray, b: np.ndarray, f: float) -> np.ndarray:
    """Sampson distance (pixels) of normalised correspondences a -> b [N, 2] under E."""
    ah = np.concatenate([a, np.ones((len(a), 1))], 1)
    bh = np.concatenate([b, np.ones((len(b), 1))], 1)
    Ea, Etb = ah @ E.T, bh @ E
    num = np.einsum("ni,ni->n", bh, Ea) ** 2
    den = Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Etb[:, 0] ** 2 + Etb[:, 1] ** 2
    return f * np.sqrt(num / np.maximum(den, 1e-18))


def parallax_evidence(pairs: list[PairMatches], track: RotationTrack, k: Intrinsics) -> tuple[float, float]:
    """(median rotation-model residual, median essential-matrix residual) in pixels over the
    matches an essential matrix explains (RANSAC), pooled over the pairs both models saw.
    A pure rotation fits both to the noise level (E is then free in its translation); parallax
    raises only the rotation model's residual, which no choice of rotation removes."""
    import cv2

    pos = {f: n for n, f in enumerate(track.kept)}
    rot_res, e_res = [], []
    for m in pairs:
        if len(m) < MIN_INLIERS or m.i not in pos or m.j not in pos:
            continue
        a = np.stack(((m.xi[:, 0] - k.cx) / k.fx, (m.xi[:, 1] - k.cy) / k.fy), 1)
        b = np.stack(((m.xj[:, 0] - k.cx) / k.fx, (m.xj[:, 1] - k.cy) / k.fy), 1)
        E, mask = cv2.findEssentialMat(a, b, np.eye(3), cv2.RANSAC, 0.999, INLIER_PX / k.fx)
        if E is None or E.shape != (3, 3):
            continue
        inl = mask.ravel() > 0
        if inl.sum() < MIN_INLIERS:
            continue
        e_res.append(_sampson_px(E, a[inl], b[inl], k.fx))
        R = track.rotations[pos[m.j]].T @ track.rotations[pos[m.i]]
        uv, _ = project(bearings(m.xi[inl], k, track.focal) @ R.T, k, track.focal)
        rot_res.append(np.linalg.norm(uv - m.xj[inl], axis=1))
    if not e_res:
        return math.inf, math.inf
    return float(np.median(np.concatenate(rot_res))), float(np.median(np.concatenate(e_res)))
