"""Camera tracking for captures without poses: decide, estimate, scale, and say how.

`track_camera(frames, intrinsics, depth=None)`:
1. SIFT features at the analysis resolution; `detect_motion` decides whether the camera
   moves (statistic and evidence recorded). Static -> identity poses, method "static" (with a
   warning when too few features matched to judge: a pan would then be read as the light
   changing).
2. Moving: rotation about a fixed centre first (core.tracking.rotation). When the rotation
   model explains the matches (`RotationTrack.fits`), the poses are those rotations with
   zero translation: method "rotation", no scale needed.
3. Otherwise general structure from motion with pycolmap (method "sfm:pycolmap"), falling
   back to OpenCV two-view geometry chained by PnP (method "sfm:opencv") if COLMAP finds no
   model; then scale (core.tracking.scale): from given depth, else the floor, else the room
   assumption.
4. If structure from motion fails too, or registers fewer frames than the rotation track,
   the rotation track still stands when it registered most frames and explains nearly every
   match within a pixel or the clip's keypoint noise (`rotation_fallback_ok`: on a noisy,
   blurred handheld pan the rotation model's residual, a point-to-point distance, grows
   against the essential matrix's, a point-to-line one, until it fails the model comparison
   of step 2; such a pan has no baseline to reconstruct, or a reconstruction takes its
   residual shear for one and loses frames): method "rotation", with a warning. Where COLMAP
   registered too few frames, that test comes before OpenCV's chained two-view geometry,
   which registers a pan with a translation it invents.
5. A room scan (a camera turning about one spot through tilts, where the ceiling, floor and
   smooth walls leave features for few frames): when the features' rotations fit but leave
   frames out, or as the last resort before a static camera, the frames are registered by
   their pixels (core.tracking.direct, `_direct_completion`): kept if that places more frames
   than the features did and agrees with their rotations within
   tracking.track.direct_max_disagreement_deg.
6. If every method fails: identity poses, method "failed:static-fallback", and a warning.
   The caller still succeeds (a capture is never refused for being hard to track).
World = the first kept frame's camera frame (core.conventions). Frames that could not be
registered are listed in `dropped`; the caller removes them from the capture.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from core.camera import Intrinsics
from core.tracking.config import TrackConfig, tracking_config
from core.tracking.direct import track_rotation_direct
from core.tracking.features import analysis_frames, extract, match, pair_schedule
from core.tracking.geometry import rotation_angle_deg
from core.tracking.motion import MotionDecision, detect_motion
from core.tracking.rotation import estimate_rotations
from core.tracking.scale import ScaleEstimate, apply_scale, scale_from_depth, scale_from_room
from core.tracking.sfm import run_sfm
from core.tracking.twoview import run_two_view

SFM_ENV = "LIGHTFIELD_SFM"  # "pycolmap" (default) or "opencv": where pycolmap's wheel is unavailable or unwanted


def _knobs() -> TrackConfig:
    return tracking_config().track


def sfm_backend_from_env() -> bool:
    """True to use pycolmap (the default), False for the OpenCV tracker only (LIGHTFIELD_SFM=opencv)."""
    value = os.environ.get(SFM_ENV, "pycolmap").strip().lower() or "pycolmap"
    if value not in ("pycolmap", "opencv"):
        raise ValueError(f"{SFM_ENV} must be 'pycolmap' or 'opencv', got {value!r}")
    return value == "pycolmap"


@dataclass
class TrackingResult:
    poses: torch.Tensor  # [K, 4, 4] float64 c2w of the kept frames (world = kept[0]'s camera)
    kept: list[int]
    dropped: list[int]
    method: str  # "static" | "rotation" | "sfm:pycolmap" | "sfm:opencv" | "failed:static-fallback"
    motion: MotionDecision
    reprojection_error_px: float | None = None  # at the analysis resolution
    analysis_size: tuple[int, int] = (0, 0)  # (width, height) the error is measured at
    scale: ScaleEstimate | None = None
    points: torch.Tensor | None = None  # [N, 3] float64 sparse points, metres, world frame
    focal_px: float | None = None  # refined fx at the INPUT resolution (None when not refined)
    warnings: list[str] = field(default_factory=list)
    cpu_seconds: float = 0.0
    stats: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.method.startswith("failed")

    def summary(self) -> dict:
        """What the artefact records (poses are recorded by the capture summary)."""
        return {
            "method": self.method,
            "camera_moves": self.motion.moving,
            "motion": self.motion.as_dict(),
            "reprojection_error_px": None
            if self.reprojection_error_px is None
            else round(self.reprojection_error_px, 4),
            "analysis_size": list(self.analysis_size),
            "frames_kept": list(self.kept),
            "frames_dropped": list(self.dropped),
            "scale_source": self.scale.source
            if self.scale
            else ("none: no translation" if self.method == "rotation" else None),
            "scale": None if self.scale is None else {"metres_per_unit": self.scale.scale, **self.scale.evidence},
            "sparse_points": 0 if self.points is None else int(self.points.shape[0]),
            "refined_focal_px": self.focal_px,
            "cpu_seconds": round(self.cpu_seconds, 3),
            "warnings": list(self.warnings),
            **({"stats": self.stats} if self.stats else {}),
        }


def _identity(n: int) -> torch.Tensor:
    return torch.eye(4, dtype=torch.float64).expand(n, 4, 4).clone()


def _poses_from_rotations(rots: np.ndarray) -> torch.Tensor:
    p = _identity(len(rots))
    p[:, :3, :3] = torch.from_numpy(rots)
    return p


def track_camera(frames: torch.Tensor, intrinsics: Intrinsics, depth: torch.Tensor | None = None,
                 refine_focal: bool = False, use_pycolmap: bool | None = None) -> TrackingResult:
    """Poses for `frames` [T, H, W, 3] LDR (see module docstring). `depth` [T, H, W] (planar
    metres, NaN invalid) fixes the scale when given. `refine_focal` lets a pan refine fx
    (use it when the intrinsics were assumed, not given). `use_pycolmap=None` reads SFM_ENV."""
    t_cpu = time.process_time()
    use_pycolmap = sfm_backend_from_env() if use_pycolmap is None else use_pycolmap
    cv2.setRNGSeed(0)  # OpenCV's RANSAC: the same capture tracks the same way every time
    T = int(frames.shape[0])
    images, k = analysis_frames(frames, intrinsics)
    features = [extract(im) for im in images]
    motion = detect_motion(features, k.width)
    result = TrackingResult(_identity(T), list(range(T)), [], "static", motion, analysis_size=(k.width, k.height))
    if motion.moving:
        result = _track_moving(images, features, k, intrinsics, depth, refine_focal, use_pycolmap, motion, frames)
    elif not np.isfinite(motion.statistic):  # could not be judged: say so, a moving camera would be misread
        result.warnings.append(
            f"{motion.reason}; if the camera moved, give poses (params.poses) or a capture-app export"
        )
    result.cpu_seconds = time.process_time() - t_cpu
    return result


def _track_moving(images, features, k: Intrinsics, full: Intrinsics, depth, refine_focal, use_pycolmap,
                  motion: MotionDecision, frames: torch.Tensor) -> TrackingResult:
    T = len(images)
    pairs = [match(features[i], features[j], i, j) for i, j in pair_schedule(T)]
    rot = estimate_rotations(pairs, T, k, refine_focal=refine_focal)
    stats = {"rotation_model": {"median_px": round(rot.median_px, 4), "inlier_share": round(rot.inlier_share, 4),
                                "parallax_px": round(rot.parallax_px, 4), "epipolar_px": round(rot.epipolar_px, 4),
                                "fits": rot.fits, "pairs": rot.pairs, "readout_frames": round(rot.readout, 4),
                                "readout_direction": rot.readout_direction and list(rot.readout_direction)}}
    size = (k.width, k.height)
    noise = float(motion.evidence.get("keypoint_noise_px", 0.0))
    if rot.fits and len(rot.kept) == T:
        focal = rot.focal * full.width / k.width if refine_focal else None
        return TrackingResult(_poses_from_rotations(rot.rotations), rot.kept, rot.dropped, "rotation", motion,
                              rot.rms_px, size, None, None, focal, _dropped_warning(rot.dropped), stats=stats)
    if rot.fits:  # the matches say the camera turns about one spot but leave frames out: their pixels place them
        direct = _direct_completion(frames, k, full, rot, refine_focal, stats)
        if direct is not None:
            direct.motion, direct.analysis_size = motion, size
            return direct
        if len(rot.kept) >= _knobs().min_kept_fraction * T:
            focal = rot.focal * full.width / k.width if refine_focal else None
            return TrackingResult(_poses_from_rotations(rot.rotations), rot.kept, rot.dropped, "rotation", motion,
                                  rot.rms_px, size, None, None, focal, _dropped_warning(rot.dropped), stats=stats)
    failures = []
    for name, runner in (("sfm:pycolmap", _pycolmap_track if use_pycolmap else None), ("sfm:opencv", _opencv_track)):
        if runner is None:
            continue
        try:
            track = runner(images, features, k)
            if track is not None and "models" in track.stats:  # COLMAP's starts, kept whichever method wins
                stats["models"] = track.stats["models"]
            kept = 0 if track is None else len(track.kept)
            too_few = kept < max(2, _knobs().min_kept_fraction * T)
            failure = f"{name}: registered {kept} of {T} frames" if too_few else None
        except Exception as exc:  # a library failure is a tracking failure, never a job failure
            failure = f"{name}: {type(exc).__name__}: {exc}"
        if failure:
            failures.append(failure)
            if rotation_fallback_ok(rot, T, noise):
                # a pan: no pair with parallax to start from; the next, weaker reconstruction (OpenCV's
                # chained two-view geometry) would register it with a translation it invents
                break
            continue
        if len(track.kept) < len(rot.kept) and rotation_fallback_ok(rot, T, noise):
            # a pan: the reconstruction took what the rotation left (noise, shear) for a baseline and lost frames
            failures.append(f"{name}: registered {len(track.kept)} of {T} frames, the rotation {len(rot.kept)}")
            break
        scale = None
        if depth is not None:
            scale = scale_from_depth(track.poses, k, track.points, track.observations, depth, track.kept)
        scale = scale or scale_from_room(track.poses, k, track.points, track.observations)
        poses, points = apply_scale(track.poses, track.points, scale.scale)
        warn = _dropped_warning(track.dropped)
        if scale.source != "depth":
            warn.append(
                f"camera translation scaled by the {scale.source} rule (no depth given): distances are approximate"
            )
        return TrackingResult(
            torch.from_numpy(poses),
            track.kept,
            track.dropped,
            name,
            motion,
            track.reprojection_error_px,
            size,
            scale,
            torch.from_numpy(points),
            None,
            warn,
            stats={**stats, **track.stats, "failures": failures} if failures else {**stats, **track.stats},
        )
    if rotation_fallback_ok(rot, T, noise, alone=True):
        focal = rot.focal * full.width / k.width if refine_focal else None
        warn = [
            f"camera tracking: a pure rotation left residuals above an essential matrix's ({rot.parallax_px:.2f} vs "
            f"{rot.epipolar_px:.2f} px: some parallax, or blur and noise) and structure from motion did not "
            f"register the frames as well ({'; '.join(failures)}): using the rotation; give poses (params.poses) "
            "if the camera moved far"
        ] + _dropped_warning(rot.dropped)
        return TrackingResult(_poses_from_rotations(rot.rotations), rot.kept, rot.dropped, "rotation", motion,
                              rot.rms_px, size, None, None, focal, warn,
                              stats={**stats, "failures": failures, "rotation_fallback": True})
    if not rot.fits:  # too few matches to judge the motion: the pixels may still register a turn
        direct = _direct_completion(frames, k, full, rot, refine_focal, stats)
        if direct is not None:
            direct.motion, direct.analysis_size = motion, size
            direct.warnings.insert(0, "camera tracking: too few matched features ("
                                   + "; ".join(failures) + "); the frames were registered as a camera turning about "
                                   "one spot from their pixels: give poses (params.poses) if the camera moved far")
            return direct
    warning = ("camera tracking failed (" + "; ".join(failures) + "): treating the camera as static; "
               "give poses (params.poses) or a capture-app export for a moving camera")
    return TrackingResult(_identity(T), list(range(T)), [], "failed:static-fallback", motion, None, size,
                          warnings=[warning], stats={**stats, "failures": failures})


def _direct_completion(frames: torch.Tensor, k: Intrinsics, full: Intrinsics, rot, refine_focal: bool,
                       stats: dict) -> TrackingResult | None:
    """The rotation of every frame from its pixels (core.tracking.direct), where matched features
    say the camera turns about one spot but register too few frames (a room scan's blank ceiling
    and floor, a studio's smooth walls). The features' rotations start the pairs they cover and
    their refined focal length is used, then refitted from the loop closures where `refine_focal`
    (core.tracking.direct `_self_calibrate`: the features saw too little of the turn to fix it
    within a degree, and a focal length slightly off turns a ring's frames degrees off); the
    result is kept if it places more frames than they did and agrees with them, frame by frame,
    within tracking.track.direct_max_disagreement_deg (else None). The comparison is at the
    refitted focal length, so the features' own focal error counts against it; comparing at the
    focal length both used was tried and let a focal fit that had gone wrong, 178 deg off, through."""
    T = frames.shape[0]
    focal = rot.focal * full.width / k.width if refine_focal and len(rot.kept) >= 3 else None
    intr = (
        full
        if focal is None
        else Intrinsics(focal, focal * full.fy / full.fx, full.cx, full.cy, full.width, full.height)
    )
    pos = {f: n for n, f in enumerate(rot.kept)}
    feature_pairs = {(f - 1, f): rot.rotations[pos[f]].T @ rot.rotations[pos[f - 1]]
                     for f in range(1, T) if f in pos and f - 1 in pos}
    track = track_rotation_direct(frames, intr, feature_pairs, refine_focal=refine_focal)
    if track.stats.get("focal_scale_applied"):  # the loop closures fixed the focal length better than the features
        focal = intr.fx / track.focal_scale
    placed = track.stats["frames_fixed_by_pairs"]
    at = {f: n for n, f in enumerate(track.kept)}
    common = [f for f in rot.kept if f in at]
    if common:  # both tracks in the first common frame's axes
        a, b = rot.rotations[pos[common[0]]], track.rotations[at[common[0]]]
        disagree = max(
            rotation_angle_deg((a.T @ rot.rotations[pos[f]]).T @ (b.T @ track.rotations[at[f]])) for f in common
        )
    else:
        disagree = 0.0
    stats["direct"] = {**track.stats, "max_disagreement_with_features_deg": round(disagree, 3)}
    knobs = _knobs()
    consistent = track.stats["matched_pairs"] >= knobs.direct_min_matched_share * max(track.stats["pairs"], 1)
    if (placed <= len(rot.kept) or disagree > knobs.direct_max_disagreement_deg or placed < knobs.min_kept_fraction * T
            or not consistent):
        return None
    rots = track.rotations[0].T[None] @ track.rotations  # world = the first kept frame's camera
    warn = _dropped_warning(track.dropped)
    if track.stats["frames_from_motion_prior"]:
        warn.append(f"camera tracking placed {len(track.stats['frames_from_motion_prior'])} frame(s) "
                    f"{track.stats['frames_from_motion_prior'][:20]} from the camera's motion alone (too little "
                    "texture to register them)")
    return TrackingResult(_poses_from_rotations(rots), list(track.kept), list(track.dropped), "rotation", None, None,
                          (0, 0), None, None, focal, warn,
                          stats={**stats, "rotation_source": "photometric (core.tracking.direct)"})


def rotation_fallback_ok(rot, T: int, noise_px: float = 0.0, alone: bool = False) -> bool:
    """When structure from motion cannot register a clip as well, is the rotation track still the
    camera? Under motion blur and noise a rotation's point-to-point residual grows to two to
    three times an essential matrix's point-to-line one and fails the model comparison
    (RotationTrack.fits, which also models the rolling shutter), while there is no baseline to
    reconstruct. The rotation must register most frames, explain nearly every match, and keep
    its median residual within a pixel or within the clip's keypoint noise (`noise_px`, the
    motion statistic's: a dim room's features are that much less precise), and within
    tracking.track.fallback_ratio of the essential matrix's: a walk's parallax leaves 5-10 times.
    Where nothing else registered the clip (`alone`: the rotation or a static camera), a larger
    ratio passes when the median residual is still within tracking.track.fallback_noise_ratio of
    the keypoint noise: in a dim room the ratio of the two residuals reaches 4 on pans, while a
    walk's parallax leaves its residual
    several times its keypoints' noise (6x on the sharp walk of tests/test_tracking.py)."""
    explains = (len(rot.kept) >= _knobs().min_kept_fraction * T and rot.inlier_share >= _knobs().fallback_inlier_share
                and rot.median_px <= max(_knobs().fallback_max_median_px, noise_px))
    noise_level = alone and rot.median_px <= _knobs().fallback_noise_ratio * noise_px
    return explains and (rot.parallax_px <= _knobs().fallback_ratio * rot.epipolar_px or noise_level)


def _dropped_warning(dropped: list[int]) -> list[str]:
    return (
        [f"camera tracking could not register {len(dropped)} frame(s) {dropped[:20]}: they are left out"]
        if dropped
        else []
    )


def _pycolmap_track(images, features, k):
    return run_sfm(images, k)


def _opencv_track(images, features, k):
    return run_two_view(features, k)
