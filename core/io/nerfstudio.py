"""Captures in the nerfstudio `transforms.json` layout (Polycam, Record3D, KIRI Engine,
`ns-process-data`): a directory or a zip holding `transforms.json`, the images and, optionally,
depth maps.

Conversion to our conventions (docs/capture-formats.md):
* `transform_matrix` (4x4, or 3x4 + the implied last row) is camera-to-world with an OpenGL
  camera (x right, y up, looking along -z): exactly our camera frame, so poses are taken as
  they are. The world is the app's: ARKit-based apps are +y up like ours; COLMAP-based
  exports (`ns-process-data`) are +z up. When the cameras' up vectors say the world is +z
  up, it is turned to +y up by R = Rx(-90°), i.e. (x, y, z)_ours = (x, z, -y)_file; the
  rotation is recorded so positions can be mapped back. Nothing else is changed (no
  recentring, no rescaling: nerfstudio's `applied_scale` is informational here).
* Intrinsics `fl_x, fl_y, cx, cy, w, h` (top level or per frame, one camera: per-frame
  values must agree within 0.5 %) are pixels in the same continuous convention as ours
  (COLMAP's, pixel centres at + 0.5); `camera_angle_x` (NeRF-synthetic) stands in for
  `fl_x`. When the images are not w x h (a downscaled folder), intrinsics are rescaled.
* `camera_model`: PINHOLE / SIMPLE_PINHOLE used as is; OPENCV (k1, k2, p1, p2, k3) and
  OPENCV_FISHEYE (k1-k4) are undistorted to a pinhole with the same fx, fy, cx, cy (OpenCV
  remap; depth maps with nearest-neighbour); anything else (EQUIRECTANGULAR, ...) is refused
  by name.
* `depth_file_path`: planar depth per frame. A 16-bit PNG is millimetres, as nerfstudio's
  default `depth_unit_scale_factor` = 1e-3 (a top-level `depth_unit_scale_factor` overrides
  it for PNGs); .npy/.npz/.exr are metres (core.io.depth). Depth of another size is resized
  (nearest). Depth is used only when every kept frame has one.
* Frames keep the file's order. Too many frames are subsampled evenly (core.io.video
  .select_frame_indices) with their poses.
Every problem is an `ArchiveError` whose `.field` names the offending key, e.g.
`transforms.json: frames[3].transform_matrix`.
"""
from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from PIL import Image

from core.camera import MAX_FOV_DEG, MAX_POSE_TRANSLATION_M, MIN_FOV_DEG
from core.io.archive import ArchiveError, CaptureFiles, ZipFiles, member_name, open_capture_files
from core.io.depth import check_depth_range, read_depth
from core.io.images import check_complete, decode_image, probe_image
from core.io.jsonbounds import JsonBudget, load_json
from core.io.limits import DEFAULT_LIMITS, MediaError, MediaLimits, Source
from core.io.metadata import frames_exposure_ev
from core.io.video import select_frame_indices

INDEX = "transforms.json"
# The index is parsed in the API's upload check: its cost is bounded before it is parsed
# (core.io.jsonbounds). 10 000 frames is 30x the default frame budget; a 10 000-frame index
# with 4x4 matrices is about 2 MB compact, 8 MB indented.
MAX_INDEX_BYTES = 8 * 1024 * 1024
MAX_INDEX_FRAMES = 10_000
INDEX_BUDGET = JsonBudget(max_bytes=MAX_INDEX_BYTES, max_depth=32, max_containers=20 * MAX_INDEX_FRAMES)
# Distortion a real lens has (OpenCV's radial k1..k4 are O(0.1-1), tangential p1, p2 O(0.01));
# beyond these the undistortion maps are garbage or not finite.
MAX_RADIAL_DISTORTION = 10.0
MAX_TANGENTIAL_DISTORTION = 1.0
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
DISTORTED_MODELS = ("OPENCV", "OPENCV_FISHEYE")
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
CAMERA_KEYS = INTRINSIC_KEYS + ("camera_angle_x", "camera_model", "k1", "k2", "k3", "k4", "p1", "p2")
RIGID_TOLERANCE = 1e-3
SAME_CAMERA_TOLERANCE = 0.005
Z_UP_TO_Y_UP = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], np.float64)  # Rx(-90 deg)


