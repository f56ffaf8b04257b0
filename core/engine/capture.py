"""Load a capture (image, video or simulator capture directory) into one validated `Capture`.

Defaults when the user gives nothing (recorded in `Capture.warnings` / `depth_source`):
* intrinsics: a centred pinhole with horizontal FOV `core.conventions.DEFAULT_HFOV_DEG`;
* poses: a static camera at the world origin (world = first camera frame);
* fps: the video's own rate, else 1 (a single image has t = 0);
* depth: the given file, else the geometric assumption `assumed_box_depth` (a 5 x 3 x 4 m box
  room seen from a camera 1.5 m above the floor looking at the back wall; the SCALE IS
  ARBITRARY and so is the geometry — good enough to place probes and splat colours, not a
  measurement); or, when the env var `DEPTH_MODEL_ENV` (LIGHTFIELD_DEPTH_MODEL) names a
  local model directory, a learned estimator (`core.engine.depth_model`, relative scale).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings as _warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from core.camera import Camera, CameraError, Intrinsics
from core.conventions import DEFAULT_HFOV_DEG, frame_time, pixel_to_camera_ray, valid_depth_mask
from core.engine.params import CaptureParams
from core.io.limits import MediaLimits

# Depth with fewer valid pixels than this (per frame) is hole-filled with a warning.
MIN_VALID_DEPTH_FRACTION = 0.5
ASSUMED_DEPTH_SOURCE = "assumed:box-room 5x3x4 m, camera 1.5 m above floor, arbitrary scale"
DEPTH_MODEL_ENV = "LIGHTFIELD_DEPTH_MODEL"
DEFAULT_MEDIAN_DEPTH_M = 2.0  # metres, when a frame has no valid depth at all


class CaptureError(ValueError):
    """Bad or inconsistent capture input; `.field` names the offending input."""

    def __init__(self, field_name: str, message: str):
        super().__init__(f"{field_name}: {message}")
        self.field = field_name


@dataclass
class Capture:
    frames: torch.Tensor  # [T, H, W, 3] float32 LDR in [0, 1]
    depth: torch.Tensor  # [T, H, W] float32 planar metres, NaN where invalid
    intrinsics: Intrinsics
    poses: torch.Tensor  # [T, 4, 4] float64 camera-to-world
    times: torch.Tensor  # [T] float32 seconds from the first frame
    fps: float
    depth_source: str
    source: str = ""
    warnings: list[str] = field(default_factory=list)

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def height(self) -> int:
        return int(self.frames.shape[1])

    @property
    def width(self) -> int:
        return int(self.frames.shape[2])

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0]) if self.num_frames > 1 else 0.0

    @property
    def static_camera(self) -> bool:
        return bool(torch.allclose(self.poses, self.poses[:1].expand_as(self.poses), atol=1e-9))

    def camera(self, i: int) -> Camera:
        return Camera(self.intrinsics, self.poses[i])

    def resized(self, height: int) -> "Capture":
        """The same capture at a working resolution (area-averaged frames, nearest-valid depth
        by min-pooling so thin near objects are not averaged with the far wall)."""
        if height >= self.height:
            return self
        width = max(1, round(self.width * height / self.height))
        f = torch.nn.functional.interpolate(self.frames.permute(0, 3, 1, 2), size=(height, width), mode="area")
        d = self.depth.clone()
        d = torch.where(valid_depth_mask(d), d, torch.full_like(d, float("inf")))
        d = -torch.nn.functional.adaptive_max_pool2d(-d[:, None], (height, width))[:, 0]
        d = torch.where(torch.isfinite(d), d, torch.full_like(d, float("nan")))
        return Capture(
            frames=f.permute(0, 2, 3, 1).contiguous().clamp(0, 1),
            depth=d.contiguous(),
            intrinsics=self.intrinsics.scaled(width, height),
            poses=self.poses,
            times=self.times,
            fps=self.fps,
            depth_source=self.depth_source,
            source=self.source,
            warnings=list(self.warnings),
        )

    def summary(self) -> dict:
        return {
            "source": self.source,
            "frames": self.num_frames,
            "width": self.width,
            "height": self.height,
            "fps": self.fps,
            "duration_s": self.duration,
            "intrinsics": self.intrinsics.as_dict(),
            "static_camera": self.static_camera,
            "poses": self.poses.reshape(self.num_frames, 16).tolist(),
            "depth_source": self.depth_source,
            "warnings": list(self.warnings),
        }


# ---------------------------------------------------------------------------------------
# Assumed geometry and hole filling
# ---------------------------------------------------------------------------------------
def assumed_box_depth(intr: Intrinsics, half_width: float = 2.5, floor: float = 1.5,
                      ceiling: float = 1.5, back: float = 4.0) -> torch.Tensor:
    """Planar depth [H, W] of a box room around a camera looking along -z at its origin.

    The ray through a pixel is s * (x, y, -1) with planar depth s; it hits the floor at
    s = floor / -y, the ceiling at ceiling / y, the side walls at half_width / |x| and the
    back wall at s = back; the nearest positive hit is the depth.
    """
    v, u = torch.meshgrid(torch.arange(intr.height, dtype=torch.float64) + 0.5,
                          torch.arange(intr.width, dtype=torch.float64) + 0.5, indexing="ij")
    ray = pixel_to_camera_ray(u, v, intr.fx, intr.fy, intr.cx, intr.cy)
    x, y = ray[..., 0], ray[..., 1]
    inf = torch.full_like(x, math.inf)
    s = torch.full_like(x, back)
    s = torch.minimum(s, torch.where(y < 0, floor / (-y).clamp_min(1e-12), inf))
    s = torch.minimum(s, torch.where(y > 0, ceiling / y.clamp_min(1e-12), inf))
    s = torch.minimum(s, torch.where(x.abs() > 0, half_width / x.abs().clamp_min(1e-12), inf))
    return s.float()


def median_valid_depth(depth: torch.Tensor) -> float:
    """Median of the valid pixels of a depth map: the stand-in where a pixel's depth is invalid
    (DEFAULT_MEDIAN_DEPTH_M when no pixel is valid)."""
    valid = valid_depth_mask(depth)
    return float(depth[valid].median()) if bool(valid.any()) else DEFAULT_MEDIAN_DEPTH_M


def fill_depth_holes(depth: torch.Tensor, max_iters: int = 64) -> torch.Tensor:
    """Fill invalid pixels of [H, W] depth by repeated 3x3 mean of valid neighbours (a
    diffusion fill). Keeps valid pixels unchanged. Requires at least one valid pixel."""
    d = depth.clone()
    valid = valid_depth_mask(d)
    kernel = torch.ones(1, 1, 3, 3, dtype=d.dtype)
    for _ in range(max_iters):
        if valid.all():
            break
        num = torch.nn.functional.conv2d(torch.where(valid, d, 0)[None, None], kernel, padding=1)[0, 0]
        cnt = torch.nn.functional.conv2d(valid.to(d.dtype)[None, None], kernel, padding=1)[0, 0]
        grow = ~valid & (cnt > 0)
        d = torch.where(grow, num / cnt.clamp_min(1), d)
        valid = valid | grow
    if not valid.all():  # disconnected leftovers: the median of what we have
        d = torch.where(valid, d, d[valid].median())
    return d


# ---------------------------------------------------------------------------------------
# Readers (core.io: limits, magic-byte sniffing; MediaError propagates with its .code)
# ---------------------------------------------------------------------------------------
def _read_image(path: Path, limits: MediaLimits) -> torch.Tensor:
    from core.io import read_image

    return torch.from_numpy(np.ascontiguousarray(read_image(path, limits=limits), dtype=np.float32))


def _read_depth(path: Path, limits: MediaLimits) -> torch.Tensor:
    """Depth file (.npz 'depth' / .npy / .exr / 16-bit PNG mm) -> float32 [T,H,W] or [H,W], NaN invalid."""
    from core.io import read_depth

    return torch.from_numpy(np.ascontiguousarray(read_depth(path, limits=limits), dtype=np.float32))


def _sniff(path: Path) -> str | None:
    """'image', 'video' or None from magic bytes. A GIF is a 'video' (possibly animated), as
    the service's upload validation classifies it, so every frame is decoded under the limits."""
    from core.io import sniff_media
    from core.io.sniff import sniff_image

    with open(path, "rb") as f:
        head = f.read(64)
    return "video" if sniff_image(head) == "gif" else sniff_media(head)


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
    from core.io import select_frame_indices

    h, w = int(index.get("intrinsics", {}).get("height", 1)), int(index.get("intrinsics", {}).get("width", 1))
    keep = [int(i) for i in select_frame_indices(len(names), h * w, limits)]
    frames = torch.stack([_read_image(root / names[i], limits) for i in keep])
    out = {"frames": frames, "fps": float(index["fps"]) if index.get("fps") else None, "source_indices": keep,
           "original_count": len(names)}
    intr = index.get("intrinsics")
    if intr:
        out["intrinsics_dict"] = intr
    poses = index.get("poses")
    if poses:
        out["poses"] = [poses[i] for i in keep] if len(poses) == len(names) else poses
    if index.get("depth"):
        d = _read_depth(root / index["depth"], limits)
        out["depth"] = d[keep] if d.ndim == 3 and d.shape[0] == len(names) else d
        out["depth_source"] = f"file:{index['depth']}"
    return out


