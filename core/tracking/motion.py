"""Does the camera move? A documented statistic, recorded with its evidence.

Statistic (docs/engine.md, "Camera tracking"):
1. SIFT features per frame at the analysis resolution (core.tracking.features).
2. The reference is the first frame that matches its successor (at least tracking.motion.min_matches mutual
   ratio-test matches): frame 0 unless it is dark, blurred or cut; frames before it are listed
   as without matches. For every later frame t, the MEDIAN displacement of the features
   matched between the reference and frame t. The median ignores a
   minority of moving objects and mismatches; a lighting change moves no feature. Where six
   matches stayed put (within half a pixel), the median of those: a person walking through
   may bring more features than the wall behind them, but a moving camera leaves no six
   features of the room in place (mutual ratio-test matches landing within half a pixel by
   chance do not come six at a time). A frame with too few matches to the reference to
   measure a motion, but six that stayed put, did not move.
   When frame t no longer overlaps the reference enough, its displacement is chained through
   frame t - 1 (displacement(t - 1) + median displacement between t - 1 and t).
   Frames with too few matches either way (dark, blurred, a cut) are left out and listed.
3. statistic = max over frames of that displacement / image width (resolution-free).
4. threshold = max(min_motion_fraction, k_sigma x the keypoint noise), the noise being the
   smallest over frames of the robust spread (1.4826 MAD) of the features' residuals after a
   RANSAC homography between the two frames (localisation noise; the smallest because
   parallax adds to the residual of later frames of a moving camera).
moving = statistic > threshold.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from core.tracking.config import tracking_config
from core.tracking.features import FrameFeatures, match


@dataclass(frozen=True)
class MotionDecision:
    moving: bool
    statistic: float
    threshold: float
    reason: str
    evidence: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return asdict(self)


def _still_median(xi: np.ndarray, xj: np.ndarray) -> float | None:
    """The median displacement of the matches that stayed within still_px, where at least
    still_min did (else None): a moving camera moves every feature of the room, so features that
    stayed put are the room behind something moving through the view (a person whose features
    can outnumber a plain wall's), not a camera that moved."""
    norms = np.linalg.norm(xj - xi, axis=1)
    cfg = tracking_config().motion
    still = norms < cfg.still_px
    return float(np.median(norms[still])) if still.sum() >= cfg.still_min else None


def _median_displacement(xi: np.ndarray, xj: np.ndarray) -> tuple[float, float]:
    """(median displacement, the still matches' where enough stayed put (`_still_median`);
    robust spread of the residuals after a homography) in pixels."""
    still = _still_median(xi, xj)
    disp = still if still is not None else float(np.median(np.linalg.norm(xj - xi, axis=1)))
    H, _ = cv2.findHomography(xi, xj, cv2.RANSAC, 3.0)
    if H is None:
        return disp, float("nan")
    pred = cv2.perspectiveTransform(xi[None].astype(np.float64), H)[0]
    return disp, 1.4826 * float(np.median(np.linalg.norm(xj - pred, axis=1)))


def detect_motion(features: list[FrameFeatures], width: int) -> MotionDecision:
    """Decide from per-frame features (analysis resolution, `width` pixels wide)."""
    cfg = tracking_config().motion
    T = len(features)
    if T < 2:
        return MotionDecision(False, 0.0, 0.0, "single frame: camera treated as static", {"frames": T})
    ref, first = 0, None
    for t in range(T - 1):  # the reference: the first frame that matches its successor
        first = match(features[t], features[t + 1], t, t + 1)
        if len(first) >= cfg.min_matches:
            ref = t
            break
    else:
        first = None  # none does: judged from frame 0, which finds too few matches below
    disp = np.full(T, np.nan)
    disp[ref] = 0.0
    noise, matches, chained, lost = [], [0] * T, [], list(range(ref))
    for t in range(ref + 1, T):
        m = first if t == ref + 1 and first is not None else match(features[ref], features[t], ref, t)
        matches[t] = len(m)
        if len(m) >= cfg.min_matches:
            disp[t], s = _median_displacement(m.xi, m.xj)
            noise.append(s)
            continue
        still = _still_median(m.xi, m.xj)  # too few to measure a motion, maybe enough to see none
        if still is not None:
            disp[t] = still
            continue
        prev = match(features[t - 1], features[t], t - 1, t)
        if len(prev) >= cfg.min_matches and np.isfinite(disp[t - 1]):
            step, s = _median_displacement(prev.xi, prev.xj)
            disp[t] = disp[t - 1] + step
            noise.append(s)
            chained.append(t)
        else:
            lost.append(t)
    finite = disp[np.isfinite(disp)]
    evidence = {
        "analysis_width": int(width),
        "frames": T,
        "displacement_px": [round(float(d), 3) for d in disp],
        "reference_frame": ref,
        "matches_to_reference": matches,
        "chained_frames": chained,
        "frames_without_matches": lost,
    }
    if len(finite) < 2:
        return MotionDecision(False, float("nan"), float("nan"),
                              "too few matched features to judge camera motion: camera treated as static", evidence)
    stat = float(finite.max()) / width
    noise = [n for n in noise if np.isfinite(n)]
    sigma = float(min(noise)) / width if noise else 0.0
    thr = max(cfg.min_motion_fraction, cfg.k_sigma * sigma)
    evidence["keypoint_noise_px"] = round(sigma * width, 4)
    moving = stat > thr
    worst = int(np.nanargmax(disp))
    reason = (
        f"camera {'moves' if moving else 'is static'}: max median feature displacement {stat * width:.2f} px "
        f"({stat:.4f} of the width) at frame {worst} vs threshold {thr:.4f} (keypoint noise {sigma * width:.2f} px"
        f"{f', {len(lost)} frame(s) without matches' if lost else ''})"
    )
    return MotionDecision(moving, stat, thr, reason, evidence)