def _err(key: str, message: str, code: str = "shape_mismatch") -> ArchiveError:
    f = f"{INDEX}: {key}" if key else INDEX
    return ArchiveError(code, f"{f}: {message}", f)


def _index_error(code: str, message: str) -> ArchiveError:
    return ArchiveError(code, message, INDEX)


def _num(obj: dict, key: str, where: str, required: bool = True, positive: bool = False) -> float | None:
    v = obj.get(key)
    if v is None:
        if required:
            raise _err(f"{where}{key}", "is missing")
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _err(f"{where}{key}", f"must be a finite number, got {v!r}")
    if positive and v <= 0:
        raise _err(f"{where}{key}", f"must be > 0, got {v!r}")
    return float(v)


@dataclass(frozen=True)
class NerfstudioCamera:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    model: str
    distortion: tuple[float, ...]  # OPENCV: (k1, k2, p1, p2, k3); OPENCV_FISHEYE: (k1, k2, k3, k4)

    @property
    def distorted(self) -> bool:
        return self.model in DISTORTED_MODELS and any(abs(x) > 0 for x in self.distortion)

    def scaled(self, width: int, height: int) -> "NerfstudioCamera":
        sx, sy = width / self.width, height / self.height
        return NerfstudioCamera(
            self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height, self.model, self.distortion
        )

    def as_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width, "height": self.height}


@dataclass
class NerfstudioIndex:
    """transforms.json parsed and checked against the files, nothing decoded."""

    camera: NerfstudioCamera
    files: list[str]
    poses: np.ndarray  # [N, 4, 4] c2w, our convention and +y-up world
    depth_files: list[str] | None
    depth_unit_scale: float | None
    world_rotation: np.ndarray | None  # the rotation applied to the file's world (None: none)
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    def describe(self) -> dict:
        return {
            "format": "nerfstudio transforms.json",
            "frames": len(self.files),
            "camera_model": self.camera.model,
            "distortion": list(self.camera.distortion),
            "intrinsics": self.camera.as_dict(),
            "depth": "per frame" if self.depth_files else "none",
            "world_rotation_applied": None if self.world_rotation is None else self.world_rotation.tolist(),
            "notes": list(self.notes),
        }


@dataclass
class NerfstudioCapture:
    frames: np.ndarray  # [T, H, W, 3] float32 in [0, 1], undistorted
    intrinsics: dict  # fx, fy, cx, cy, width, height (pinhole)
    poses: np.ndarray  # [T, 4, 4]
    depth: np.ndarray | None  # [T, H, W] float32 metres, NaN invalid
    source_indices: list[int]
    original_count: int
    names: list[str]
    metadata: dict
    warnings: list[str]
    # each kept image's exposure (stops, vs the first) when every one's EXIF states it
    frame_ev: list[float] | None = None


def _camera(meta: dict, where: str, image_size: tuple[int, int] | None) -> NerfstudioCamera:
    """One camera from the intrinsic keys of `meta` (top level merged with a frame's own)."""
    model = meta.get("camera_model", "OPENCV")
    if not isinstance(model, str):
        raise _err(f"{where}camera_model", f"must be a string, got {model!r}")
    model = model.upper()
    if model not in PINHOLE_MODELS + DISTORTED_MODELS:
        raise _err(
            f"{where}camera_model",
            f"{model!r} is not supported (use PINHOLE, SIMPLE_PINHOLE, OPENCV or "
            "OPENCV_FISHEYE; 360-degree EQUIRECTANGULAR captures need a perspective export)",
            "unsupported_codec",
        )
    if "w" in meta or "h" in meta or image_size is None:
        w, h = _num(meta, "w", where, positive=True), _num(meta, "h", where, positive=True)
        if w != int(w) or h != int(h):
            raise _err(f"{where}w", f"w and h must be whole pixels, got {w} x {h}")
    else:
        w, h = image_size
    if "fl_x" in meta:
        fx = _num(meta, "fl_x", where, positive=True)
    elif "camera_angle_x" in meta:
        angle = _num(meta, "camera_angle_x", where, positive=True)
        if not angle < math.pi:
            raise _err(f"{where}camera_angle_x", f"must be < pi, got {angle}")
        fx = 0.5 * w / math.tan(angle / 2)
    else:
        raise _err(f"{where}fl_x", "is missing (give fl_x, fl_y, cx, cy, w, h)")
    fy = _num(meta, "fl_y", where, positive=True) if "fl_y" in meta else fx
    cx = _num(meta, "cx", where) if "cx" in meta else w / 2
    cy = _num(meta, "cy", where) if "cy" in meta else h / 2
    keys = {"OPENCV": ("k1", "k2", "p1", "p2", "k3"), "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4")}.get(model, ())
    dist = tuple(_num(meta, k, where, required=False) or 0.0 for k in keys)
    for k, value in zip(keys, dist):
        bound = MAX_TANGENTIAL_DISTORTION if k.startswith("p") else MAX_RADIAL_DISTORTION
        if abs(value) > bound:
            raise _err(f"{where}{k}", f"distortion coefficient {value:g} is outside the range [-{bound:g}, {bound:g}]",
                       "invalid_intrinsics")
    cam = NerfstudioCamera(float(fx), float(fy), float(cx), float(cy), int(w), int(h), model, dist)
    fx_key = "fl_x" if "fl_x" in meta else "camera_angle_x"
    _check_plausible(cam, where, fx_key, "fl_y" if "fl_y" in meta else fx_key)
    return cam