def _resolve_intrinsics(params: CaptureParams, file_intr: dict | None, width: int, height: int,
                        warn: list[str]) -> Intrinsics:
    try:
        if params.intrinsics is not None:
            p = params.intrinsics
            if p.hfov_deg is not None:
                return Intrinsics.from_hfov(width, height, p.hfov_deg)
            return Intrinsics(p.fx, p.fy, p.cx, p.cy, width, height)
        if file_intr is not None:
            k = Intrinsics(float(file_intr["fx"]), float(file_intr["fy"]), float(file_intr["cx"]),
                           float(file_intr["cy"]), int(file_intr.get("width", width)),
                           int(file_intr.get("height", height)))
            return k if (k.width, k.height) == (width, height) else k.scaled(width, height)
    except CameraError as exc:
        raise CaptureError("intrinsics", str(exc)) from None
    warn.append(f"no intrinsics given: assuming a centred pinhole with {DEFAULT_HFOV_DEG:g} deg horizontal FOV")
    return Intrinsics.from_hfov(width, height, DEFAULT_HFOV_DEG)


def _resolve_poses(poses, T: int) -> torch.Tensor:
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
    return p


def _resolve_depth(depth, T: int, H: int, W: int, intr: Intrinsics, source: str | None,
                   warn: list[str]) -> tuple[torch.Tensor, str]:
    if depth is None:
        warn.append("no depth given: using the assumed box-room geometry (arbitrary scale); "
                    "probe placement and reprojection are approximate")
        return assumed_box_depth(intr).expand(T, H, W).clone(), ASSUMED_DEPTH_SOURCE
    d = torch.as_tensor(depth, dtype=torch.float32)
    if d.ndim == 2:
        d = d[None]
    if d.ndim != 3:
        raise CaptureError("depth", f"expected [T, H, W] or [H, W], got shape {tuple(d.shape)}")
    if tuple(d.shape[1:]) != (H, W):
        raise CaptureError("depth", f"depth size {d.shape[2]}x{d.shape[1]} does not match frame size {W}x{H}")
    if d.shape[0] == 1 and T > 1:
        d = d.expand(T, H, W)
    elif d.shape[0] != T:
        raise CaptureError("depth", f"{d.shape[0]} depth maps for {T} frames (give 1 or {T})")
    d = d.clone()
    valid = valid_depth_mask(d)
    if not valid.any():
        raise CaptureError("depth", "no valid pixels (all non-finite or <= 0)")
    filled = []
    for i in range(T):
        frac = float(valid[i].float().mean())
        if frac == 0.0:
            raise CaptureError("depth", f"frame {i} has no valid depth pixels")
        if frac < MIN_VALID_DEPTH_FRACTION:
            filled.append(i)
            d[i] = fill_depth_holes(d[i])
    if filled:
        warn.append(f"depth mostly invalid in {len(filled)} frame(s) (< {MIN_VALID_DEPTH_FRACTION:.0%} valid): holes filled by diffusion")
    d = torch.where(valid_depth_mask(d), d, torch.full_like(d, float("nan")))
    return d, source or "file"


