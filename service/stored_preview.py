"""Reading a job's stored capture preview (format and writer: jobs.capture_preview)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from jobs.capture_preview import META_FILE, FORMAT, TENSORS_FILE, VERSION, PreviewCameras, preview_dir


class PreviewError(ValueError):
    """A stored preview is missing, corrupt or inconsistent (the message names the part)."""


class StoredPreview(PreviewCameras):
    """A preview on disk: cameras and times in memory, frames and depth read one at a time
    (safetensors slices), so a request touches one frame, not the whole clip."""

    def __init__(self, root: Path, meta: dict, poses: np.ndarray, times: np.ndarray, shape: tuple[int, int, int]):
        self.root = root
        self.intrinsics = meta["intrinsics"]
        self.fps = float(meta["fps"])
        self.depth_source = str(meta.get("depth_source", ""))
        self.source_frames = int(meta.get("source_frames", shape[0]))
        self.poses = poses
        self.times = times
        self.num_frames, self.height, self.width = shape

    def _slice(self, name: str, index: int) -> np.ndarray:
        from safetensors import safe_open

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


def load_preview(job_dir: Path) -> StoredPreview:
    """Open and validate a stored preview; raises PreviewError (FileNotFoundError if absent)."""
    from safetensors import SafetensorError, safe_open

    root = preview_dir(job_dir)
    if not (root / META_FILE).is_file():
        raise FileNotFoundError(f"no capture preview in {root}")
    try:
        meta = json.loads((root / META_FILE).read_text())
        with safe_open(str(root / TENSORS_FILE), framework="numpy") as f:
            if set(f.keys()) != set(_DTYPES):
                raise PreviewError(f"{TENSORS_FILE}: expected tensors {sorted(_DTYPES)}, got {sorted(f.keys())}")
            shapes = {k: tuple(f.get_slice(k).get_shape()) for k in _DTYPES}
            dtypes = {k: f.get_slice(k).get_dtype() for k in _DTYPES}
            poses, times = f.get_tensor("poses"), f.get_tensor("times")
    except (OSError, ValueError, SafetensorError) as exc:
        if isinstance(exc, PreviewError):
            raise
        raise PreviewError(f"capture preview in {root} is unreadable: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise PreviewError(f"{META_FILE}: not a {FORMAT} v{VERSION} document")
    if dtypes != _DTYPES:
        raise PreviewError(f"{TENSORS_FILE}: dtypes must be {_DTYPES}, got {dtypes}")
    fs = shapes["frames"]
    if len(fs) != 4 or fs[-1] != 3 or fs[0] < 1:
        raise PreviewError(f"{TENSORS_FILE}: frames must be [T,h,w,3], got {fs}")
    t, h, w = fs[:3]
    if shapes["depth"] != (t, h, w) or shapes["poses"] != (t, 4, 4) or shapes["times"] != (t,):
        raise PreviewError(f"{TENSORS_FILE}: depth {shapes['depth']}, poses {shapes['poses']}, times {shapes['times']} "
                           f"do not match {t} frames of {h}x{w}")
    if not (np.isfinite(poses).all() and np.isfinite(times).all()):
        raise PreviewError(f"{TENSORS_FILE}: poses and times must be finite")
    intr = meta.get("intrinsics")
    if not isinstance(intr, dict) or intr.get("width") != w or intr.get("height") != h:
        raise PreviewError(f"{META_FILE}: intrinsics must describe the {w}x{h} preview frames")
    fps = meta.get("fps")
    if not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise PreviewError(f"{META_FILE}: fps must be a positive number, got {fps!r}")
    return StoredPreview(root, meta, poses.astype(np.float64), times.astype(np.float32), (t, h, w))
