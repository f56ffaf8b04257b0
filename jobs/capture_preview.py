"""A small copy of a job's capture (frames, depth, cameras) kept for the web page: its
stored format and the worker's writer (the API reads it with service.stored_preview).

The worker deletes a job's uploads once the job succeeds, but the page needs the frame at
time t to click on, and the depth at the clicked pixel to place a probe just in front of
the surface. So, before the uploads go, the worker stores a preview beside the artefact:

    <job_dir>/preview/capture.safetensors   frames uint8 [T,h,w,3], depth float16 [T,h,w]
                                            (NaN where invalid; beyond 65504 m it reads as
                                            inf, i.e. invalid), poses float64 [T,4,4],
                                            times float32 [T] (seconds from the first frame),
                                            frame_ev float32 [T] (stops; only when the
                                            capture stated per-frame exposures)
    <job_dir>/preview/capture.json          format, version, intrinsics at the preview
                                            size, fps, depth source, source frame count,
                                            SHA-256 of capture.safetensors and of itself

It is made from the capture the engine decoded for the job (run_job's `on_capture`), so its
cameras, times and fallback depth are exactly the ones the light field was estimated with. At most PREVIEW_MAX_HEIGHT
rows
and PREVIEW_MAX_FRAMES frames (evenly spaced) are kept, which bounds it to a few tens of MB.
Written to a temporary sibling and renamed, like the artefact; never unpickled. The reader
(service.stored_preview) verifies both checksums before serving a byte (version 1 previews,
written before checksums existed, are read without).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.integrity import seal_document

PREVIEW_DIR = "preview"
TENSORS_FILE = "capture.safetensors"
META_FILE = "capture.json"
FORMAT = "lightfield-ui-preview"
VERSION = 2  # 2: checksums (core.integrity); 1 is still read
READABLE_VERSIONS = (1, 2)
PREVIEW_MAX_HEIGHT = 360
PREVIEW_MAX_FRAMES = 120


class PreviewCameras:
    """Shared by the in-memory and the stored preview: needs times, poses, intrinsics."""

    def nearest_frame(self, t: float) -> int:
        """Index of the stored frame closest in time to t (ties: the earlier frame)."""
        return int(np.argmin(np.abs(self.times.astype(np.float64) - float(t))))

    def camera(self, index: int):
        from core.camera import Camera, Intrinsics  # noqa: PLC0415 — core.camera pulls in torch: imported when used

        return Camera(Intrinsics(**self.intrinsics), self.poses[index])


@dataclass(frozen=True)
class CapturePreview(PreviewCameras):
    frames: np.ndarray  # uint8 [T, h, w, 3]
    depth: np.ndarray  # float32 [T, h, w] planar metres, NaN where invalid
    poses: np.ndarray  # float64 [T, 4, 4] camera-to-world
    times: np.ndarray  # float32 [T] seconds from the first frame
    intrinsics: dict  # fx, fy, cx, cy, width, height at the preview size
    fps: float
    depth_source: str
    source_frames: int  # frames the engine saw (before the preview's subsampling)
    frame_ev: np.ndarray | None = None  # float32 [T] stated exposure per frame (stops), when the capture gave them

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def height(self) -> int:
        return int(self.frames.shape[1])

    @property
    def width(self) -> int:
        return int(self.frames.shape[2])

    def frame(self, index: int) -> np.ndarray:
        return self.frames[index]

    def depth_map(self, index: int) -> np.ndarray:
        return self.depth[index]


def preview_dir(job_dir: Path) -> Path:
    return Path(job_dir) / PREVIEW_DIR


def _evenly_spaced(count: int, keep: int) -> np.ndarray:
    if count <= keep:
        return np.arange(count)
    return np.unique(np.round(np.linspace(0, count - 1, keep)).astype(np.int64))


def preview_from_capture(
    capture, max_height: int = PREVIEW_MAX_HEIGHT, max_frames: int = PREVIEW_MAX_FRAMES
) -> CapturePreview:
    """Downsample a core.capture.base.Capture: pick frames first (cheap), then the engine's own
    resize (area-averaged frames, nearest-surface depth)."""
    import torch  # noqa: PLC0415 — torch is heavy: imported when used

    from core.conventions import valid_depth_mask  # noqa: PLC0415 — core.conventions pulls in torch: imported when used

    keep = torch.from_numpy(_evenly_spaced(capture.num_frames, max_frames))
    picked = dataclasses.replace(capture, frames=capture.frames[keep], depth=capture.depth[keep],
                                 poses=capture.poses[keep], times=capture.times[keep],
                                 stated_ev=None if capture.stated_ev is None else capture.stated_ev[keep])
    small = picked.resized(max_height)
    frames = (small.frames.clamp(0, 1) * 255.0).round().to(torch.uint8).numpy()
    depth = torch.where(valid_depth_mask(small.depth), small.depth, float("nan")).numpy().astype(np.float32)
    return CapturePreview(
        frames=np.ascontiguousarray(frames),
        depth=depth,
        poses=small.poses.numpy().astype(np.float64),
        times=small.times.numpy().astype(np.float32),
        intrinsics=small.intrinsics.as_dict(),
        fps=float(small.fps),
        depth_source=str(small.depth_source),
        source_frames=int(capture.num_frames),
        frame_ev=None if small.stated_ev is None else small.stated_ev.numpy().astype(np.float32),
    )


def save_preview(preview: CapturePreview, job_dir: Path) -> Path:
    """Write the preview under job_dir atomically (temp sibling + rename); return its directory."""
    from safetensors.numpy import save_file  # noqa: PLC0415 — safetensors is heavy: imported when used

    job_dir = Path(job_dir)
    job_dir.mkdir(parents=True, exist_ok=True)
    final = preview_dir(job_dir)
    tmp = Path(tempfile.mkdtemp(prefix=f".{PREVIEW_DIR}.tmp-", dir=job_dir))
    try:
        tensors = {
            "frames": preview.frames,
            "depth": preview.depth.astype(np.float16),
            "poses": preview.poses.astype(np.float64),
            "times": preview.times.astype(np.float32),
        }
        if preview.frame_ev is not None:
            tensors["frame_ev"] = preview.frame_ev.astype(np.float32)
        save_file(tensors, str(tmp / TENSORS_FILE))
        meta = {"format": FORMAT, "version": VERSION, "intrinsics": preview.intrinsics, "fps": preview.fps,
                "depth_source": preview.depth_source, "source_frames": preview.source_frames,
                "tensors_sha256": file_sha256(tmp / TENSORS_FILE)}
        (tmp / META_FILE).write_text(json.dumps(seal_document(meta), indent=2))
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def file_sha256(path: Path) -> str:
    """SHA-256 of a file, read in 1 MiB blocks (previews reach tens of MB)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_capture_preview(capture, job_dir: Path) -> Path:
    """Store the preview of the capture the engine decoded (the worker's on_capture hook).
    Idempotent: an existing preview (a re-delivered job) is kept."""
    if (preview_dir(job_dir) / META_FILE).is_file():
        return preview_dir(job_dir)
    return save_preview(preview_from_capture(capture), job_dir)
