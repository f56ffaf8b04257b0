"""Load a capture (image, video, nerfstudio capture directory or zip, simulator capture
directory) into one validated `Capture`.

Files are read as a viewer shows them (EXIF orientation, video display rotation, ICC colour
profile -> sRGB: core.io.metadata); what they said is in `Capture.metadata`.
Defaults when the user gives nothing (recorded in `Capture.warnings` / `depth_source` /
`metadata`; docs/captures.md):
* intrinsics: the capture file's, else the image's EXIF focal length, else a centred pinhole
  with horizontal FOV `core.conventions.DEFAULT_HFOV_DEG`;
* poses: several frames are tracked when the capture is prepared (core.capture.prepare, then
  core.capture.track; `params.tracking`), one frame is a
  camera at the world origin (world = first camera frame);
* fps: the video's own rate, else 1 (a single image has t = 0); a video's frame times are its
  presentation timestamps (a variable frame rate keeps its real timing) unless params.fps is
  given, which times frame i at i / fps;
* depth: the given file, else the geometric assumption `assumed_box_depth` (a 5 x 3 x 4 m box
  room seen from a camera 1.5 m above the floor looking at the back wall; the SCALE IS
  ARBITRARY and so is the geometry — good enough to place probes and splat colours, not a
  measurement); or, when the env var `DEPTH_MODEL_ENV` (LIGHTFIELD_DEPTH_MODEL) names a
  local model directory, a learned estimator (`core.capture.depth_model`, relative scale).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np
import torch

from core.camera import CameraError, Intrinsics, check_rigid_pose
from core.capture.base import Capture, CaptureError
from core.capture.depth import resolve_depth
from core.capture.depth_model import load_depth_estimator
from core.capture.params import MAX_EXPOSURE_STOPS, CaptureParams
from core.conventions import DEFAULT_HFOV_DEG, GAMMA, frame_time
from core.io import read_depth, read_image, select_frame_indices, sniff_media
from core.io.images import decode_image
from core.io.limits import MediaLimits
from core.io.metadata import exif_intrinsics
from core.io.nerfstudio import load_nerfstudio
from core.io.sniff import ZIP_MAGIC, sniff_image
from core.transfer import AUTO, SRGB, parse_transfer

DEPTH_MODEL_ENV = "LIGHTFIELD_DEPTH_MODEL"


# ---------------------------------------------------------------------------------------
# Readers (core.io: limits, magic-byte sniffing; MediaError propagates with its .code)
# ---------------------------------------------------------------------------------------
def _read_image(path: Path, limits: MediaLimits) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(read_image(path, limits=limits), dtype=np.float32))


def _read_depth(path: Path, limits: MediaLimits) -> torch.Tensor:
    """Depth file (.npz 'depth' / .npy / .exr / 16-bit PNG mm) -> float32 [T,H,W] or [H,W], NaN invalid."""
    return torch.from_numpy(np.ascontiguousarray(read_depth(path, limits=limits), dtype=np.float32))


def sniff_capture_file(path: Path) -> str | None:
    """'image', 'video', 'archive' (a zip: a nerfstudio capture) or None from magic bytes. A GIF
    is a 'video' (possibly animated), as the service's upload validation classifies it, so
    every frame is decoded under the limits."""
    with open(path, "rb") as f:
        head = f.read(64)
    if head.startswith(ZIP_MAGIC):
        return "archive"
    return "video" if sniff_image(head) == "gif" else sniff_media(head)


EXIF_EXPOSURE_SOURCE = "the images' EXIF: log2(exposure time x ISO / f-number^2), relative to the first"


def _read_nerfstudio(source: Path, limits: MediaLimits) -> dict:
    """A nerfstudio capture (directory or zip with transforms.json; core.io.nerfstudio)."""
    cap = load_nerfstudio(source, limits)
    out = {"frames": torch.from_numpy(cap.frames), "intrinsics_dict": cap.intrinsics, "poses": cap.poses,
           "poses_source": "nerfstudio transforms.json", "intrinsics_source": "nerfstudio transforms.json",
           "source_indices": cap.source_indices, "original_count": cap.original_count,
           "metadata": {"nerfstudio": cap.metadata}, "warnings": cap.warnings}
    if cap.depth is not None:
        out["depth"] = torch.from_numpy(cap.depth)
        out["depth_source"] = "file:nerfstudio depth_file_path"
    if cap.frame_ev is not None:  # a photo set taken in auto mode: each photo's EXIF states its exposure
        out["frame_ev"] = cap.frame_ev
        out["exposure_source"] = EXIF_EXPOSURE_SOURCE
    return out


def _read_image_file(path: Path, limits: MediaLimits) -> dict:
    """One image, upright and sRGB, with what its metadata says (EXIF focal length -> intrinsics)."""
    img = decode_image(path, limits)
    h, w = img.pixels.shape[:2]
    out = {"frames": torch.from_numpy(np.ascontiguousarray(img.pixels, dtype=np.float32))[None],
           "metadata": {"file": img.metadata.as_dict(), **({"applied": img.applied} if img.applied else {})},
           "stated_transfer": img.stated_transfer}
    exif = exif_intrinsics(img.metadata, w, h, stored_width=img.stored_size[0])
    if exif is not None:
        out["exif_intrinsics"] = exif
    return out


# ---------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------
def _read_capture_dir(root: Path, limits: MediaLimits) -> dict:
    index_path = root / "capture.json"
    try:
        index = json.loads(index_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CaptureError("input", f"cannot read {index_path}: {exc}") from None
    if index.get("format") != "lightfield-capture":
        raise CaptureError("input", f"{index_path} is not a lightfield capture (format={index.get('format')!r})")
    names = index.get("frames") or []
    if not names:
        raise CaptureError("frames", "capture.json lists no frames")
    h, w = int(index.get("intrinsics", {}).get("height", 1)), int(index.get("intrinsics", {}).get("width", 1))
    keep = [int(i) for i in select_frame_indices(len(names), h * w, limits)]
    first = decode_image(root / names[keep[0]], limits)  # what the frames' files say of their curve
    frames = torch.stack([_read_image(root / names[i], limits) for i in keep])
    out = {"frames": frames, "fps": float(index["fps"]) if index.get("fps") else None, "source_indices": keep,
           "original_count": len(names), "stated_transfer": first.stated_transfer}
    if index.get("transfer") is not None:  # the capture app states its camera's curve
        out["declared_transfer"] = (str(index["transfer"]), "capture.json")
    intr = index.get("intrinsics")
    if intr:
        out["intrinsics_dict"] = intr
        out["intrinsics_source"] = "capture.json"
    frame_ev = index.get("frame_ev")  # per-frame exposure metadata (an auto-exposure clip), optional
    if frame_ev is not None:
        if not isinstance(frame_ev, list) or not all(isinstance(e, (int, float)) for e in frame_ev):
            raise CaptureError("frame_ev", f"{index_path} frame_ev must be a list of numbers, one per frame")
        out["frame_ev"] = [frame_ev[i] for i in keep] if len(frame_ev) == len(names) else frame_ev
    poses = index.get("poses")
    if poses:
        out["poses"] = [poses[i] for i in keep] if len(poses) == len(names) else poses
        out["poses_source"] = "capture.json"
    if index.get("depth"):
        d = _read_depth(root / index["depth"], limits)
        out["depth"] = d[keep] if d.ndim == 3 and d.shape[0] == len(names) else d
        out["depth_source"] = f"file:{index['depth']}"
    return out


ASSUMED_INTRINSICS_SOURCE = f"assumed: centred pinhole, {DEFAULT_HFOV_DEG:g} deg horizontal FOV"


def resolve_intrinsics(params: CaptureParams, file_intr: dict | None, width: int, height: int,
                       warn: list[str], exif: tuple[Intrinsics, str] | None = None,
                       sources: dict | None = None) -> Intrinsics:
    """params > the capture file's > the image's EXIF (`exif`: intrinsics and the rule used) >
    the assumption; `sources["intrinsics_source"]` says which."""
    sources = {} if sources is None else sources
    try:
        if params.intrinsics is not None:
            p = params.intrinsics
            sources["intrinsics_source"] = "params"
            if p.hfov_deg is not None:
                return Intrinsics.from_hfov(width, height, p.hfov_deg).check_plausible()
            return Intrinsics(p.fx, p.fy, p.cx, p.cy, width, height).check_plausible()
        if file_intr is not None:
            k = Intrinsics(float(file_intr["fx"]), float(file_intr["fy"]), float(file_intr["cx"]),
                           float(file_intr["cy"]), int(file_intr.get("width", width)),
                           int(file_intr.get("height", height)))
            sources.setdefault("intrinsics_source", "capture file")
            return (k if (k.width, k.height) == (width, height) else k.scaled(width, height)).check_plausible()
    except CameraError as exc:
        raise CaptureError("intrinsics", str(exc)) from None
    if exif is not None:
        sources["intrinsics_source"] = exif[1]
        return exif[0]
    warn.append(f"no intrinsics given: assuming a centred pinhole with {DEFAULT_HFOV_DEG:g} deg horizontal FOV")
    sources["intrinsics_source"] = ASSUMED_INTRINSICS_SOURCE
    return Intrinsics.from_hfov(width, height, DEFAULT_HFOV_DEG)


def kept_per_frame(given, T: int, source_count: int, source_indices: list[int]):
    """The given per-frame values (poses, exposures) of the kept frames: values given for every
    source frame follow the frames' subsampling; any other count is kept as is (resolve_poses
    and resolve_exposures refuse a mismatch)."""
    if given is not None and len(given) == source_count != T:
        return [given[i] for i in source_indices]
    return given


def effective_limits(params: CaptureParams, limits: MediaLimits | None) -> MediaLimits:
    """`limits` (default: from the environment), with params.max_frames lowering max_frames."""
    limits = limits or MediaLimits.from_env()
    if params.max_frames is not None and params.max_frames < limits.max_frames:
        limits = dataclasses.replace(limits, max_frames=params.max_frames)
    return limits


def resolve_poses(poses, T: int) -> torch.Tensor:
    if poses is None:
        return torch.eye(4, dtype=torch.float64).expand(T, 4, 4).clone()
    p = torch.as_tensor(poses, dtype=torch.float64)
    if p.ndim == 2 and p.shape[-1] == 16:
        p = p.reshape(-1, 4, 4)
    if p.ndim != 3 or p.shape[1:] != (4, 4):
        raise CaptureError("poses", f"expected T x 16 numbers (row-major 4x4), got shape {tuple(p.shape)}")
    if p.shape[0] != T:
        raise CaptureError("poses", f"{p.shape[0]} poses for {T} frames (they must match)")
    if not torch.isfinite(p).all():
        raise CaptureError("poses", "contains non-finite values")
    for i in range(p.shape[0]):
        try:
            check_rigid_pose(p[i], f"poses[{i}]")
        except CameraError as exc:
            raise CaptureError("poses", str(exc)) from None
    return p


def resolve_exposures(frame_ev, T: int) -> torch.Tensor | None:
    """[T] float32 per-frame exposure in stops, or None when the capture gives none."""
    if frame_ev is None:
        return None
    e = torch.as_tensor(frame_ev, dtype=torch.float32).reshape(-1)
    if e.shape[0] != T:
        raise CaptureError("frame_ev", f"{e.shape[0]} exposures for {T} frames (they must match)")
    if not bool((torch.isfinite(e) & (e.abs() <= MAX_EXPOSURE_STOPS)).all()):
        raise CaptureError("frame_ev", f"must be finite and within +-{MAX_EXPOSURE_STOPS:g} stops")
    return e


def _estimate_depth(
    frames: torch.Tensor, intr: Intrinsics, model_dir: str, warn: list[str]
) -> tuple[torch.Tensor, str]:
    estimator = load_depth_estimator(model_dir)
    warn.append(f"no depth given: estimated by the model in {DEPTH_MODEL_ENV} ({estimator.depth_source}); "
                "probe placement and reprojection are approximate")
    return estimator(frames, intr), estimator.depth_source


def load_capture(input_path, depth_path=None, params: CaptureParams | None = None,
                 limits: MediaLimits | None = None) -> Capture:
    """Load an image, a video, a nerfstudio capture (directory or zip) or a simulator capture
    directory (see module docstring), before camera tracking: a job prepares what this returns
    in stages of its own (core.capture.prepare; `load_prepared_capture` there loads and
    prepares in one call).

    `limits=None` reads them from the environment (`MediaLimits.from_env`: LIGHTFIELD_MAX_PIXELS
    etc.), so the CLI honours the same variables as the service. `params.max_frames` lowers
    `limits.max_frames`; longer videos are subsampled evenly by core.io and each kept frame
    keeps its source time (source index / fps). Poses given for every source frame are
    subsampled the same way. (The service's upload check reads headers only:
    core.capture.probe.probe_capture.)
    """
    params = params or CaptureParams()
    limits = effective_limits(params, limits)
    path = Path(input_path)
    warn: list[str] = []
    loaded = read_capture_input(path, limits, warn)
    metadata = dict(loaded.get("metadata", {}))
    frames = decode_transfer(_checked_frames(loaded["frames"]), params, loaded, metadata)
    T, H, W, _ = frames.shape
    source_idx = loaded.get("source_indices") or list(range(T))
    fps = params.fps or loaded.get("fps") or 1.0
    if not (math.isfinite(fps) and fps > 0):
        raise CaptureError("fps", f"must be finite and > 0, got {fps}")
    if loaded.get("intrinsics_source"):
        metadata["intrinsics_source"] = loaded["intrinsics_source"]
    intr = resolve_intrinsics(
        params, loaded.get("intrinsics_dict"), W, H, warn, loaded.get("exif_intrinsics"), metadata
    )
    poses, frame_ev = _per_frame_values(params, loaded, T, source_idx, metadata)
    depth, depth_src = _capture_depth(depth_path, loaded, frames, intr, source_idx, limits, warn, metadata)
    return Capture(
        frames=frames.clamp(0, 1).contiguous(),
        depth=depth.contiguous(),
        intrinsics=intr,
        poses=poses,
        times=_frame_times(params, loaded, source_idx, fps),
        fps=float(fps),
        depth_source=depth_src,
        source=path.name,
        warnings=warn,
        metadata=metadata,
        stated_ev=frame_ev,
    )


def read_capture_input(path: Path, limits: MediaLimits, warn: list[str]) -> dict:
    """What the reader of `path`'s kind returned (a directory: nerfstudio or simulator capture;
    a file: sniffed video, image or nerfstudio zip); their warnings appended to `warn`."""
    from core.io import read_video  # noqa: PLC0415 — looked up at call time: tests patch core.io.read_video

    if not path.exists():
        raise CaptureError("input", f"{path} does not exist")
    if path.is_dir():
        loaded = (
            _read_nerfstudio(path, limits) if (path / "transforms.json").is_file() else _read_capture_dir(path, limits)
        )
    else:
        kind = sniff_capture_file(path)
        if kind == "video":
            vf = read_video(path, limits)
            warn.extend(vf.warnings)
            loaded = {
                "frames": torch.from_numpy(np.ascontiguousarray(vf.frames)),
                "fps": vf.fps,
                "source_indices": [int(i) for i in vf.source_frame_indices],
                "original_count": vf.original_frame_count,
                "times": vf.times,
                "stated_transfer": vf.stated_transfer,
            }  # presentation timestamps (variable frame rate), else index / fps
            if vf.rotation_ccw_deg:
                loaded["metadata"] = {
                    "applied": [
                        f"video display rotation {vf.rotation_ccw_deg} deg counter-clockwise: frames turned upright"
                    ]
                }
        elif kind == "image":
            loaded = _read_image_file(path, limits)
        elif kind == "archive":
            loaded = _read_nerfstudio(path, limits)
        else:
            raise CaptureError("input", f"{path.name} is neither an image, a video nor a capture directory or zip")
    warn.extend(loaded.get("warnings", []))
    return loaded


DEFAULT_TRANSFER_SOURCE = "default: the file states no transfer, read as sRGB (what cameras and phones write)"
# linear BT.2020 RGB -> linear BT.709 / sRGB RGB (ITU-R BT.2087); out-of-gamut colours clip at 0
BT2020_TO_BT709 = torch.tensor([[1.6605, -0.5876, -0.0728], [-0.1246, 1.1329, -0.0083], [-0.0182, -0.1006, 1.1187]])


def decode_transfer(frames: torch.Tensor, params: CaptureParams, loaded: dict, metadata: dict) -> torch.Tensor:
    """The frames' code values decoded from their camera's transfer into the engine's convention
    (core.transfer): params.transfer unless 'auto', else what the capture file declares
    (capture.json), else what the image or video file says, else sRGB. `metadata["transfer"]`
    records the curve, where it came from, and the file's bit depth and primaries."""
    stated = loaded.get("stated_transfer")
    if params.transfer != AUTO:
        transfer, source = parse_transfer(params.transfer), "params"
    elif loaded.get("declared_transfer") is not None:
        text, where = loaded["declared_transfer"]
        try:
            transfer, source = parse_transfer(text), where
        except ValueError as exc:
            raise CaptureError("transfer", f"{where}: {exc}") from None
    elif stated is not None and stated.transfer is not None:
        transfer, source = stated.transfer, stated.source
    else:
        transfer, source = SRGB, DEFAULT_TRANSFER_SOURCE
    primaries = None if stated is None else stated.primaries
    bits = None if stated is None else stated.bit_depth
    metadata["transfer"] = {"curve": str(transfer), "source": source, "bit_depth": bits,
                            "primaries": primaries or "bt709"}
    if primaries != "bt2020":
        return transfer.to_convention(frames)
    linear = (transfer.to_linear(frames) @ BT2020_TO_BT709.T).clamp(0.0, 1.0)
    return linear.pow(1.0 / GAMMA)


