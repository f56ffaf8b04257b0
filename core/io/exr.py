"""OpenEXR through the `OpenEXR` package (>= 3.2 `OpenEXR.File` API).

The opencv wheels used here are built without an EXR codec, so cv2 is never used for EXR.
Reading goes through an in-memory stream; the header is read first so the pixel limit is
enforced before any pixel data is decoded.
"""
from __future__ import annotations

import fractions
import io
import os
import warnings
from pathlib import Path
from typing import Literal, Mapping, Optional, Sequence

import numpy as np
import OpenEXR

from core.io.limits import DEFAULT_LIMITS, MediaError, MediaLimits, Source, read_source
from core.io.sniff import EXR_MAGIC

HALF_MAX = 65504.0


class HalfOverflowWarning(UserWarning):
    """Values beyond the half-float range were clamped to +-65504 when writing."""


def _open(data: bytes, header_only: bool) -> "OpenEXR.File":
    try:
        return OpenEXR.File(io.BytesIO(data), separate_channels=True, header_only=header_only)
    except Exception as exc:  # the binding raises bare RuntimeError for every failure
        if data.startswith(EXR_MAGIC):
            raise MediaError("truncated", f"EXR file is truncated or corrupt ({exc})") from None
        raise MediaError("not_media", "not an OpenEXR file (bad magic number)") from None


