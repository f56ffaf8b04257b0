"""Fallback structure from motion with OpenCV: two-view initialisation, then PnP per frame.

Used when COLMAP finds no model. A small incremental tracker:
1. Initial pair: frame 0 and, of the next tracking.twoview.init_candidates frames, the one whose matches a
   homography explains least (parallax, not just rotation); essential matrix (RANSAC) and
   `recoverPose`, inliers triangulated (positive depth, reprojection under tracking.twoview.max_reproj_px in
   both views, parallax at least tracking.twoview.min_parallax_deg).
2. Every other frame, nearest to the registered ones first: 2D-3D correspondences through
   its matches with registered frames, `solvePnPRansac` + iterative refinement; then new
   points triangulated with each registered neighbour (parallax at least tracking.twoview.min_parallax_deg).
3. A bundle adjustment of all poses and points (frame 0 fixed), without which the chained
   PnP drifts by degrees over a 20-frame walk.
OpenCV's pixel centres are at integers and its camera looks along +z with y down, so
pixels are shifted by 0.5 and poses converted with core.conventions.OPENCV_TO_OURS
(core.tracking.geometry). Output has the same shape as the COLMAP path (`SfMTrack`).
"""
from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from core.camera import Intrinsics
from core.tracking.config import tracking_config
from core.tracking.features import FrameFeatures, PairMatches, match
from core.tracking.geometry import opencv_w2c_to_c2w, relative_to_first, rotvec_to_matrix
from core.tracking.sfm import SfMTrack


def _k_cv(k: Intrinsics) -> np.ndarray:
    return np.array([[k.fx, 0, k.cx - 0.5], [0, k.fy, k.cy - 0.5], [0, 0, 1]], np.float64)