def _estimate_depth(frames: torch.Tensor, intr: Intrinsics, model_dir: str, warn: list[str]) -> tuple[torch.Tensor, str]:
    from core.engine.depth_model import load_depth_estimator

    estimator = load_depth_estimator(model_dir)
    warn.append(f"no depth given: estimated by the model in {DEPTH_MODEL_ENV} ({estimator.depth_source}); "
                "probe placement and reprojection are approximate")
    return estimator(frames, intr), estimator.depth_source


def load_capture(input_path, depth_path=None, params: CaptureParams | None = None,
                 limits: MediaLimits | None = None, estimate_depth: bool = True) -> Capture:
    """Load an image, a video or a simulator capture directory (see module docstring).

    `limits=None` reads them from the environment (`MediaLimits.from_env`: LIGHTFIELD_MAX_PIXELS
    etc.), so the CLI honours the same variables as the service. `params.max_frames` lowers
    `limits.max_frames`; longer videos are subsampled evenly by core.io and each kept frame
    keeps its source time (source index / fps). Poses given for every source frame are
    subsampled the same way. `estimate_depth=False` never runs the learned depth model
    (the service's upload check: the worker runs it).
    """
    from core.io import read_video

    params = params or CaptureParams()
    limits = limits or MediaLimits.from_env()
    if params.max_frames is not None and params.max_frames < limits.max_frames:
        limits = dataclasses.replace(limits, max_frames=params.max_frames)
    path = Path(input_path)
    if not path.exists():
        raise CaptureError("input", f"{path} does not exist")
    warn: list[str] = []
    if path.is_dir():
        loaded = _read_capture_dir(path, limits)
    else:
        kind = _sniff(path)
        if kind == "video":
            vf = read_video(path, limits)
            warn.extend(vf.warnings)
            loaded = {"frames": torch.from_numpy(np.ascontiguousarray(vf.frames)), "fps": vf.fps,
                      "source_indices": [int(i) for i in vf.source_frame_indices], "original_count": vf.original_frame_count}
        elif kind == "image":
            loaded = {"frames": _read_image(path, limits)[None]}
        else:
            raise CaptureError("input", f"{path.name} is neither an image, a video nor a capture directory")

    frames = loaded["frames"].float()
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] < 1:
        raise CaptureError("input", f"decoded frames have shape {tuple(frames.shape)}, expected [T, H, W, 3]")
    T, H, W, _ = frames.shape
    if not torch.isfinite(frames).all():
        raise CaptureError("input", "frames contain non-finite values")
    source_idx = loaded.get("source_indices") or list(range(T))

    fps = params.fps or loaded.get("fps") or 1.0
    if not (math.isfinite(fps) and fps > 0):
        raise CaptureError("fps", f"must be finite and > 0, got {fps}")
    intr = _resolve_intrinsics(params, loaded.get("intrinsics_dict"), W, H, warn)
    poses_in = loaded.get("poses")
    if params.poses is not None:
        poses_in = params.poses
        if len(poses_in) == loaded.get("original_count", T) != T:
            poses_in = [poses_in[i] for i in source_idx]
    poses = _resolve_poses(poses_in, T)
    depth_arg = _read_depth(Path(depth_path), limits) if depth_path is not None else loaded.get("depth")
    if depth_path is not None and depth_arg.ndim == 3 and depth_arg.shape[0] == loaded.get("original_count", T) != T:
        depth_arg = depth_arg[source_idx]
    depth_src = f"file:{Path(depth_path).name}" if depth_path is not None else loaded.get("depth_source")
    if depth_arg is None and estimate_depth and os.environ.get(DEPTH_MODEL_ENV):
        depth_arg, depth_src = _estimate_depth(frames, intr, os.environ[DEPTH_MODEL_ENV], warn)
    depth, depth_src = _resolve_depth(depth_arg, T, H, W, intr, depth_src, warn)
    for w in warn:
        _warnings.warn(w, stacklevel=2)
    return Capture(
        frames=frames.clamp(0, 1).contiguous(),
        depth=depth.contiguous(),
        intrinsics=intr,
        poses=poses,
        times=frame_time(torch.tensor(source_idx, dtype=torch.float32), fps),
        fps=float(fps),
        depth_source=depth_src,
        source=path.name,
        warnings=warn,
    )


def capture_from_arrays(frames: torch.Tensor, depth: torch.Tensor | None = None, *, intrinsics: Intrinsics | None = None,
                        poses: torch.Tensor | None = None, fps: float = 1.0, source: str = "arrays") -> Capture:
    """Build a validated Capture from in-memory tensors (tests, the demo, the simulator)."""
    frames = torch.as_tensor(frames, dtype=torch.float32)
    if frames.ndim == 3:
        frames = frames[None]
    T, H, W, _ = frames.shape
    warn: list[str] = []
    intr = intrinsics or Intrinsics.from_hfov(W, H, DEFAULT_HFOV_DEG)
    p = _resolve_poses(None if poses is None else torch.as_tensor(poses, dtype=torch.float64), T)
    d, src = _resolve_depth(depth, T, H, W, intr, "arrays" if depth is not None else None, warn)
    return Capture(frames.clamp(0, 1).contiguous(), d.contiguous(), intr, p,
                   frame_time(torch.arange(T, dtype=torch.float32), fps), float(fps), src, source, warn)
