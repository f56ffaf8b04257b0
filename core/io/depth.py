"""Depth maps from .npz / .npy, EXR and 16-bit PNG (millimetres).

Result: float32 planar depth in metres, [H, W] or [T, H, W]. Invalid pixels (zero,
negative, NaN, +-inf) all become NaN, so validity is carried as one mask (`isfinite`)
as core.conventions says; whether a mostly-invalid map is acceptable is the engine's call.
The container is chosen by magic bytes, never by file name. NumPy files are loaded with
`allow_pickle=False`, must hold exactly one real-valued array named `depth`, and their
shape is read from the array header before the data is decompressed (zip bombs).
"""
from __future__ import annotations

import io
import math
import os
import zipfile
from pathlib import Path

import numpy as np

from core.io.exr import atomic_write, read_exr_channels
from core.io.images import encode_png16, read_png16
from core.io.limits import DEFAULT_LIMITS, MediaError, MediaLimits, Source, read_source
from core.io.sniff import npy_header, sniff_depth

MM_PER_METRE = 1000.0
_EXR_DEPTH_CHANNELS = ("Z", "depth", "Y", "R")


def _check_shape(shape: tuple, limits: MediaLimits, what: str) -> None:
    if len(shape) not in (2, 3) or min(shape, default=0) < 1:
        raise MediaError("invalid_depth", f"{what} must be [H, W] or [T, H, W] with no empty axis, got shape {shape}")
    limits.check_pixels(shape[-1], shape[-2], what)
    frames = shape[0] if len(shape) == 3 else 1
    if frames > limits.max_frames:
        raise MediaError("too_many_frames", f"{what} has {frames} frames, more than the limit of {limits.max_frames}")
    if frames * shape[-1] * shape[-2] > limits.max_total_pixels:
        raise MediaError("too_many_pixels", f"{what} shape {shape} exceeds max_total_pixels={limits.max_total_pixels}")


def _check_array_header(shape: tuple, dtype: np.dtype, limits: MediaLimits, what: str) -> None:
    if dtype.hasobject or not (np.issubdtype(dtype, np.floating) or np.issubdtype(dtype, np.integer)):
        raise MediaError("invalid_depth", f"{what} must be a real-valued float or integer array, got dtype {dtype}")
    _check_shape(tuple(shape), limits, what)


def _check_npz_members(archive: zipfile.ZipFile) -> None:
    names = archive.namelist()
    if names != ["depth.npy"]:
        keys = [n[:-4] if n.endswith(".npy") else n for n in names]
        raise MediaError("invalid_depth", f".npz must hold exactly one array named 'depth', found {keys}")


def _load_npz(data: bytes, limits: MediaLimits) -> np.ndarray:
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            _check_npz_members(archive)
            with archive.open("depth.npy") as member:
                shape, dtype = npy_header(member)
                _check_array_header(shape, dtype, limits, "depth array")
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            return npz["depth"]
    except MediaError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise MediaError("truncated", f".npz depth file is truncated or corrupt ({exc})") from None


def _load_npy(data: bytes, limits: MediaLimits) -> np.ndarray:
    try:
        shape, dtype = npy_header(io.BytesIO(data))
        _check_array_header(shape, dtype, limits, "depth array")
        return np.load(io.BytesIO(data), allow_pickle=False)
    except MediaError:
        raise
    except (EOFError, OSError, ValueError) as exc:
        raise MediaError("truncated", f".npy depth file is truncated or corrupt ({exc})") from None


def _load_exr(data: bytes, limits: MediaLimits) -> np.ndarray:
    channels = read_exr_channels(data, limits)
    name = next((n for n in _EXR_DEPTH_CHANNELS if n in channels), next(iter(channels)))
    return channels[name]


def _load_png(data: bytes, limits: MediaLimits) -> np.ndarray:
    try:
        millimetres = read_png16(data, limits)
    except MediaError as exc:
        if exc.code == "wrong_bit_depth":
            raise MediaError("wrong_bit_depth", f"depth PNG must be 16-bit millimetres; {exc}") from None
        raise
    if millimetres.ndim != 2:
        raise MediaError("invalid_depth", f"depth PNG must be single-channel (greyscale), got {millimetres.shape[2]} channels")
    return millimetres.astype(np.float32) / np.float32(MM_PER_METRE)  # 0 mm -> 0 -> NaN below


