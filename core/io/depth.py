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
import os
import zipfile
from pathlib import Path

import numpy as np

from core.io.archive import check_zip_directory
from core.io.exr import atomic_write, read_exr_channels
from core.io.images import encode_png16, read_png16
from core.io.limits import DEFAULT_LIMITS, MediaError, MediaLimits, Source, read_source
from core.io.sniff import npy_header, sniff_depth

MM_PER_METRE = 1000.0
_EXR_DEPTH_CHANNELS = ("Z", "depth", "Y", "R")
# Planar depth a capture may state: indoor scenes span metres; 10 km is a unit error (depth in
# millimetres sent as metres) or a sentinel, and the scene bounds built from it break the field
# (the same bound as core.camera.MAX_POSE_TRANSLATION_M and the API's insertion depths).
MAX_DEPTH_M = 1.0e4
_NPZ_MAX_MEMBERS = 64  # an .npz holds one array; a few more are named in the refusal
_NPZ_MAX_RATIO = 200.0  # as core.io.archive.MAX_RATIO: float depth compresses a few times, not 600x
_NPZ_RATIO_MIN_BYTES = 1 << 20


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


def check_depth_range(depth: np.ndarray, what: str = "depth") -> None:
    """Refuse ('invalid_depth') depths beyond MAX_DEPTH_M in a sanitised map (invalid = NaN),
    naming the value and the range."""
    if not depth.size or np.isnan(depth).all():
        return
    deepest = np.nanmax(depth)  # sanitised depth: invalid pixels are NaN (an inf here came from scaling)
    if deepest > MAX_DEPTH_M:
        raise MediaError("invalid_depth", f"{what}: values up to {float(deepest):.4g} m; planar depth must be within "
                                          f"(0, {MAX_DEPTH_M:g}] m (metres; a 16-bit PNG holds millimetres)")


def _open_npz(target, size: int, limits: MediaLimits) -> zipfile.ZipFile:
    """The .npz (a zip) with its directory walked within bounds (core.io.archive) before zipfile
    parses it, and exactly one member `depth.npy`."""
    check_zip_directory(target, size, _NPZ_MAX_MEMBERS, "depth .npz")
    target.seek(0)
    archive = zipfile.ZipFile(target)
    try:
        _check_npz_members(archive)
    except BaseException:
        archive.close()
        raise
    return archive


def _check_npz_data(archive: zipfile.ZipFile, limits: MediaLimits) -> None:
    """After the array header: `depth.npy` at most `limits.max_bytes` and not compressed more
    than _NPZ_MAX_RATIO : 1 (a 1 MB file declaring 800 MB of float64), before its data is read."""
    info = archive.getinfo("depth.npy")
    if info.file_size > limits.max_bytes:
        raise MediaError("too_large", f"depth array is {info.file_size} bytes uncompressed, more than the limit "
                                      f"of {limits.max_bytes}")
    if info.file_size > _NPZ_RATIO_MIN_BYTES and info.file_size > _NPZ_MAX_RATIO * max(info.compress_size, 1):
        raise MediaError("too_large", f"depth array expands {info.file_size / max(info.compress_size, 1):.0f}x "
                                      f"(more than {_NPZ_MAX_RATIO:g}x: a zip bomb?)")


def _check_npz_members(archive: zipfile.ZipFile) -> None:
    names = archive.namelist()
    if names != ["depth.npy"]:
        keys = [n[:-4] if n.endswith(".npy") else n for n in names]
        raise MediaError("invalid_depth", f".npz must hold exactly one array named 'depth', found {keys}")


def _load_npz(data: bytes, limits: MediaLimits) -> np.ndarray:
    try:
        with _open_npz(io.BytesIO(data), len(data), limits) as archive:
            with archive.open("depth.npy") as member:
                shape, dtype = npy_header(member)
                _check_array_header(shape, dtype, limits, "depth array")
            _check_npz_data(archive, limits)
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
        raise MediaError(
            "invalid_depth", f"depth PNG must be single-channel (greyscale), got {millimetres.shape[2]} channels"
        )
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
    depth = sanitize_depth(depth)
    check_depth_range(depth, "depth")
    return depth