def _check_plausible(cam: NerfstudioCamera, where: str, fx_key: str, fy_key: str) -> None:
    """core.camera.Intrinsics.check_plausible's rules (what load_capture enforces), with the
    key that breaks them and its allowed range: fields of view within [MIN_FOV_DEG,
    MAX_FOV_DEG], the principal point within one image size of the centre."""
    lo_fov, hi_fov = math.radians(MIN_FOV_DEG) / 2, math.radians(MAX_FOV_DEG) / 2
    for key, f, size, axis in ((fx_key, cam.fx, cam.width, "horizontal"), (fy_key, cam.fy, cam.height, "vertical")):
        fov = math.degrees(2 * math.atan(0.5 * size / f))
        if not MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
            raise _err(
                f"{where}{key}",
                f"{f:g} px gives a {fov:.4g} deg {axis} field of view for {cam.width}x{cam.height} "
                f"images; expected {MIN_FOV_DEG:g} to {MAX_FOV_DEG:g} deg (a focal length of "
                f"{0.5 * size / math.tan(hi_fov):.4g} to {0.5 * size / math.tan(lo_fov):.4g} px)",
                "invalid_intrinsics",
            )
    for key, c, size in (("cx", cam.cx, cam.width), ("cy", cam.cy, cam.height)):
        if abs(c - size / 2) > size:
            raise _err(f"{where}{key}", f"{c:g} px lies more than one image size from the centre; expected "
                                        f"{-size / 2:g} to {1.5 * size:g} px for {cam.width}x{cam.height} images",
                       "invalid_intrinsics")


def _same_camera(a: NerfstudioCamera, b: NerfstudioCamera) -> bool:
    if a.model != b.model or (a.width, a.height) != (b.width, b.height):
        return False
    close = all(abs(x - y) <= SAME_CAMERA_TOLERANCE * max(abs(x), 1.0) for x, y in
                ((a.fx, b.fx), (a.fy, b.fy), (a.cx, b.cx), (a.cy, b.cy)))
    return close and all(abs(x - y) < 1e-6 for x, y in zip(a.distortion, b.distortion))


