"""Check an uploaded image, video or capture zip as `load_capture` will load it, without decoding it.

The service's upload check runs this in the API process, where a full decode would cost as
much memory as the capture (a 200 KB MP4 can declare 3000 HD frames). It reads what the
headers tell (image size, video size, frame rate and frame count, the depth array's shape),
decodes one video frame (does the stream decode at all?) and reads the first depth map (does
it hold any valid pixel?), and applies the same limits and the same resolution rules as
load_capture (frame budget, intrinsics, poses per kept frame, depth shape), raising the same
MediaError / CaptureError / CameraError. What only a full decode reveals (a frame corrupt
halfway through, a later depth map without valid pixels) is found by the worker, whose
load_capture enforces every limit again while decoding, and fails the job with the same code.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch

from core.capture.base import CaptureError
from core.capture.depth import check_depth_shape
from core.capture.load import (
    effective_limits,
    kept_per_frame,
    resolve_exposures,
    resolve_intrinsics,
    resolve_poses,
    sniff_capture_file,
)
from core.capture.params import CaptureParams
from core.conventions import valid_depth_mask
from core.io import probe_depth, probe_image, probe_video
from core.io.limits import MediaLimits
from core.io.nerfstudio import inspect_nerfstudio


@dataclass(frozen=True)
class CaptureHeader:
    kind: str  # "image" | "video" | "archive"
    frames: int  # frames load_capture will keep (after the frame budget)
    width: int
    height: int


def probe_capture(input_path, depth_path=None, params: CaptureParams | None = None,
                  limits: MediaLimits | None = None) -> CaptureHeader:
    """What load_capture(input_path, depth_path, params, limits) would load, checked from the
    headers (see module docstring). Only files: capture directories are not uploads."""
    params = params or CaptureParams()
    limits = effective_limits(params, limits)
    path = Path(input_path)
    if not path.is_file():
        raise CaptureError("input", f"{path} does not exist or is not a file")
    kind = sniff_capture_file(path)
    if kind == "video":
        video = probe_video(path, limits)
        width, height, fps = video.width, video.height, video.fps
        source_count, source_indices = video.frame_count, [int(i) for i in video.selected]
    elif kind == "image":
        (width, height), fps = probe_image(path, limits), None
        source_count, source_indices = 1, [0]
    elif kind == "archive":  # a nerfstudio capture: transforms.json and the files it names
        info = inspect_nerfstudio(path, limits)
        width, height, fps = info["intrinsics"]["width"], info["intrinsics"]["height"], None
        source_count, source_indices = info["frames"], info["kept"]
    else:
        raise CaptureError("input", f"{path.name} is neither an image, a video nor a capture zip")
    frames = len(source_indices)

    fps = params.fps or fps or 1.0
    if not (math.isfinite(fps) and fps > 0):
        raise CaptureError("fps", f"must be finite and > 0, got {fps}")
    resolve_intrinsics(params, None, width, height, [])
    resolve_poses(kept_per_frame(params.poses, frames, source_count, source_indices), frames)
    if not isinstance(params.frame_ev, str):  # "estimate" / "locked" name no values
        resolve_exposures(kept_per_frame(params.frame_ev, frames, source_count, source_indices), frames)
    if depth_path is not None:
        shape, first = probe_depth(Path(depth_path), limits)
        if len(shape) == 3 and shape[0] == source_count != frames:  # one map per source frame: subsampled alike
            shape = (frames, *shape[1:])
        check_depth_shape(shape, frames, height, width)
        if not bool(valid_depth_mask(torch.from_numpy(first)).any()):
            several = len(shape) == 3 and shape[0] > 1
            raise CaptureError("depth", "frame 0 has no valid depth pixels" if several
                               else "no valid pixels (all non-finite or <= 0)")
    return CaptureHeader(kind, frames, width, height)
