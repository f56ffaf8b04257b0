"""Reading a job's stored capture preview (format and writer: jobs.capture_preview).

Both files are checked against the checksums recorded when they were written before any
byte is served. Hashing tens of MB per request would cost more than the request, so a
verified file is remembered by its identity on disk (inode, size, mtime): any rewrite,
including a corruption through the filesystem, changes that identity and is verified anew.
"""
from __future__ import annotations

import json
import math
import os
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from core.capture.params import MAX_EXPOSURE_STOPS
from core.integrity import IntegrityError, verify_document
from jobs.capture_preview import (
    FORMAT,
    META_FILE,
    READABLE_VERSIONS,
    TENSORS_FILE,
    PreviewCameras,
    file_sha256,
    preview_dir,
)


class PreviewError(ValueError):
    """A stored preview is missing, corrupt or inconsistent (the message names the part)."""


class PreviewCorrupt(PreviewError):
    """A stored preview file does not match the checksum recorded when it was written."""


_VERIFIED_MAX = 256
_verified: "OrderedDict[tuple, str]" = OrderedDict()  # file identity -> its sha256
_verified_lock = threading.Lock()


def _identity(path: Path) -> tuple:
    st = os.stat(path)
    return (str(path), st.st_ino, st.st_size, st.st_mtime_ns)


def _verify_tensors(path: Path, expected: str) -> None:
    key = _identity(path)
    with _verified_lock:
        known = _verified.get(key)
    if known is None:
        known = file_sha256(path)
        with _verified_lock:
            _verified[key] = known
            while len(_verified) > _VERIFIED_MAX:
                _verified.popitem(last=False)
    if known != expected:
        raise PreviewCorrupt(
            f"{TENSORS_FILE}: checksum mismatch (the file was modified or corrupted after it was written)"
        )


class StoredPreview(PreviewCameras):
    """A preview on disk: cameras and times in memory, frames and depth read one at a time
    (safetensors slices), so a request touches one frame, not the whole clip."""

    def __init__(self, root: Path, meta: dict, poses: np.ndarray, times: np.ndarray, shape: tuple[int, int, int],
                 stated_ev: np.ndarray | None = None):
        self.root = root
        self.intrinsics = meta["intrinsics"]
        self.fps = float(meta["fps"])
        self.depth_source = str(meta.get("depth_source", ""))
        self.source_frames = int(meta.get("source_frames", shape[0]))
        self.poses = poses
        self.times = times
        self.stated_ev = stated_ev  # float32 [T] stops, when the capture stated them
        self.num_frames, self.height, self.width = shape

    def frame_ev(self, index: int) -> float:
        """The stated exposure of frame `index` in stops (0 when the capture gave none)."""
        return 0.0 if self.stated_ev is None else float(self.stated_ev[index])

    def _slice(self, name: str, index: int) -> np.ndarray:
        from safetensors import safe_open  # noqa: PLC0415 — safetensors is heavy: imported when used

        if not 0 <= index < self.num_frames:
            raise IndexError(f"frame {index} out of range [0, {self.num_frames})")
        with safe_open(str(self.root / TENSORS_FILE), framework="numpy") as f:
            return np.asarray(f.get_slice(name)[index])

    def frame(self, index: int) -> np.ndarray:
        """uint8 [h, w, 3]."""
        return self._slice("frames", index)

    def depth_map(self, index: int) -> np.ndarray:
        """float32 [h, w] planar metres, NaN where invalid."""
        return self._slice("depth", index).astype(np.float32)


_DTYPES = {"frames": "U8", "depth": "F16", "poses": "F64", "times": "F32"}
_OPTIONAL_DTYPES = {"frame_ev": "F32"}  # only in previews of captures that stated exposures


def load_preview(job_dir: Path) -> StoredPreview:
    """Open and validate a stored preview; raises PreviewError (FileNotFoundError if absent)."""
    from safetensors import SafetensorError, safe_open  # noqa: PLC0415 — safetensors is heavy: imported when used

    root = preview_dir(job_dir)
    if not (root / META_FILE).is_file():
        raise FileNotFoundError(f"no capture preview in {root}")
    try:
        meta = json.loads((root / META_FILE).read_text())
        if not isinstance(meta, dict) or meta.get("format") != FORMAT or meta.get("version") not in READABLE_VERSIONS:
            raise PreviewError(f"{META_FILE}: not a {FORMAT} document of version {READABLE_VERSIONS}")
        if meta["version"] >= 2:  # version 1 was written before checksums existed
            try:
                verify_document(meta, META_FILE)
            except IntegrityError as exc:
                raise PreviewCorrupt(str(exc)) from None
            _verify_tensors(root / TENSORS_FILE, meta.get("tensors_sha256"))
        with safe_open(str(root / TENSORS_FILE), framework="numpy") as f:
            names = set(f.keys())
            if not set(_DTYPES) <= names <= set(_DTYPES) | set(_OPTIONAL_DTYPES):
                raise PreviewError(f"{TENSORS_FILE}: expected tensors {sorted(_DTYPES)} (and optionally "
                                   f"{sorted(_OPTIONAL_DTYPES)}), got {sorted(names)}")
            expected = {k: v for k, v in {**_DTYPES, **_OPTIONAL_DTYPES}.items() if k in names}
            shapes = {k: tuple(f.get_slice(k).get_shape()) for k in expected}
            dtypes = {k: f.get_slice(k).get_dtype() for k in expected}
            poses, times = f.get_tensor("poses"), f.get_tensor("times")
            frame_ev = f.get_tensor("frame_ev") if "frame_ev" in names else None
    except (OSError, ValueError, SafetensorError) as exc:
        if isinstance(exc, PreviewError):
            raise
        raise PreviewCorrupt(f"capture preview in {root.name}/ is unreadable: {exc}") from None
    if dtypes != expected:
        raise PreviewError(f"{TENSORS_FILE}: dtypes must be {expected}, got {dtypes}")
    fs = shapes["frames"]
    if len(fs) != 4 or fs[-1] != 3 or fs[0] < 1:
        raise PreviewError(f"{TENSORS_FILE}: frames must be [T,h,w,3], got {fs}")
    t, h, w = fs[:3]
    if shapes["depth"] != (t, h, w) or shapes["poses"] != (t, 4, 4) or shapes["times"] != (t,):
        raise PreviewError(f"{TENSORS_FILE}: depth {shapes['depth']}, poses {shapes['poses']}, times {shapes['times']} "
                           f"do not match {t} frames of {h}x{w}")
    if not (np.isfinite(poses).all() and np.isfinite(times).all()):
        raise PreviewError(f"{TENSORS_FILE}: poses and times must be finite")
    if frame_ev is not None and (shapes["frame_ev"] != (t,) or not np.isfinite(frame_ev).all()
                                    or np.abs(frame_ev).max() > MAX_EXPOSURE_STOPS):
        raise PreviewError(f"{TENSORS_FILE}: frame_ev must be {t} finite stops within +-{MAX_EXPOSURE_STOPS:g}")
    intr = meta.get("intrinsics")
    if not isinstance(intr, dict) or intr.get("width") != w or intr.get("height") != h:
        raise PreviewError(f"{META_FILE}: intrinsics must describe the {w}x{h} preview frames")
    fps = meta.get("fps")
    if not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise PreviewError(f"{META_FILE}: fps must be a positive number, got {fps!r}")
    return StoredPreview(root, meta, poses.astype(np.float64), times.astype(np.float32), (t, h, w),
                         None if frame_ev is None else frame_ev.astype(np.float32))
