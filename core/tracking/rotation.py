"""Camera rotation for a pan from one spot (the common phone case): centre fixed.

With a camera that only turns, two views are related by the homography K R K⁻¹, so the
matched bearings b of frames i and j satisfy b_j = R_jᵀ R_i b_i with the c2w rotations R:
1. every scheduled pair: a relative rotation from matched bearings (2-point Kabsch inside
   RANSAC; inlier threshold tracking.rotation.inlier_px reprojected);
2. initial rotations grown frame by frame over the largest set of frames the pairs connect,
   from its first frame (R = I there: world = the first kept camera frame), each frame placed
   where most of its pairs with the placed frames agree (`_consensus_tree`; every pair offers
   the rotation most of its matches agree on and a second one among the rest, so that someone
   walking through the view, whose features agree with each other, is outvoted by the room);
3. a small bundle adjustment (Brown & Lowe's panorama formulation: symmetric transfer error
   of every inlier match through the two rotations; scipy least_squares with the Jacobian's
   sparsity, twice: all RANSAC inliers, then those within tracking.rotation.inlier_px of the first solution —
   a Huber loss converged ~10x slower in scipy's trust region for the same answer), optionally refining the focal length
   too (self-calibration: a pan of
   more than ~15 deg fixes it), and with a rolling shutter (`readout`, below).
A phone reads its rows out one after another, so under a brisk pan each row sees the camera a
little further on and the frame is sheared (or, held in portrait, stretched along the pan). The
bundle adjustment models it with one number for the clip, the readout r (frame intervals from
the first row to the last, signed: which end is read first): a pixel is read at
tau = r (v - cy) / H frame intervals after the frame's centre, or r (u - cx) / W in a portrait
frame (core.conventions.sensor_readout_direction: the short side), and the camera then is
Exp(w tau) R, with w the frame's angular velocity from its neighbours' rotations (a constant
turn over one frame). The row that sees a match is dated where the model predicts it: dating it
where the match was found let the noise push the readout up. A global shutter fits r = 0; the
rotations are the cameras at the frames' centre rows. The readout is fitted from the
global-shutter solution, on clips that one leaves close to a pan (tracking.rotation.rolling_max_ratio), and only
along the short side: a free readout along the long side of a landscape pan traded with the
focal length in trials on dev pans and made the rotations worse.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, lil_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from core.camera import Intrinsics
from core.conventions import sensor_readout_direction
from core.tracking.config import RotationConfig, tracking_config
from core.tracking.features import PairMatches
from core.tracking.geometry import bearings, kabsch, matrix_to_rotvec, project, rotation_angle_deg, rotvec_to_matrix


def _knobs() -> RotationConfig:
    return tracking_config().rotation


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
    readout: float = 0.0  # rolling shutter: frame intervals from the first row read to the last
    readout_direction: tuple[float, float] | None = None  # the axis the rows are read along (core.conventions)

    def predict(
        self, xa: np.ndarray, a: np.ndarray, xb: np.ndarray, b: np.ndarray, k: Intrinsics
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pixels xa of kept positions a seen in kept positions b (xb: where they were matched, the
        start of the search for the row that saw them): (pixels [M, 2], planar depth [M])."""
        return _transfer(self.rotations, np.asarray(self.kept), self.readout, self.readout_direction, xa, a, xb, b, k,
                         self.focal)

    @property
    def fits(self) -> bool:
        explained = self.parallax_px <= max(_knobs().fit_floor_px, _knobs().fit_ratio * self.epipolar_px)
        return explained and self.inlier_share >= _knobs().fit_inlier_share