def _reproject(K, Rt: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pc = X @ Rt[:, :3].T + Rt[:, 3]
    uv = pc @ K.T
    return uv[:, :2] / uv[:, 2:3], pc[:, 2]


class _Tracker:
    def __init__(self, features: list[FrameFeatures], k: Intrinsics):
        self.f, self.k, self.K = features, k, _k_cv(k)
        self.cfg = tracking_config().twoview
        self.cv = [f.points - 0.5 for f in features]  # OpenCV pixel coordinates
        self.Rt: dict[int, np.ndarray] = {}  # frame -> 3x4 OpenCV world-to-camera
        self.points: list[np.ndarray] = []
        self.point_of: dict[tuple[int, int], int] = {}  # (frame, feature) -> point
        self._matches: dict[tuple[int, int], PairMatches] = {}

    def matches(self, a: int, b: int) -> PairMatches:
        key = (min(a, b), max(a, b))
        if key not in self._matches:
            self._matches[key] = match(self.f[key[0]], self.f[key[1]], *key)
        m = self._matches[key]
        return m if a < b else PairMatches(b, a, m.xj, m.xi, m.jj, m.ii)

    def triangulate(self, a: int, b: int, ia: np.ndarray, ib: np.ndarray) -> int:
        Pa, Pb = self.K @ self.Rt[a], self.K @ self.Rt[b]
        Xh = cv2.triangulatePoints(Pa, Pb, self.cv[a][ia].T, self.cv[b][ib].T)
        X = (Xh[:3] / Xh[3]).T
        ok = np.isfinite(X).all(1)
        for fr, idx in ((a, ia), (b, ib)):
            uv, z = _reproject(self.K, self.Rt[fr], X)
            ok &= (z > 0) & (np.linalg.norm(uv - self.cv[fr][idx], axis=1) < self.cfg.max_reproj_px)
        ca, cb = (-self.Rt[f][:, :3].T @ self.Rt[f][:, 3] for f in (a, b))
        ra, rb = X - ca, X - cb
        cosang = (ra * rb).sum(1) / (np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1) + 1e-12)
        ok &= cosang < math.cos(math.radians(self.cfg.min_parallax_deg))
        added = 0
        for x, p, q in zip(X[ok], ia[ok], ib[ok]):
            if (a, p) in self.point_of or (b, q) in self.point_of:
                continue
            self.point_of[(a, p)] = self.point_of[(b, q)] = len(self.points)
            self.points.append(x)
            added += 1
        return added

    def _candidate(self, j: int):
        """(homography/essential inlier ratio, E inlier mask, matches) for the pair (0, j)."""
        m = self.matches(0, j)
        if len(m) < 2 * self.cfg.min_pnp:
            return None
        E, mask = cv2.findEssentialMat(m.xi - 0.5, m.xj - 0.5, self.K, cv2.RANSAC, 0.999, 1.0)
        if E is None or E.shape != (3, 3):
            return None
        _, hmask = cv2.findHomography(m.xi, m.xj, cv2.RANSAC, 2.0)
        e_in = int(mask.sum())
        h_in = int(hmask.sum()) if hmask is not None else 0
        return (h_in / max(e_in, 1), E, mask, m) if e_in >= 2 * self.cfg.min_pnp else None

    def initialise(self, n: int) -> bool:
        """Initial pair: among frame 0 and the next self.cfg.init_candidates frames, the one a homography
        explains least (most parallax), as COLMAP's max_H_inlier_ratio rule."""
        last = min(n, 1 + self.cfg.init_candidates)
        cands = [(j, c) for j in range(1, last) if (c := self._candidate(j)) is not None]
        for j, (ratio, E, mask, m) in sorted(cands, key=lambda jc: jc[1][0]):
            if ratio > self.cfg.init_max_h_ratio:
                break
            _, R, t, mask = cv2.recoverPose(E, m.xi - 0.5, m.xj - 0.5, self.K, mask=mask)
            inl = mask.ravel() > 0
            self.Rt = {0: np.hstack([np.eye(3), np.zeros((3, 1))]), j: np.hstack([R, t])}
            if self.triangulate(0, j, m.ii[inl], m.jj[inl]) >= 2 * self.cfg.min_pnp:
                return True
            self.Rt, self.points, self.point_of = {}, [], {}
        return False

    def register(self, t: int) -> bool:
        corr: dict[int, int] = {}  # feature of t -> point (first registered neighbour wins)
        for r in sorted(self.Rt, key=lambda r: abs(r - t))[:self.cfg.neighbours]:
            m = self.matches(t, r)
            for p, q in zip(m.ii, m.jj):
                pid = self.point_of.get((r, q))
                if pid is not None and p not in corr:
                    corr[int(p)] = pid
        if len(corr) < self.cfg.min_pnp:
            return False
        feats = np.array(list(corr))
        pids = np.array([corr[p] for p in feats])
        obj = np.array([self.points[i] for i in pids], np.float64)
        img = self.cv[t][feats]
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, self.K, None, reprojectionError=self.cfg.max_reproj_px,
                                                 iterationsCount=200, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inl is None or len(inl) < self.cfg.min_pnp:
            return False
        inl = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], self.K, None, rvec, tvec)
        self.Rt[t] = np.hstack([cv2.Rodrigues(rvec)[0], tvec.reshape(3, 1)])
        for p, pid in zip(feats[inl], pids[inl]):  # the inliers extend their tracks (BA needs them)
            self.point_of[(t, int(p))] = int(pid)
        for r in sorted((r for r in self.Rt if r != t), key=lambda r: abs(r - t))[:self.cfg.neighbours]:
            m = self.matches(t, r)
            free = np.array(
                [(t, p) not in self.point_of and (r, q) not in self.point_of for p, q in zip(m.ii, m.jj)], bool
            )
            if free.any():
                self.triangulate(t, r, m.ii[free], m.jj[free])
        return True


