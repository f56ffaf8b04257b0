"""Local features for tracking: SIFT keypoints (OpenCV) and mutual ratio-test matching.

Keypoints are returned in OUR continuous pixel coordinates (core.conventions: the centre of
pixel (r, c) is (c + 0.5, r + 0.5)); OpenCV puts pixel centres at integers, hence the + 0.5.
Frames are tracked at an analysis resolution (long side <= tracking.features.analysis_max_side), so the cost
of tracking does not grow with the input's resolution.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from core.camera import Intrinsics
from core.tracking.config import tracking_config


@dataclass(frozen=True)
class FrameFeatures:
    points: np.ndarray  # [N, 2] float64 (u, v), our continuous pixel coordinates
    descriptors: np.ndarray  # [N, 128] float32

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass(frozen=True)
class PairMatches:
    i: int
    j: int
    xi: np.ndarray  # [M, 2] points in frame i
    xj: np.ndarray  # [M, 2] points in frame j
    ii: np.ndarray | None = None  # [M] feature indices in frame i
    jj: np.ndarray | None = None  # [M] feature indices in frame j

    def __len__(self) -> int:
        return int(self.xi.shape[0])


def analysis_frames(frames: torch.Tensor, intrinsics: Intrinsics, max_side: int | None = None
                    ) -> tuple[list[np.ndarray], Intrinsics]:
    """LDR frames [T, H, W, 3] in [0, 1] -> uint8 grey images at the analysis resolution, and
    the intrinsics at that resolution."""
    max_side = tracking_config().features.analysis_max_side if max_side is None else max_side
    T, H, W, _ = frames.shape
    s = min(1.0, max_side / max(H, W))
    w, h = max(8, round(W * s)), max(8, round(H * s))
    grey = (0.2126 * frames[..., 0] + 0.7152 * frames[..., 1] + 0.0722 * frames[..., 2]).clamp(0, 1)
    if (w, h) != (W, H):
        grey = torch.nn.functional.interpolate(grey[:, None].float(), size=(h, w), mode="area")[:, 0]
    images = [np.ascontiguousarray((g.numpy() * 255.0 + 0.5).astype(np.uint8)) for g in grey]
    return images, intrinsics.scaled(w, h)


def extract(image: np.ndarray, max_features: int | None = None) -> FrameFeatures:
    """SIFT at the strongest contrast threshold that finds `min_features` (tracking.features)."""
    cfg = tracking_config().features
    max_features = cfg.max_features if max_features is None else max_features
    for threshold in cfg.contrast_thresholds:
        kps, desc = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=threshold).detectAndCompute(image, None)
        if len(kps) >= cfg.min_features:
            break
    if desc is None or not kps:
        return FrameFeatures(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    pts = np.array([k.pt for k in kps], np.float64) + 0.5
    return FrameFeatures(pts, desc.astype(np.float32))


def _ratio_matches(a: np.ndarray, b: np.ndarray, ratio: float) -> dict[int, int]:
    if len(a) < 2 or len(b) < 2:
        return {}
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a, b, k=2)
    return {m[0].queryIdx: m[0].trainIdx for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance}


def match(fa: FrameFeatures, fb: FrameFeatures, i: int, j: int, ratio: float | None = None) -> PairMatches:
    """Mutual nearest neighbours that also pass Lowe's ratio test both ways."""
    ratio = tracking_config().features.ratio if ratio is None else ratio
    ab = _ratio_matches(fa.descriptors, fb.descriptors, ratio)
    ba = _ratio_matches(fb.descriptors, fa.descriptors, ratio)
    pairs = [(q, t) for q, t in ab.items() if ba.get(t) == q]
    if not pairs:
        return PairMatches(i, j, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, int), np.zeros(0, int))
    qa, tb = np.array(pairs).T
    return PairMatches(i, j, fa.points[qa], fb.points[tb], qa, tb)


def pair_schedule(n: int, offsets=(1, 2, 4, 8)) -> list[tuple[int, int]]:
    """Frame pairs to match: neighbours and a few longer baselines (loop-free videos)."""
    return [(i, i + k) for k in offsets for i in range(n - k)]
