"""General camera motion: structure from motion with pycolmap (COLMAP), intrinsics fixed.

The analysis frames go to a private temporary directory as PNGs, COLMAP extracts SIFT,
matches every pair (sequentially with an overlap for long clips), and its incremental
mapper registers the frames with the intrinsics held fixed (a single PINHOLE camera; COLMAP
also puts pixel centres at + 0.5, as we do). The initial pair's minimum triangulation angle
is lowered from COLMAP's 16 deg, which suits object scans, to INIT_MIN_TRI_ANGLE_DEG: a
phone walking through a room rarely gets that much parallax between two frames.

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

from core.camera import Intrinsics
from core.tracking.geometry import opencv_w2c_to_c2w, relative_to_first

INIT_MIN_TRI_ANGLE_DEG = 4.0
EXHAUSTIVE_MAX_FRAMES = 40
SEQUENTIAL_OVERLAP = 10
MAX_FEATURES = 2048
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
        import pycolmap
    except ImportError as exc:  # a dependency; only a broken install lands here
        raise SfMUnavailable(f"pycolmap is not importable ({exc})") from None
    return pycolmap


def run_sfm(images: list[np.ndarray], k: Intrinsics, threads: int = THREADS, seed: int = 0) -> SfMTrack | None:
    """Register grey uint8 `images` (analysis resolution, intrinsics `k`); None if COLMAP
    finds no model with at least two frames."""
    pycolmap = _pycolmap()
    pycolmap.set_random_seed(seed)
    quiet, pycolmap.logging.minloglevel = pycolmap.logging.minloglevel, 2  # COLMAP logs every step at INFO
    try:
        return _run(pycolmap, images, k, threads, seed)
    finally:
        pycolmap.logging.minloglevel = quiet


def _run(pycolmap, images: list[np.ndarray], k: Intrinsics, threads: int, seed: int) -> SfMTrack | None:
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
        extraction.sift.max_num_features = MAX_FEATURES
        pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = threads
        if len(images) <= EXHAUSTIVE_MAX_FRAMES:
            pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = SEQUENTIAL_OVERLAP
            pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = threads
        opts.random_seed = seed
        opts.multiple_models = False
        opts.min_model_size = 2
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.extract_colors = False
        opts.mapper.init_min_tri_angle = INIT_MIN_TRI_ANGLE_DEG
        opts.mapper.abs_pose_refine_focal_length = False
        opts.mapper.abs_pose_refine_extra_params = False
        out = root / "sparse"
        out.mkdir()
        recs = pycolmap.incremental_mapping(db, image_dir, out, opts)
    if not recs:
        return None
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
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
    return SfMTrack(poses, kept, sorted(set(range(len(images))) - set(kept)), pts, observations,
                    err if math.isfinite(err) else math.inf,
                    {"points": int(len(pts)), "mean_track_length": float(rec.compute_mean_track_length())})
