"""General camera motion: structure from motion with pycolmap (COLMAP), intrinsics fixed.

The analysis frames go to a private temporary directory as PNGs, COLMAP extracts SIFT,
matches every pair (sequentially with an overlap for long clips), and its incremental
mapper registers the frames with the intrinsics held fixed (a single PINHOLE camera; COLMAP
also puts pixel centres at + 0.5, as we do).

Which model comes out depends on the pair the mapper starts from, and on a phone's walk the
wrong start leaves a model that drifts: a sideways step and a turn move a room's features
almost alike, and with noisy keypoints a model can trade one for the other, frame after frame
(dev `dancing_hall` `walk-noisy` turned 0.9 deg a frame too far, 17.7 deg by the last, and
COLMAP's bundle adjustment, rerun to convergence, stayed there, though the true poses
reproject its own tracks with half its median error). So the mapper runs from the matches
once per initial-pair angle in tracking.sfm.init_min_tri_angles_deg (4 deg lets a phone's small baselines
start; COLMAP's 16 deg suits object scans), and `choose_model` keeps the model that registers
the most frames; among those, the first start's, unless another reprojects the pooled feature
tracks of all the models clearly better (`pooled_median_error`, tracking.sfm.clearly_better). Each model's
own tracks were pruned to fit its own poses; the pooled ones are a common yardstick. Measured
in bench/README.md section 7, "Three starts".

The same clip gives the same poses every time: every stage runs on one thread (THREADS). With
two, COLMAP's feature extraction, matching and mapping each differed from run to run with the
random seed fixed. On a noisy 20-frame walk (bench.handheld's dev `blocky_photo_studio`
`walk-short-noisy`, one-off runs), three runs with two threads throughout gave three different
reconstructions of all 20 frames, and with two threads in any one stage models of 3 to 20
frames; one thread gave the same model every time (tests/test_tracking.py asserts the repeat).

Output: c2w poses in OUR camera convention and world = the first registered frame's camera
frame (core.conventions), the sparse points in that frame, COLMAP's mean reprojection error,
and the frames COLMAP could not register (dropped). The scale is COLMAP's arbitrary one:
core.tracking.scale resolves it.
"""
from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from core.camera import Intrinsics
from core.tracking.config import tracking_config
from core.tracking.geometry import c2w_to_opencv_w2c, opencv_w2c_to_c2w, relative_to_first

THREADS = 1  # more make every COLMAP stage differ from run to run (module docstring)


class SfMUnavailable(RuntimeError):
    """pycolmap is not installed here."""


@dataclass
class SfMTrack:
    poses: np.ndarray  # [K, 4, 4] c2w (ours) of the kept frames, world = kept[0]'s camera
    kept: list[int]
    dropped: list[int]
    points: np.ndarray  # [N, 3] sparse points, same frame and (arbitrary) scale
    observations: list[tuple[int, np.ndarray, np.ndarray]]  # (frame, pixel [M, 2], point index [M])
    reprojection_error_px: float
    stats: dict = field(default_factory=dict)


def _pycolmap():
    try:
        import pycolmap  # noqa: PLC0415 — optional: an ImportError is handled here
    except ImportError as exc:  # a dependency; only a broken install lands here
        raise SfMUnavailable(f"pycolmap is not importable ({exc})") from None
    return pycolmap


def run_sfm(images: list[np.ndarray], k: Intrinsics, threads: int = THREADS, seed: int = 0,
            starts: tuple[float, ...] | None = None) -> SfMTrack | None:
    """Register grey uint8 `images` (analysis resolution, intrinsics `k`); None if COLMAP
    finds no model with at least two frames. `starts`: the mapper's initial-pair angles
    (default tracking.sfm.init_min_tri_angles_deg)."""
    pycolmap = _pycolmap()
    pycolmap.set_random_seed(seed)
    quiet, pycolmap.logging.minloglevel = pycolmap.logging.minloglevel, 2  # COLMAP logs every step at INFO
    try:
        return _run(pycolmap, images, k, threads, seed, starts or tracking_config().sfm.init_min_tri_angles_deg)
    finally:
        pycolmap.logging.minloglevel = quiet


def _run(pycolmap, images: list[np.ndarray], k: Intrinsics, threads: int, seed: int,
         starts: tuple[float, ...]) -> SfMTrack | None:
    with tempfile.TemporaryDirectory(prefix="lf-sfm-") as tmp:
        root = Path(tmp)
        image_dir = root / "images"
        image_dir.mkdir()
        names = [f"{i:05d}.png" for i in range(len(images))]
        for name, im in zip(names, images):
            cv2.imwrite(str(image_dir / name), im)
        db = root / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        reader.camera_params = f"{k.fx},{k.fy},{k.cx},{k.cy}"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = threads
        cfg = tracking_config().sfm
        extraction.sift.max_num_features = cfg.max_features
        pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = threads
        if len(images) <= cfg.exhaustive_max_frames:
            pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = cfg.sequential_overlap
            pycolmap.match_sequential(
                db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu
            )
        models = []
        for n, angle in enumerate(starts):
            opts = pycolmap.IncrementalPipelineOptions()
            opts.num_threads = threads
            opts.random_seed = seed
            opts.multiple_models = False
            opts.min_model_size = 2
            opts.ba_refine_focal_length = False
            opts.ba_refine_principal_point = False
            opts.ba_refine_extra_params = False
            opts.extract_colors = False
            opts.mapper.init_min_tri_angle = angle
            opts.mapper.abs_pose_refine_focal_length = False
            opts.mapper.abs_pose_refine_extra_params = False
            out = root / f"sparse{n}"
            out.mkdir()
            recs = pycolmap.incremental_mapping(db, image_dir, out, opts)
            track = _track(max(recs.values(), key=lambda r: r.num_reg_images()), len(images)) if recs else None
            if track is not None:
                track.stats["init_min_tri_angle_deg"] = angle
                models.append(track)
    return choose_model(models, k)