def read_exr_channels(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> dict[str, np.ndarray]:
    """All channels of the first part as float32 [H, W] arrays, in file order."""
    data = read_source(source, limits, "EXR file")
    if not data.startswith(EXR_MAGIC):
        raise MediaError("not_media", "not an OpenEXR file (bad magic number)")
    header = _open(data, header_only=True).header()
    lo, hi = header["dataWindow"]
    width, height = int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
    limits.check_pixels(width, height, "EXR image")
    exr = _open(data, header_only=False)
    try:  # a file whose pixel chunks are cut off opens with zero parts instead of raising
        file_channels = exr.channels().items()
    except (ValueError, RuntimeError, IndexError) as exc:
        raise MediaError("truncated", "EXR pixel data is truncated or corrupt") from exc
    channels = {}
    for name, channel in file_channels:
        if channel.xSampling != 1 or channel.ySampling != 1:
            raise MediaError(
                "unsupported_codec", f"EXR channel {name!r} is subsampled; only full-resolution channels are supported"
            )
        pixels = np.asarray(channel.pixels)
        if pixels.shape != (height, width):
            raise MediaError("truncated", f"EXR channel {name!r} has shape {pixels.shape}, expected {(height, width)}")
        channels[name] = pixels.astype(np.float32, copy=False)
    if not channels:
        raise MediaError("not_media", "EXR file has no channels")
    return channels


def read_exr(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> np.ndarray:
    """float32 [H, W, C]: R, G, B when present (alpha and other layers dropped), else a
    single 'Y' (luminance) channel, else every channel in file order."""
    channels = read_exr_channels(source, limits)
    for names in (("R", "G", "B"), ("Y",)):
        if all(n in channels for n in names):
            return np.stack([channels[n] for n in names], axis=-1)
    return np.stack(list(channels.values()), axis=-1)


def _default_channel_names(n: int) -> Sequence[str]:
    return {1: ("Y",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}.get(n) or tuple(f"C{i}" for i in range(n))


def _prepare(
    array: np.ndarray, half: bool, on_overflow: Literal["clamp", "error"], allow_non_finite: bool
) -> np.ndarray:
    a = np.asarray(array)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[0] < 1 or a.shape[1] < 1 or a.shape[2] < 1:
        raise MediaError("shape_mismatch", f"EXR array must be [H, W] or [H, W, C], got shape {np.shape(array)}")
    if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise MediaError("shape_mismatch", f"EXR array must be real-valued, got dtype {a.dtype}")
    a = a.astype(np.float32)
    finite = np.isfinite(a)
    if not allow_non_finite and not finite.all():
        raise MediaError(
            "non_finite",
            f"EXR array has {int((~finite).sum())} NaN/inf values; pass allow_non_finite=True to keep them",
        )
    if half:
        over = finite & (np.abs(a) > HALF_MAX)
        if over.any():
            if on_overflow == "error":
                raise MediaError(
                    "non_finite",
                    f"{int(over.sum())} values exceed the half-float range (|x| > {HALF_MAX:g}); max |x| = "
                    f"{float(np.abs(a[over]).max()):g}",
                )
            warnings.warn(
                f"clamped {int(over.sum())} values beyond the half-float range to +-{HALF_MAX:g}",
                HalfOverflowWarning,
                stacklevel=3,
            )
            a = np.where(over, np.sign(a) * HALF_MAX, a)
        return a.astype(np.float16)
    return a


# Attribute names the OpenEXR library owns; `attributes` may not override them.
_RESERVED = frozenset({"channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
                       "screenWindowCenter", "screenWindowWidth", "type", "tiles", "name", "version", "chunkCount"})


def _check_attributes(attributes: Optional[Mapping[str, object]]) -> dict:
    out = {}
    for key, value in (attributes or {}).items():
        if not isinstance(key, str) or not key or key in _RESERVED:
            raise ValueError(f"EXR attribute name {key!r} is empty or reserved by OpenEXR")
        if isinstance(value, bool) or not isinstance(value, (str, int, float, tuple, np.ndarray, OpenEXR.Envmap,
                                                             OpenEXR.TimeCode, fractions.Fraction)):
            raise ValueError(f"EXR attribute {key!r}: unsupported value type {type(value).__name__}")
        out[key] = value
    return out


def read_exr_header(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> dict[str, object]:
    """The first part's header attributes (standard and custom), without decoding pixels."""
    data = read_source(source, limits, "EXR file")
    if not data.startswith(EXR_MAGIC):
        raise MediaError("not_media", "not an OpenEXR file (bad magic number)")
    return dict(_open(data, header_only=True).header())


def _build(array, half, on_overflow, allow_non_finite, channel_names, attributes=None,
           compress: bool = True) -> "OpenEXR.File":
    if on_overflow not in ("clamp", "error"):
        raise ValueError(f"on_overflow must be 'clamp' or 'error', got {on_overflow!r}")
    a = _prepare(array, half, on_overflow, allow_non_finite)
    names = tuple(channel_names) if channel_names is not None else _default_channel_names(a.shape[2])
    if len(names) != a.shape[2]:
        raise MediaError("shape_mismatch", f"{len(names)} channel names given for {a.shape[2]} channels")
    channels = {n: np.ascontiguousarray(a[..., i]) for i, n in enumerate(names)}
    header = {**_check_attributes(attributes), "type": OpenEXR.scanlineimage,
              "compression": OpenEXR.ZIP_COMPRESSION if compress else OpenEXR.NO_COMPRESSION}
    return OpenEXR.File(header, channels)


def encode_exr(
    array: np.ndarray,
    half: bool = False,
    on_overflow: Literal["clamp", "error"] = "clamp",
    allow_non_finite: bool = False,
    channel_names: Optional[Sequence[str]] = None,
    attributes: Optional[Mapping[str, object]] = None,
    compress: bool = True,
) -> bytes:
    """EXR file bytes (ZIP-compressed scanlines; `compress=False`: uncompressed, 5-15x faster
    to write, and float32 radiance maps compress by only 2-11 %). [H, W] -> 'Y', 3 channels
    -> RGB, 4 -> RGBA unless `channel_names` says otherwise. With `half`, |x| > 65504 is
    clamped with a HalfOverflowWarning or refused (`on_overflow='error'`); values below ~6e-5
    become half subnormals (absolute precision ~6e-8). NaN/inf are refused unless
    `allow_non_finite`. `attributes` adds header attributes (str, int, float, a tuple of 8
    floats for `chromaticities`, float32 numpy vectors for V2f/V3f, OpenEXR.TimeCode, a
    fractions.Fraction for a rational); see
    `core.export.metadata` for the ones our env maps carry."""
    stream = io.BytesIO()
    _build(array, half, on_overflow, allow_non_finite, channel_names, attributes, compress).write(stream)
    return stream.getvalue()


def write_exr(
    path: str | os.PathLike,
    array: np.ndarray,
    half: bool = False,
    on_overflow: Literal["clamp", "error"] = "clamp",
    allow_non_finite: bool = False,
    channel_names: Optional[Sequence[str]] = None,
    attributes: Optional[Mapping[str, object]] = None,
) -> Path:
    """Write `encode_exr(...)` to `path` atomically (temp sibling + rename)."""
    data = encode_exr(array, half, on_overflow, allow_non_finite, channel_names, attributes)
    return atomic_write(path, data)


def atomic_write(path: str | os.PathLike, data: bytes) -> Path:
    """Write bytes to a temporary sibling, then rename, so readers never see a partial file."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