def probe_depth(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> tuple[tuple[int, ...], np.ndarray]:
    """(shape, first map) of a depth file `read_depth` accepts: the array header checked under
    `limits` as read_depth does, and only the first [H, W] map read (sanitised: invalid pixels
    NaN; its range checked), however many maps the file holds, with memory bounded by one map
    (a path is read as a stream, never whole). EXR and PNG files hold one map."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        return _probe_depth_stream(io.BytesIO(bytes(source)), len(source), limits)
    path = Path(source)
    if not path.is_file():
        raise MediaError("not_found", f"depth file {str(path)!r} does not exist or is not a regular file")
    with open(path, "rb") as f:
        return _probe_depth_stream(f, path.stat().st_size, limits)


def _probe_depth_stream(f, size: int, limits: MediaLimits) -> tuple[tuple[int, ...], np.ndarray]:
    limits.check_bytes(size, "depth file")
    kind = sniff_depth(f.read(16))
    f.seek(0)
    if kind is None:
        raise MediaError("not_media", "depth must be .npz/.npy (array 'depth'), OpenEXR or 16-bit PNG in millimetres")
    if kind in ("exr", "png"):
        depth = read_depth(f.read(), limits)
        return depth.shape, depth
    try:
        if kind == "npy":
            shape, first = _npy_first_map(f, limits)
        else:
            with _open_npz(f, size, limits) as archive, archive.open("depth.npy") as member:
                shape, first = _npy_first_map(member, limits, lambda: _check_npz_data(archive, limits))
    except MediaError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise MediaError("truncated", f".{kind} depth file is truncated or corrupt ({exc})") from None
    check_depth_range(first, "depth" if len(shape) == 2 else "depth map 0")
    return shape, first


_COLUMN_READ_BYTES = 4 << 20


def _npy_first_map(fp, limits: MediaLimits, after_header=None) -> tuple[tuple[int, ...], np.ndarray]:
    version = np.lib.format.read_magic(fp)
    read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, fortran_order, dtype = read_header(fp)
    _check_array_header(shape, dtype, limits, "depth array")
    if after_header is not None:
        after_header()
    h, w = shape[-2:]
    frames = shape[0] if len(shape) == 3 else 1
    if not fortran_order or frames == 1:
        raw = fp.read(h * w * dtype.itemsize)
        if len(raw) < h * w * dtype.itemsize:
            raise MediaError("truncated", "depth array data is truncated")
        first = np.frombuffer(raw, dtype).reshape((h, w), order="F" if fortran_order else "C")
        return tuple(shape), sanitize_depth(first)
    # Fortran order [T, H, W]: map 0 is every T-th value. Read column blocks of the stack (each
    # column holds T * H values) and keep map 0's share: memory stays at one block, never the stack.
    first = np.empty((h, w), dtype)
    column = frames * h
    per_read = max(1, _COLUMN_READ_BYTES // (column * dtype.itemsize))
    for c0 in range(0, w, per_read):
        n = min(per_read, w - c0)
        raw = fp.read(n * column * dtype.itemsize)
        if len(raw) < n * column * dtype.itemsize:
            raise MediaError("truncated", "depth array data is truncated")
        block = np.frombuffer(raw, dtype).reshape((frames, h, n), order="F")
        first[:, c0:c0 + n] = block[0]
    return tuple(shape), sanitize_depth(first)


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
        raise MediaError(
            "invalid_depth", f"depth {float(np.nanmax(d)):.3f} m exceeds the 16-bit millimetre range (65.535 m)"
        )
    return encode_png16(mm.astype(np.uint16))


def write_depth_npz(path: str | os.PathLike, depth_m: np.ndarray) -> Path:
    """Compressed .npz with the single array `depth` (float32 metres, NaN = invalid)."""
    buf = io.BytesIO()
    np.savez_compressed(buf, depth=sanitize_depth(depth_m))
    return atomic_write(path, buf.getvalue())