def _pose(v: Any, key: str) -> np.ndarray:
    try:
        m = np.asarray(v, np.float64)
    except (TypeError, ValueError):
        raise _err(key, "must be a 4x4 (or 3x4) list of numbers") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    if m.shape != (4, 4):
        raise _err(key, f"must be 4x4 (or 3x4), got shape {m.shape}")
    if not np.isfinite(m).all():
        raise _err(key, "contains non-finite values")
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
        raise _err(key, f"last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    R = m[:3, :3]
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    if dev > RIGID_TOLERANCE or np.linalg.det(R) < 0:
        raise _err(key, f"is not a rigid camera-to-world transform (rotation part off orthonormal by {dev:.3g}, "
                        f"det {np.linalg.det(R):.3g}); scaled or mirrored poses are not accepted")
    if np.abs(m[:3, 3]).max() > MAX_POSE_TRANSLATION_M:
        raise _err(key, f"translation {m[:3, 3].tolist()} m is outside +-{MAX_POSE_TRANSLATION_M:g} m "
                        "(the capture's camera positions, in metres)", "invalid_poses")
    return m


def _poses(values: list, keys: list[str]) -> np.ndarray:
    """[N, 4, 4] from the frames' transform_matrix values: checked all at once (an index may list
    thousands), and per frame (for the message naming the first bad one) only when one fails."""
    try:
        m = np.asarray(values, np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.ndim != 3 or m.shape[1:] not in ((4, 4), (3, 4)):
        return np.stack([_pose(v, k) for v, k in zip(values, keys)])
    if m.shape[1:] == (3, 4):
        m = np.concatenate([m, np.broadcast_to(np.array([[[0.0, 0, 0, 1]]]), (m.shape[0], 1, 4))], axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        finite = np.isfinite(m).all(axis=(1, 2))
        R = np.where(finite[:, None, None], m[:, :3, :3], 0.0)
        dev = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
        bad = (~finite | (np.abs(m[:, 3] - [0, 0, 0, 1]).max(axis=1) > 1e-6) | (dev > RIGID_TOLERANCE)
               | (np.linalg.det(R) < 0) | ~(np.abs(m[:, :3, 3]).max(axis=1) <= MAX_POSE_TRANSLATION_M))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        _pose(values[i], keys[i])  # raises, naming the frame
    return m


def _world_rotation(poses: np.ndarray) -> np.ndarray | None:
    """Rx(-90 deg) when the cameras' mean up vector says the file's world is +z up, else None."""
    up = poses[:, :3, 1].mean(0)
    n = np.linalg.norm(up)
    if n < 0.3:  # cameras point every which way: no evidence, keep the file's frame
        return None
    up = up / n
    return Z_UP_TO_Y_UP if up[2] > 0.7 and up[2] > abs(up[1]) else None


def _image_size(files: CaptureFiles, name: str, key: str, limits: MediaLimits = DEFAULT_LIMITS) -> tuple[int, int]:
    """(width, height) as stored (before any EXIF turn, as transforms.json's w, h are), checked
    as a directly uploaded image is (core.io.images.probe_image), so a bad image gets the same
    code in a capture as on its own."""
    data = files.read(name, f"{INDEX}: {key}")
    try:
        probe_image(data, limits)
        return _stored_size(data)
    except ArchiveError:
        raise
    except MediaError as exc:
        raise _err(key, f"{name!r}: {exc}", exc.code) from None


def _stored_size(data: bytes) -> tuple[int, int]:

    with Image.open(io.BytesIO(data)) as im:
        return im.size


def _find_index(files: CaptureFiles) -> None:
    if files.exists(INDEX):
        return
    if isinstance(files, ZipFiles):
        found = files.find(INDEX)
        if len(found) == 1:
            files.prefix = found[0][: -len(INDEX)].rstrip("/")
            return
        if len(found) > 1:
            raise _err(
                "",
                f"the archive holds {len(found)} {INDEX} files ({found[:3]}...); send one capture per archive",
                "not_media",
            )
    raise _err("", f"no {INDEX} in the capture", "not_found")


def read_index(files: CaptureFiles) -> NerfstudioIndex:
    """Parse and check transforms.json against the files present (headers only, no decoding),
    its cost bounded before it is parsed (size, depth and count of its arrays/objects, frames)."""
    _find_index(files)
    size = files.size(INDEX)
    if size > MAX_INDEX_BYTES:
        raise _index_error("too_large", f"{INDEX} is {size} bytes, more than the limit of {MAX_INDEX_BYTES}")
    meta = load_json(files.read(INDEX, INDEX), INDEX, INDEX_BUDGET, _index_error)
    if not isinstance(meta, dict):
        raise _err("", "must be a JSON object")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise _err("frames", "must be a non-empty list")
    if len(frames) > MAX_INDEX_FRAMES:
        raise _err(
            "frames", f"lists {len(frames)} frames, more than the limit of {MAX_INDEX_FRAMES}", "too_many_frames"
        )
    top = {k: meta[k] for k in CAMERA_KEYS if k in meta}
    notes: list[str] = []
    cams, names, matrices, depth_files = [], [], [], []
    cache: dict[str, NerfstudioCamera] = {}
    safe_names: dict[str, str] = {}
    image_size = None
    for i, fr in enumerate(frames):
        where = f"frames[{i}]."
        if not isinstance(fr, dict):
            raise _err(f"frames[{i}]", "must be an object")
        path = fr.get("file_path")
        if not isinstance(path, str):
            raise _err(f"{where}file_path", "is missing or not a string", "not_found")
        name = safe_names.get(path)
        if name is None:
            name = safe_names[path] = member_name(path, f"{INDEX}: {where}file_path")
            if not files.exists(name):
                raise _err(f"{where}file_path", f"{path!r} is not in the capture", "not_found")
        if "transform_matrix" not in fr:
            raise _err(f"{where}transform_matrix", "is missing")
        own = {k: fr[k] for k in CAMERA_KEYS if k in fr}
        merged = {**top, **own} if own else top
        if "w" not in merged and image_size is None:
            image_size = _image_size(files, name, f"{where}file_path", files.limits)
        key = json.dumps(merged, sort_keys=True, default=str) if own else ""
        if key not in cache:
            cache[key] = _camera(merged, where if own else "", image_size)
        cam = cache[key]
        if cams and cam is not cams[0] and not _same_camera(cams[0], cam):
            raise _err(
                f"{where}fl_x", "intrinsics differ from frames[0]: captures from several cameras are not supported"
            )
        cams.append(cam)
        names.append(name)
        matrices.append(fr["transform_matrix"])
        d = fr.get("depth_file_path")
        if d is not None:
            dname = member_name(d, f"{INDEX}: {where}depth_file_path")
            if not files.exists(dname):
                raise _err(f"{where}depth_file_path", f"{d!r} is not in the capture", "not_found")
            depth_files.append(dname)
    if "mask_path" in frames[0]:
        notes.append("mask_path ignored (masks are not used)")
    warnings = []
    if depth_files and len(depth_files) != len(frames):
        warnings.append(f"only {len(depth_files)} of {len(frames)} frames have a depth_file_path: depth ignored")
        depth_files = []
    scale = (
        _num(meta, "depth_unit_scale_factor", "", required=False, positive=True)
        if "depth_unit_scale_factor" in meta
        else None
    )
    P = _poses(matrices, [f"frames[{i}].transform_matrix" for i in range(len(matrices))])
    R = _world_rotation(P)
    if R is not None:
        P = R[None] @ P
        notes.append("the file's world is +z up (cameras' mean up vector): turned to +y up by Rx(-90 deg), "
                     "(x, y, z)_ours = (x, z, -y)_file")
    if cams[0].distorted:
        notes.append(
            f"{cams[0].model} distortion {list(cams[0].distortion)} removed (undistorted to a pinhole, same fx, fy, "
            "cx, cy)"
        )
    return NerfstudioIndex(cams[0], names, P, depth_files or None, scale, R, notes, warnings)


def _undistort_maps(cam: NerfstudioCamera):
    K = np.array([[cam.fx, 0, cam.cx - 0.5], [0, cam.fy, cam.cy - 0.5], [0, 0, 1]], np.float64)  # OpenCV pixel centres
    size = (cam.width, cam.height)
    if cam.model == "OPENCV_FISHEYE":
        return cv2.fisheye.initUndistortRectifyMap(K, np.array(cam.distortion[:4]), np.eye(3), K, size, cv2.CV_32FC1)
    return cv2.initUndistortRectifyMap(K, np.array(cam.distortion), np.eye(3), K, size, cv2.CV_32FC1)


def _depth_frame(files: CaptureFiles, name: str, key: str, shape: tuple[int, int], scale: float | None,
                 limits: MediaLimits) -> np.ndarray:
    data = files.read(name, key)
    try:
        d = read_depth(data, limits)
    except ArchiveError:
        raise
    except ValueError as exc:  # MediaError: name the field that pointed at the file
        raise _err(key, f"{name!r}: {exc}", getattr(exc, "code", "invalid_depth")) from None
    if d.ndim == 3 and d.shape[0] == 1:
        d = d[0]
    if d.ndim != 2:
        raise _err(key, f"{name!r} must hold one [H, W] depth map, got shape {d.shape}", "invalid_depth")
    if scale is not None and data[:4] == b"\x89PNG":
        d = d * (scale * 1000.0)  # read_depth gave mm / 1000; the file says mm * 1000 * scale metres
        try:
            check_depth_range(d, f"{name!r}")
        except MediaError as exc:
            raise _err(key, str(exc), exc.code) from None
    if d.shape != shape:
        d = cv2.resize(d, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
    return d


def load_nerfstudio(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> NerfstudioCapture:
    """Read a nerfstudio capture (directory or zip) under `limits` (see module docstring)."""
    with open_capture_files(source, limits) as files:
        index = read_index(files)
        cam = index.camera
        keep = [int(i) for i in select_frame_indices(len(index.files), cam.width * cam.height, limits)]
        frames, applied, metas = [], [], []
        for i in keep:
            key = f"frames[{i}].file_path"
            try:
                decoded = decode_image(files.read(index.files[i], f"{INDEX}: {key}"), limits)
            except ArchiveError:
                raise
            except ValueError as exc:
                raise _err(key, f"{index.files[i]!r}: {exc}", getattr(exc, "code", "not_media")) from None
            frames.append(decoded.pixels)
            metas.append(decoded.metadata)
            applied.extend(a for a in decoded.applied if a not in applied)
        h, w = frames[0].shape[:2]
        for n, f in enumerate(frames):
            if f.shape[:2] != (h, w):
                raise _err(
                    f"frames[{keep[n]}].file_path", f"image is {f.shape[1]}x{f.shape[0]}, frames[{keep[0]}] is {w}x{h}"
                )
        notes = list(index.notes) + applied
        if (w, h) != (cam.width, cam.height):
            notes.append(f"images are {w}x{h}, transforms.json says {cam.width}x{cam.height}: intrinsics rescaled")
            cam = cam.scaled(w, h)
        stack = np.stack(frames)
        depth = None
        if index.depth_files:
            depth = np.stack([_depth_frame(files, index.depth_files[i], f"frames[{i}].depth_file_path", (h, w),
                                           index.depth_unit_scale, limits) for i in keep])
        if cam.distorted:
            mx, my = _undistort_maps(cam)
            stack = np.stack([cv2.remap(f, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for f in stack])
            if depth is not None:
                depth = np.stack([cv2.remap(d, mx, my, cv2.INTER_NEAREST, borderValue=float("nan")) for d in depth])
    return NerfstudioCapture(
        frames=np.clip(stack, 0.0, 1.0).astype(np.float32), intrinsics=cam.as_dict(), poses=index.poses[keep],
        depth=depth, source_indices=keep, original_count=len(index.files), names=[index.files[i] for i in keep],
        metadata={**index.describe(), "notes": notes}, warnings=list(index.warnings),
        frame_ev=frames_exposure_ev(metas),
    )


def inspect_nerfstudio(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> dict:
    """Submission-time check without decoding the capture: the index, the files it names, the
    first kept image checked as a direct upload is (header, structure, a full decode for
    formats whose structure check does not see truncation), every other kept image's end
    marker (a truncated JPEG or PNG), and the first kept depth map (valid pixels, range).
    Returns `NerfstudioIndex.describe()` and the kept frames' indices (`kept`)."""
    with open_capture_files(source, limits) as files:
        index = read_index(files)
        limits.check_pixels(index.camera.width, index.camera.height, f"{INDEX}: w x h")
        keep = [
            int(i) for i in select_frame_indices(len(index.files), index.camera.width * index.camera.height, limits)
        ]
        first = keep[0]
        limits.check_pixels(*_image_size(files, index.files[first], f"frames[{first}].file_path", limits),
                            f"frames[{first}] image")
        for i in keep[1:]:
            key = f"frames[{i}].file_path"
            try:
                check_complete(files.read(index.files[i], f"{INDEX}: {key}"))
            except ArchiveError:
                raise
            except MediaError as exc:
                raise _err(key, f"{index.files[i]!r}: {exc}", exc.code) from None
        if index.depth_files:
            _depth_frame(files, index.depth_files[first], f"frames[{first}].depth_file_path",
                         (index.camera.height, index.camera.width), index.depth_unit_scale, limits)
        return {**index.describe(), "kept": keep}