def _checked_frames(frames: torch.Tensor) -> torch.Tensor:
    """The decoded frames as float [T, H, W, 3], finite (CaptureError otherwise)."""
    frames = frames.float()
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] < 1:
        raise CaptureError("input", f"decoded frames have shape {tuple(frames.shape)}, expected [T, H, W, 3]")
    if not torch.isfinite(frames).all():
        raise CaptureError("input", "frames contain non-finite values")
    return frames


def _per_frame_values(params: CaptureParams, loaded: dict, T: int, source_idx: list[int],
                      metadata: dict) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The poses and stated exposures (params' over the capture file's), and where they came
    from in `metadata` (poses_source, exposure_source)."""
    source_count = loaded.get("original_count", T)
    given_poses = (
        loaded.get("poses") if params.poses is None else kept_per_frame(params.poses, T, source_count, source_idx)
    )
    poses = resolve_poses(given_poses, T)
    if given_poses is not None:
        metadata["poses_source"] = "params" if params.poses is not None else loaded.get("poses_source", "capture file")
    given_ev = (
        loaded.get("frame_ev")
        if params.frame_ev is None
        else kept_per_frame(params.frame_ev, T, source_count, source_idx)
    )
    if isinstance(params.frame_ev, str):  # "estimate" / "locked": after tracking (core.capture.autoexposure)
        given_ev = None
    frame_ev = resolve_exposures(given_ev, T)
    if given_ev is not None:
        metadata["exposure_source"] = (
            "params" if params.frame_ev is not None else loaded.get("exposure_source", "capture.json")
        )
    return poses, frame_ev


def _capture_depth(depth_path, loaded: dict, frames: torch.Tensor, intr: Intrinsics, source_idx: list[int],
                   limits: MediaLimits, warn: list[str], metadata: dict) -> tuple[torch.Tensor, str]:
    """Depth [T, H, W] and its source: the given file (subsampled as the frames), else the
    capture's, else the depth model's (DEPTH_MODEL_ENV), else the assumption (resolve_depth)."""
    T, H, W, _ = frames.shape
    depth_arg = _read_depth(Path(depth_path), limits) if depth_path is not None else loaded.get("depth")
    if depth_path is not None and depth_arg.ndim == 3 and depth_arg.shape[0] == loaded.get("original_count", T) != T:
        depth_arg = depth_arg[source_idx]
    depth_src = f"file:{Path(depth_path).name}" if depth_path is not None else loaded.get("depth_source")
    metadata["depth_given"] = depth_arg is not None
    if depth_arg is None and os.environ.get(DEPTH_MODEL_ENV):
        depth_arg, depth_src = _estimate_depth(frames, intr, os.environ[DEPTH_MODEL_ENV], warn)
    return resolve_depth(depth_arg, T, H, W, intr, depth_src, warn)


def _frame_times(params: CaptureParams, loaded: dict, source_idx: list[int], fps: float) -> torch.Tensor:
    """A video's presentation timestamps unless params.fps is given, else source index / fps."""
    if loaded.get("times") is not None and params.fps is None:
        return torch.as_tensor(loaded["times"], dtype=torch.float32)
    return frame_time(torch.tensor(source_idx, dtype=torch.float32), fps)


def capture_from_arrays(
    frames: torch.Tensor,
    depth: torch.Tensor | None = None,
    *,
    intrinsics: Intrinsics | None = None,
    poses: torch.Tensor | None = None,
    fps: float = 1.0,
    source: str = "arrays",
    frame_ev=None,
) -> Capture:
    """Build a validated Capture from in-memory tensors (tests, the demo, the simulator);
    `frame_ev`: each frame's stated exposure in stops (as CaptureParams.frame_ev)."""
    frames = torch.as_tensor(frames, dtype=torch.float32)
    if frames.ndim == 3:
        frames = frames[None]
    T, H, W, _ = frames.shape
    warn: list[str] = []
    intr = intrinsics or Intrinsics.from_hfov(W, H, DEFAULT_HFOV_DEG)
    p = resolve_poses(None if poses is None else torch.as_tensor(poses, dtype=torch.float64), T)
    d, src = resolve_depth(depth, T, H, W, intr, "arrays" if depth is not None else None, warn)
    return Capture(frames.clamp(0, 1).contiguous(), d.contiguous(), intr, p,
                   frame_time(torch.arange(T, dtype=torch.float32), fps), float(fps), src, source, warn,
                   stated_ev=resolve_exposures(frame_ev, T))