def _batched_kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotations [S, 3, 3] minimising |b - R a|^2 for batches of unit vectors a, b [S, n, 3]."""
    u, _, vt = np.linalg.svd(np.einsum("sni,snj->sij", a, b))
    d = np.sign(np.linalg.det(np.einsum("sji,skj->sik", vt, u)))
    d[d == 0] = 1.0
    fix = np.broadcast_to(np.eye(3), (len(d), 3, 3)).copy()
    fix[:, 2, 2] = d
    return np.einsum("sji,sjk,slk->sil", vt, fix, u)


def relative_rotations(m: PairMatches, k: Intrinsics, seed: int = 0) -> list[RelativeRotation]:
    """A pair's candidate rotations: the one most matches agree on and, among the matches it
    leaves, a second one (`_ransac_rotation`). Someone walking through a pan moves their own
    features one way and the room's another: where they carry more features than the room, the
    first candidate is theirs and the room's is the second. Which one is the camera's is decided
    across pairs (`_consensus_tree`)."""
    if len(m) < _knobs().min_inliers:
        return []
    bi, bj = bearings(m.xi, k), bearings(m.xj, k)
    rng = np.random.default_rng(seed)
    out, free = [], np.ones(len(bi), dtype=bool)
    for _ in range(_knobs().pair_hypotheses):
        found = _ransac_rotation(bi, bj, free, rng, _knobs().inlier_px / k.fx)  # angle (radians) ~ pixels / focal
        if found is None:
            break
        R, best = found
        keep = np.flatnonzero(best)
        if len(keep) > _knobs().max_pair_observations:  # enough to constrain 6 numbers; bounds the BA's cost
            keep = keep[np.linspace(0, len(keep) - 1, _knobs().max_pair_observations).round().astype(int)]
        out.append(RelativeRotation(m.i, m.j, R, m.xi[keep], m.xj[keep], len(m)))
        free &= ~best
        if free.sum() < _knobs().min_inliers:
            break
    return out


def _ransac_rotation(bi: np.ndarray, bj: np.ndarray, usable: np.ndarray, rng, thr: float):
    """(R, inliers [N] among `usable`) of the rotation the most usable bearings agree on (2-point
    Kabsch inside RANSAC, refitted twice), or None with fewer than tracking.rotation.min_inliers."""
    idx = np.flatnonzero(usable)
    if len(idx) < _knobs().min_inliers:
        return None
    samples = idx[np.stack([rng.choice(len(idx), 2, replace=False) for _ in range(_knobs().ransac_iterations)])]
    hyp = _batched_kabsch(bi[samples], bj[samples])  # [S, 3, 3]
    err = np.linalg.norm(bj[None] - np.einsum("sij,nj->sni", hyp, bi), axis=-1)
    ok = (err < thr) & usable[None]
    best = ok[int(ok.sum(1).argmax())]
    if best.sum() < _knobs().min_inliers:
        return None
    for _ in range(2):  # refit on inliers, re-select
        R = kabsch(bi[best], bj[best])
        best = (np.linalg.norm(bj - bi @ R.T, axis=1) < thr) & usable
    if best.sum() < _knobs().min_inliers:
        return None
    return R, best


def _root(n: int, rel: list[RelativeRotation]) -> int:
    """The first frame of the largest set of frames the pairs connect (ties: the earliest set).
    Not frame 0 as such: a first frame that matched nothing (dark, blurred, a cut) must not lose
    the clip."""
    if not rel:
        return 0
    graph = coo_matrix((np.ones(len(rel)), ([r.i for r in rel], [r.j for r in rel])), shape=(n, n))
    labels = connected_components(graph, directed=False)[1]
    sizes = np.bincount(labels)
    return int(np.flatnonzero(sizes[labels] == sizes.max())[0])


def _consensus_tree(n: int, rel: list[RelativeRotation]) -> tuple[dict[int, np.ndarray], list[int]]:
    """Initial rotations, grown frame by frame from the root (`_root`, R = I there). Each frame
    not yet placed that shares pairs with the placed ones gets one candidate rotation per
    candidate of those pairs; a candidate's support is the number of those pairs with a
    candidate within tracking.rotation.consensus_deg of it. The frame and candidate with the most support is
    placed next (ties: a frame next to two placed ones, with the candidate nearest
    `_coasting`'s rotation; else the candidate nearest those that agree with it). Something
    moving through the view agrees with itself only over the frames it is in, while the room
    agrees across every pair that reaches a frame it is not in, so the room wins the vote even
    where it has fewer features in a pair."""
    root = _root(n, rel)
    R = {root: np.eye(3)}
    by_frame: dict[int, list[tuple[RelativeRotation, int]]] = {}
    for r in rel:  # each candidate, from the side of either frame
        by_frame.setdefault(r.j, []).append((r, r.i))
        by_frame.setdefault(r.i, []).append((r, r.j))
    while True:
        best = None
        for f, links in by_frame.items():
            if f in R:
                continue
            placed = [(r, other) for r, other in links if other in R]
            if not placed:
                continue
            # r.R = R_j^T R_i: R_j = R_i r.R^T, R_i = R_j r.R
            cands = np.stack([R[o] @ r.R.T if f == r.j else R[o] @ r.R for r, o in placed])
            pair = np.array([r.i * n + r.j for r, _ in placed])
            cos = np.clip((np.einsum("aij,bij->ab", cands, cands) - 1.0) / 2.0, -1.0, 1.0)
            angle = np.degrees(np.arccos(cos))
            close = angle <= _knobs().consensus_deg
            coasting = _coasting(R, f)
            for a in range(len(placed)):
                # the most pairs agreeing, then the candidate nearest the camera coasting on from
                # its two placed neighbours, or (without them) nearest the others that agree
                off = (
                    rotation_angle_deg(cands[a].T @ coasting)
                    if coasting is not None
                    else float(angle[a, close[a]].mean())
                )
                score = (len(np.unique(pair[close[a]])), coasting is not None, -off)
                if best is None or score > best[0]:
                    best = (score, f, cands[a])
        if best is None:
            break
        R[best[1]] = best[2]
    return R, sorted(set(range(n)) - set(R))


def _coasting(R: dict[int, np.ndarray], f: int) -> np.ndarray | None:
    """Frame f's rotation if the camera kept turning as it did between its two placed
    neighbours on one side (a camera has inertia; someone walking through the view does not
    move it), or None."""
    for a, b in ((f - 1, f - 2), (f + 1, f + 2)):
        if a in R and b in R:
            return R[a] @ (R[b].T @ R[a])
    return None


def _agreeing(rel: list[RelativeRotation], R: dict[int, np.ndarray]) -> list[RelativeRotation]:
    """Per pair between placed frames, the candidate closest to what the placed rotations say,
    if within tracking.rotation.agree_deg (a pair none of whose candidates agrees is left out)."""
    chosen: dict[tuple[int, int], tuple[float, RelativeRotation]] = {}
    for r in rel:
        if r.i not in R or r.j not in R:
            continue
        off = rotation_angle_deg((R[r.j].T @ R[r.i]).T @ r.R)
        if off <= _knobs().agree_deg and ((r.i, r.j) not in chosen or off < chosen[(r.i, r.j)][0]):
            chosen[(r.i, r.j)] = (off, r)
    return [r for _, r in chosen.values()]


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


def _neighbours(n_kept: int) -> tuple[np.ndarray, np.ndarray]:
    """Kept positions before and after each one (itself at the ends): a frame's angular velocity
    is the turn between them."""
    n = np.arange(n_kept)
    return np.maximum(n - 1, 0), np.minimum(n + 1, n_kept - 1)


def angular_velocities(rots: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """[K, 3] world-frame rotation vectors per frame interval: central differences of the c2w
    rotations over the kept frames (one-sided at the ends; frame numbers date them)."""
    if len(rots) < 2:
        return np.zeros((len(rots), 3))
    prev, nxt = _neighbours(len(rots))
    turn = matrix_to_rotvec(rots[nxt] @ np.transpose(rots[prev], (0, 2, 1)))
    return turn / (frames[nxt] - frames[prev]).astype(np.float64)[:, None]


def read_times(x: np.ndarray, readout: float, direction: tuple[float, float], k: Intrinsics) -> np.ndarray:
    """Frame intervals after the frame's centre at which pixels [M, 2] were read."""
    return readout * (direction[0] * (x[:, 0] - k.cx) / k.width + direction[1] * (x[:, 1] - k.cy) / k.height)


def _transfer(rots, frames, readout, direction, xa, a, xb, b, k: Intrinsics, focal):
    d = np.einsum("mij,mj->mi", rots[a], bearings(xa, k, focal))  # world rays at the frames' centres
    if readout:
        w = angular_velocities(rots, frames)
        d = Rotation.from_rotvec(w[a] * read_times(xa, readout, direction, k)[:, None]).apply(d)
        uv = xb
        for _ in range(2):  # the row that sees it, dated where it is predicted (fixed point; xb only starts it)
            uv, z = project(np.einsum("mji,mj->mi", rots[b], Rotation.from_rotvec(
                -w[b] * read_times(uv, readout, direction, k)[:, None]).apply(d)), k, focal)
        return uv, z
    return project(np.einsum("mji,mj->mi", rots[b], d), k, focal)  # R_b^T d


def _unpack(params: np.ndarray, n_kept: int, k: Intrinsics, refine_focal: bool, rolling: bool):
    rots = np.concatenate([np.eye(3)[None], rotvec_to_matrix(params[: 3 * (n_kept - 1)])])
    readout = float(params[3 * (n_kept - 1)]) if rolling else 0.0
    return rots, (float(np.exp(params[-1])) * k.fx if refine_focal else None), readout


def _residuals(params: np.ndarray, obs: _Observations, frames: np.ndarray, k: Intrinsics, refine_focal: bool,
               rolling: bool, direction: tuple[float, float]) -> np.ndarray:
    rots, focal, readout = _unpack(params, len(frames), k, refine_focal, rolling)
    uv, z = _transfer(rots, frames, readout, direction, obs.xa, obs.a, obs.xb, obs.b, k, focal)
    res = uv - obs.xb
    res[z <= 0] = 1e3  # a match behind the other camera: as wrong as it gets
    return res.reshape(-1)


def _sparsity(obs: _Observations, n_kept: int, refine_focal: bool, rolling: bool):
    """Each residual moves with its two frames' rotations, and with a rolling shutter with
    their neighbours' too (the angular velocities), the readout and the focal length."""
    globals_ = int(rolling) + int(refine_focal)
    cols = 3 * (n_kept - 1) + globals_
    A = lil_matrix((2 * len(obs.a), cols), dtype=int)
    rows = np.arange(2 * len(obs.a))
    prev, nxt = _neighbours(n_kept)
    for frames in (obs.a, obs.b):
        for near in ((frames, prev[frames], nxt[frames]) if rolling else (frames,)):
            f = np.repeat(near, 2)
            sel = f > 0
            for c in range(3):
                A[rows[sel], 3 * (f[sel] - 1) + c] = 1
    if globals_:
        A[:, cols - globals_:] = 1
    return A


def estimate_rotations(pairs: list[PairMatches], n_frames: int, k: Intrinsics, refine_focal: bool = False,
                       max_nfev: int = 30, rolling_shutter: bool = True) -> RotationTrack:
    """Rotations of a pan's frames (module docstring): a global shutter first, then, from it, the
    rolling shutter where the motion is a pan at all (tracking.rotation.rolling_max_ratio); `rolling_shutter=False`
    stops at the global one."""
    rel = [r for m in pairs for r in relative_rotations(m, k, seed=m.i * 1000 + m.j)]
    init, dropped = _consensus_tree(n_frames, rel)
    kept = sorted(init)
    rel = _agreeing(rel, init)
    if len(kept) < 2 or not rel:
        return RotationTrack(np.eye(3)[None], [0], dropped, k.fx, math.inf, math.inf, 0.0, 0, 0)
    x0 = matrix_to_rotvec(np.stack([init[f] for f in kept[1:]])).reshape(-1)
    if refine_focal:
        x0 = np.r_[x0, 0.0]
    essential = essential_evidence(pairs, k)
    track, x = _adjust(x0, kept, dropped, rel, k, refine_focal, False, max_nfev)
    track.parallax_px, track.epipolar_px = parallax_evidence(essential, track, k)
    if not (rolling_shutter and len(kept) > 2 and track.parallax_px <= _knobs().rolling_max_ratio * track.epipolar_px):
        return track  # two frames have no angular velocity to shear by; a walk is no pan either way
    x1 = np.r_[x[: 3 * (len(kept) - 1)], 0.0, x[3 * (len(kept) - 1):]]  # readout 0 before the focal
    rolling, _ = _adjust(x1, kept, dropped, rel, k, refine_focal, True, max_nfev)
    rolling.stats["ba_evaluations"] += track.stats["ba_evaluations"]
    rolling.parallax_px, rolling.epipolar_px = parallax_evidence(essential, rolling, k)
    return rolling


def _adjust(x0: np.ndarray, kept: list[int], dropped: list[int], rel: list[RelativeRotation], k: Intrinsics,
            refine_focal: bool, rolling: bool, max_nfev: int) -> tuple[RotationTrack, np.ndarray]:
    """The bundle adjustment from x0 (rotation vectors of kept[1:], the readout if `rolling`,
    log focal ratio if `refine_focal`): the track (without the parallax evidence) and its parameters."""
    direction = sensor_readout_direction(k.width, k.height)
    frames = np.asarray(kept)
    lower, upper = np.full(len(x0), -np.inf), np.full(len(x0), np.inf)
    if rolling:
        lower[3 * (len(kept) - 1)], upper[3 * (len(kept) - 1)] = -_knobs().max_readout, _knobs().max_readout
    obs = _Observations.build(kept, rel)
    x, nfev = x0, 0
    for _ in range(_knobs().ba_rounds):  # least squares on the inliers, re-select, again
        sol = least_squares(
            _residuals,
            x,
            jac_sparsity=_sparsity(obs, len(kept), refine_focal, rolling),
            x_scale=1.0,
            bounds=(lower, upper),
            max_nfev=max_nfev,
            args=(obs, frames, k, refine_focal, rolling, direction),
        )
        x, nfev = sol.x, nfev + sol.nfev
        keep = np.linalg.norm(sol.fun.reshape(-1, 2), axis=1) < _knobs().inlier_px
        if keep.all() or keep.sum() < _knobs().min_inliers:
            break
        obs = _Observations(obs.xa[keep], obs.xb[keep], obs.a[keep], obs.b[keep])
    err = np.linalg.norm(_residuals(x, _Observations.build(kept, rel), frames, k, refine_focal, rolling, direction)
                         .reshape(-1, 2), axis=1)
    inl = err < _knobs().inlier_px
    rots, focal, readout = _unpack(x, len(kept), k, refine_focal, rolling)
    track = RotationTrack(
        rotations=rots, kept=kept, dropped=dropped, focal=focal or k.fx,
        median_px=float(np.median(err)), rms_px=float(np.sqrt(np.mean(err[inl] ** 2))) if inl.any() else math.inf,
        inlier_share=float(inl.mean()),  # of the RANSAC inliers the BA used, both directions
        residuals=int(len(err)), pairs=len(rel),
        stats={"ba_evaluations": int(nfev), "matches": int(sum(len(r.xi) for r in rel))},
        readout=readout, readout_direction=direction,
    )
    return track, x


def _sampson_px(E: np.ndarray, a: np.ndarray, b: np.ndarray, f: float) -> np.ndarray:
    """Sampson distance (pixels) of normalised correspondences a -> b [N, 2] under E."""
    ah = np.concatenate([a, np.ones((len(a), 1))], 1)
    bh = np.concatenate([b, np.ones((len(b), 1))], 1)
    Ea, Etb = ah @ E.T, bh @ E
    num = np.einsum("ni,ni->n", bh, Ea) ** 2
    den = Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Etb[:, 0] ** 2 + Etb[:, 1] ** 2
    return f * np.sqrt(num / np.maximum(den, 1e-18))


@dataclass(frozen=True)
class EssentialFit:
    """One pair's matches that an essential matrix explains (RANSAC) and their Sampson residuals."""

    i: int
    j: int
    xi: np.ndarray
    xj: np.ndarray
    sampson_px: np.ndarray


def essential_evidence(pairs: list[PairMatches], k: Intrinsics) -> list[EssentialFit]:
    """Per pair with enough matches, the essential matrix's inliers (fitted once per clip: the
    global and the rolling-shutter track are both compared with them)."""
    out = []
    for m in pairs:
        if len(m) < _knobs().essential_min_inliers:
            continue
        a = np.stack(((m.xi[:, 0] - k.cx) / k.fx, (m.xi[:, 1] - k.cy) / k.fy), 1)
        b = np.stack(((m.xj[:, 0] - k.cx) / k.fx, (m.xj[:, 1] - k.cy) / k.fy), 1)
        E, mask = cv2.findEssentialMat(a, b, np.eye(3), cv2.RANSAC, 0.999, _knobs().inlier_px / k.fx)
        if E is None or E.shape != (3, 3):
            continue
        inl = mask.ravel() > 0
        if inl.sum() < _knobs().essential_min_inliers:
            continue
        out.append(EssentialFit(m.i, m.j, m.xi[inl], m.xj[inl], _sampson_px(E, a[inl], b[inl], k.fx)))
    return out


def parallax_evidence(essential: list[EssentialFit], track: RotationTrack, k: Intrinsics) -> tuple[float, float]:
    """(median rotation-model residual, median essential-matrix residual) in pixels over the
    matches an essential matrix explains, pooled over the pairs both models saw.
    A pure rotation fits both to the noise level (E is then free in its translation); parallax
    raises only the rotation model's residual, which no choice of rotation removes."""
    pos = {f: n for n, f in enumerate(track.kept)}
    rot_res, e_res = [], []
    for e in essential:
        if e.i not in pos or e.j not in pos:
            continue
        n = len(e.xi)
        uv, _ = track.predict(e.xi, np.full(n, pos[e.i]), e.xj, np.full(n, pos[e.j]), k)
        rot_res.append(np.linalg.norm(uv - e.xj, axis=1))
        e_res.append(e.sampson_px)
    if not e_res:
        return math.inf, math.inf
    return float(np.median(np.concatenate(rot_res))), float(np.median(np.concatenate(e_res)))