def _track(rec, n_images: int) -> SfMTrack | None:
    """COLMAP's reconstruction -> SfMTrack (ours: c2w, world = the first kept frame); None
    under two frames."""
    if rec.num_reg_images() < 2:
        return None
    frame_of = {img.image_id: int(Path(img.name).stem) for img in rec.images.values() if img.has_pose}
    kept = sorted(frame_of.values())
    by_frame = {f: i for i, f in frame_of.items()}
    c2w = []
    for f in kept:
        m = rec.images[by_frame[f]].cam_from_world().matrix()  # 3x4 OpenCV world-to-camera
        c2w.append(opencv_w2c_to_c2w(m[:, :3], m[:, 3]))
    point_ids = list(rec.points3D.keys())
    index_of = {pid: n for n, pid in enumerate(point_ids)}
    xyz = np.array([rec.points3D[pid].xyz for pid in point_ids], np.float64).reshape(-1, 3)
    poses, pts = relative_to_first(np.stack(c2w), xyz)
    observations = []
    for f in kept:
        img = rec.images[by_frame[f]]
        uv, idx = [], []
        for p2d in img.points2D:
            if p2d.has_point3D():
                uv.append(p2d.xy)
                idx.append(index_of[p2d.point3D_id])
        observations.append((f, np.array(uv, np.float64).reshape(-1, 2), np.array(idx, np.int64)))
    err = float(rec.compute_mean_reprojection_error())
    return SfMTrack(poses, kept, sorted(set(range(n_images)) - set(kept)), pts, observations,
                    err if math.isfinite(err) else math.inf,
                    {"points": int(len(pts)), "mean_track_length": float(rec.compute_mean_track_length())})


def choose_model(models: list[SfMTrack], k: Intrinsics) -> SfMTrack | None:
    """The model that registers the most frames; among those the first, unless another has a
    `pooled_median_error` over every model's tracks tracking.sfm.clearly_better times the first's or lower
    (module docstring). The candidates are recorded in the chosen model's stats."""
    if not models:
        return None
    pool = [t for m in models for t in feature_tracks(m)]
    most = max(len(m.kept) for m in models)
    errors = [pooled_median_error(m, pool, k) if len(m.kept) == most else math.inf for m in models]
    first = next(n for n, m in enumerate(models) if len(m.kept) == most)
    best = min(range(len(models)), key=lambda n: (errors[n], n))
    chosen = models[best if errors[best] < tracking_config().sfm.clearly_better * errors[first] else first]
    chosen.stats["models"] = [{"init_min_tri_angle_deg": m.stats.get("init_min_tri_angle_deg"), "frames": len(m.kept),
                               "pooled_median_px": round(e, 4) if math.isfinite(e) else None}
                              for e, m in zip(errors, models)]
    return chosen


def feature_tracks(model: SfMTrack) -> list[tuple[np.ndarray, np.ndarray]]:
    """The model's 3D points as (frames [M], pixels [M, 2]) observation tracks."""
    frames, pixels = {}, {}
    for f, uv, idx in model.observations:
        for p, i in zip(uv, idx):
            frames.setdefault(int(i), []).append(f)
            pixels.setdefault(int(i), []).append(p)
    return [(np.array(frames[i]), np.array(pixels[i], np.float64)) for i in frames]


def pooled_median_error(model: SfMTrack, tracks: list[tuple[np.ndarray, np.ndarray]], k: Intrinsics) -> float:
    """Median reprojection error (px) of `tracks` (frames, pixels) under the model's poses: each
    track is triangulated (DLT) from its frames the model registered (two at least); a point
    behind a camera counts as infinitely far off."""
    K = k.matrix(torch.float64).numpy()  # pixel centres at + 0.5, as COLMAP's keypoints
    P = {f: K @ c2w_to_opencv_w2c(c2w)[:3] for f, c2w in zip(model.kept, model.poses)}
    by_length: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for frames, uv in tracks:
        keep = np.array([f in P for f in frames.tolist()], bool)
        if keep.sum() >= 2:
            by_length.setdefault(int(keep.sum()), []).append(
                (np.stack([P[f] for f in frames[keep].tolist()]), uv[keep])
            )
    errors = []
    for group in by_length.values():
        Ps = np.stack([g[0] for g in group])  # [N, M, 3, 4]
        uv = np.stack([g[1] for g in group])  # [N, M, 2]
        A = np.concatenate([uv[..., :1] * Ps[:, :, 2] - Ps[:, :, 0], uv[..., 1:] * Ps[:, :, 2] - Ps[:, :, 1]], 1)
        X = np.linalg.svd(A)[2][:, -1]  # [N, 4] homogeneous points
        x = np.einsum("nmij,nj->nmi", Ps, X)  # [N, M, 3]
        z = x[..., 2] * np.sign(X[:, 3:4])  # depth up to the positive scale of X's w
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.linalg.norm(x[..., :2] / x[..., 2:] - uv, axis=-1)
        errors.append(np.where((z > 0) & np.isfinite(err), err, np.inf).ravel())
    return float(np.median(np.concatenate(errors))) if errors else math.inf