def read_depth(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> np.ndarray:
    """float32 planar depth in metres, [H, W] or [T, H, W]; invalid pixels are NaN."""
    data = read_source(source, limits, "depth file")
    kind = sniff_depth(data)
    loaders = {"npz": _load_npz, "npy": _load_npy, "exr": _load_exr, "png": _load_png}
    if kind is None:
        raise MediaError("not_media", "depth must be .npz/.npy (array 'depth'), OpenEXR or 16-bit PNG in millimetres")
    depth = np.asarray(loaders[kind](data, limits))
    _check_shape(depth.shape, limits, "depth map")
    return sanitize_depth(depth)


def probe_depth(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> tuple[tuple[int, ...], np.ndarray]:
    """(shape, first map) of a depth file `read_depth` accepts: the array header checked under
    `limits` as read_depth does, and only the first [H, W] map read (sanitised: invalid pixels
    NaN), however many maps the file holds. EXR and PNG files hold one map."""
    data = read_source(source, limits, "depth file")
    kind = sniff_depth(data)
    if kind is None:
        raise MediaError("not_media", "depth must be .npz/.npy (array 'depth'), OpenEXR or 16-bit PNG in millimetres")
    if kind in ("exr", "png"):
        depth = read_depth(data, limits)
        return depth.shape, depth
    try:
        if kind == "npy":
            return _npy_first_map(io.BytesIO(data), limits)
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            _check_npz_members(archive)
            with archive.open("depth.npy") as member:
                return _npy_first_map(member, limits)
    except MediaError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise MediaError("truncated", f".{kind} depth file is truncated or corrupt ({exc})") from None


def _npy_first_map(fp, limits: MediaLimits) -> tuple[tuple[int, ...], np.ndarray]:
    version = np.lib.format.read_magic(fp)
    read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, fortran_order, dtype = read_header(fp)
    _check_array_header(shape, dtype, limits, "depth array")
    h, w = shape[-2:]
    # a Fortran-ordered stack's first map is not contiguous: read the whole (limit-checked) array
    count = math.prod(shape) if fortran_order else h * w
    raw = fp.read(count * dtype.itemsize)
    if len(raw) < count * dtype.itemsize:
        raise MediaError("truncated", "depth array data is truncated")
    array = np.frombuffer(raw, dtype).reshape(shape if fortran_order else (h, w), order="F" if fortran_order else "C")
    first = array[0] if array.ndim == 3 else array
    return tuple(shape), sanitize_depth(np.array(first))


def sanitize_depth(depth: np.ndarray) -> np.ndarray:
    """float32 copy with every invalid value (<= 0, NaN, +-inf, float32 overflow) as NaN."""
    with np.errstate(over="ignore", invalid="ignore"):
        d = np.asarray(depth, dtype=np.float32).copy()
    d[~(np.isfinite(d) & (d > 0))] = np.nan
    return d


def encode_depth_png16(depth_m: np.ndarray) -> bytes:
    """16-bit PNG bytes in millimetres from metres [H, W]; invalid -> 0, beyond 65.535 m is
    refused ('invalid_depth') rather than silently wrapped or clipped."""
    d = sanitize_depth(depth_m)
    if d.ndim != 2:
        raise MediaError("invalid_depth", f"depth PNG holds one [H, W] map, got shape {d.shape}")
    mm = np.round(np.nan_to_num(d, nan=0.0) * MM_PER_METRE)
    if mm.max(initial=0.0) > 65535:
        raise MediaError("invalid_depth", f"depth {float(np.nanmax(d)):.3f} m exceeds the 16-bit millimetre range (65.535 m)")
    return encode_png16(mm.astype(np.uint16))


def write_depth_npz(path: str | os.PathLike, depth_m: np.ndarray) -> Path:
    """Compressed .npz with the single array `depth` (float32 metres, NaN = invalid)."""
    buf = io.BytesIO()
    np.savez_compressed(buf, depth=sanitize_depth(depth_m))
    return atomic_write(path, buf.getvalue())