def _bundle_adjust(tr: _Tracker, kept: list[int], max_nfev: int = 30) -> None:
    """Refine every kept pose (frame 0 fixed) and point: reprojection error in pixels, scipy
    least_squares with the Jacobian's sparsity, observations over tracking.twoview.max_reproj_px dropped once."""
    pos = {f: n for n, f in enumerate(kept)}
    obs = [(pos[f], tr.cv[f][p], pid) for (f, p), pid in tr.point_of.items() if f in pos]
    cam = np.array([o[0] for o in obs])
    uv = np.array([o[1] for o in obs])
    pid = np.array([o[2] for o in obs])
    n_cam, n_pts = len(kept) - 1, len(tr.points)
    x0 = np.concatenate([np.concatenate([cv2.Rodrigues(tr.Rt[f][:, :3])[0].ravel(), tr.Rt[f][:, 3]]) for f in kept[1:]]
                        + [np.array(tr.points).ravel()])

    def residuals(x, cam, uv, pid):
        poses = np.concatenate([np.zeros((1, 6)), x[: 6 * n_cam].reshape(-1, 6)])
        X = x[6 * n_cam:].reshape(-1, 3)[pid]
        R = rotvec_to_matrix(poses[cam, :3])
        pc = np.einsum("mij,mj->mi", R, X) + poses[cam, 3:]
        proj = pc @ tr.K.T
        z = np.where(np.abs(proj[:, 2:3]) > 1e-9, proj[:, 2:3], 1e-9)
        return (proj[:, :2] / z - uv).ravel()

    def sparsity(cam, pid):
        A = lil_matrix((2 * len(cam), 6 * n_cam + 3 * n_pts), dtype=int)
        rows = np.arange(len(cam))
        for r in (2 * rows, 2 * rows + 1):
            has = cam > 0
            for c in range(6):
                A[r[has], 6 * (cam[has] - 1) + c] = 1
            for c in range(3):
                A[r, 6 * n_cam + 3 * pid + c] = 1
        return A

    x = x0
    for _ in range(2):
        sol = least_squares(residuals, x, jac_sparsity=sparsity(cam, pid), x_scale="jac", max_nfev=max_nfev,
                            tr_solver="lsmr", args=(cam, uv, pid))
        x = sol.x
        keep = np.linalg.norm(sol.fun.reshape(-1, 2), axis=1) < tr.cfg.max_reproj_px
        if keep.all():
            break
        cam, uv, pid = cam[keep], uv[keep], pid[keep]
    for n, f in enumerate(kept[1:]):
        v = x[6 * n: 6 * n + 6]
        tr.Rt[f] = np.hstack([rotvec_to_matrix(v[:3])[0], v[3:].reshape(3, 1)])
    tr.points = list(x[6 * n_cam:].reshape(-1, 3))


def run_two_view(features: list[FrameFeatures], k: Intrinsics) -> SfMTrack | None:
    n = len(features)
    tr = _Tracker(features, k)
    if not tr.initialise(n):
        return None
    pending = [t for t in range(n) if t not in tr.Rt]
    failed: set[int] = set()
    while pending:
        pending.sort(key=lambda t: min(abs(t - r) for r in tr.Rt))
        t = pending.pop(0)
        if not tr.register(t):
            failed.add(t)
    kept = sorted(tr.Rt)
    _bundle_adjust(tr, kept)
    pts = np.array(tr.points, np.float64).reshape(-1, 3)
    c2w = np.stack([opencv_w2c_to_c2w(tr.Rt[f][:, :3], tr.Rt[f][:, 3]) for f in kept])
    errors, observations = [], []
    by_frame: dict[int, list[tuple[int, int]]] = {}
    for (f, p), pid in tr.point_of.items():
        by_frame.setdefault(f, []).append((p, pid))
    for f in kept:
        obs = by_frame.get(f, [])
        idx = np.array([pid for _, pid in obs], np.int64)
        uv = np.array([features[f].points[p] for p, _ in obs], np.float64).reshape(-1, 2)
        if len(idx):
            proj, _ = _reproject(tr.K, tr.Rt[f], pts[idx])
            errors.append(np.linalg.norm(proj + 0.5 - uv, axis=1))
        observations.append((f, uv, idx))
    poses, pts = relative_to_first(c2w, pts)
    err = float(np.mean(np.concatenate(errors))) if errors else math.inf
    return SfMTrack(poses, kept, sorted(failed), pts, observations, err, {"points": int(len(pts))})
