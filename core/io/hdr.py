"""Radiance RGBE (.hdr) reading and writing, in numpy.

Reads flat scanlines and the "new-style" run-length encoded scanlines that Poly Haven and
most tools write (each scanline: 2, 2, width_hi, width_lo, then the four byte planes R, G,
B, E each run-length encoded). Old-style (1,1,1,n) repeat markers from pre-1991 files are
not interpreted. The `EXPOSURE=` header is ignored, like OpenCV and most readers do, so
values are the stored ones. Decoding follows Radiance: x = (m + 0.5) * 2^(e - 136),
encoding truncates the mantissa, so a round trip is within one mantissa step (< 0.8% of
the pixel's largest channel).

Why by hand when OpenCV (a dependency) reads and writes .hdr: its Radiance codec has no
in-memory path in the pinned opencv 5.0 (`cv2.imencode('.hdr')` / `imdecode` write the bytes to
a temporary file `/tmp/__opencv_temp.*` and read it back, on every call: seen with
`strace -e trace=openat python -c "import cv2, numpy; cv2.imencode('.hdr', numpy.ones((4, 8, 3), 'f4'))"`),
it rejects bottom-up ('+Y') files, and it cannot refuse an oversized upload from its header
before decoding (`MediaLimits`). The service encodes /envmap?format=hdr and decodes uploads per
request, so both stay here; tests/test_io_hdr.py reads our files with OpenCV and real Poly Haven
files with both, within half a mantissa step.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from core.io.exr import atomic_write
from core.io.limits import DEFAULT_LIMITS, MediaError, MediaLimits, Source, read_source

_MAX_HEADER_BYTES = 64 * 1024
_MIN_RUN = 4  # shorter repeats are cheaper as literals


def _parse_header(data: bytes) -> tuple[int, int, bool, int]:
    """-> (height, width, bottom_up, offset of the first scanline)."""
    if not (data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE")):
        raise MediaError("not_media", "not a Radiance .hdr file (missing '#?RADIANCE' signature)")
    end = data.find(b"\n\n", 0, _MAX_HEADER_BYTES)
    if end < 0:
        raise MediaError("truncated", "Radiance header has no end (blank line) in the first 64 KiB")
    for line in data[:end].split(b"\n")[1:]:
        if line.startswith(b"FORMAT=") and line.strip() != b"FORMAT=32-bit_rle_rgbe":
            raise MediaError(
                "unsupported_codec",
                f"unsupported Radiance pixel format {line.decode(errors='replace')!r} (only 32-bit_rle_rgbe)",
            )
    eol = data.find(b"\n", end + 2)
    if eol < 0:
        raise MediaError("truncated", "Radiance file ends before its resolution line")
    parts = data[end + 2 : eol].split()
    if len(parts) != 4 or parts[2] != b"+X" or parts[0] not in (b"-Y", b"+Y"):
        raise MediaError(
            "unsupported_codec",
            f"unsupported Radiance resolution line {data[end + 2 : eol][:40]!r} (need '-Y H +X W' or '+Y H +X W')",
        )
    try:
        height, width = int(parts[1]), int(parts[3])
    except ValueError:
        raise MediaError("not_media", f"bad Radiance resolution line {data[end + 2:eol][:40]!r}") from None
    return height, width, parts[0] == b"+Y", eol + 1


def _decode_rle_plane(data: bytes, pos: int, width: int, out: np.ndarray) -> int:
    """Decode one run-length encoded byte plane of `width` bytes into `out`; return new pos."""
    x = 0
    n = len(data)
    while x < width:
        if pos >= n:
            raise MediaError("truncated", "Radiance file ends inside a scanline")
        count = data[pos]
        pos += 1
        if count > 128:  # run
            count -= 128
            if x + count > width or pos >= n:
                raise MediaError("truncated", "corrupt run in a Radiance scanline")
            out[x : x + count] = data[pos]
            pos += 1
        else:  # literal bytes
            if count == 0 or x + count > width or pos + count > n:
                raise MediaError("truncated", "corrupt literal in a Radiance scanline")
            out[x : x + count] = np.frombuffer(data, np.uint8, count, pos)
            pos += count
        x += count
    return pos


def _decode_pixels(data: bytes, pos: int, height: int, width: int) -> np.ndarray:
    rgbe = np.empty((height, width, 4), np.uint8)
    plane = np.empty(width, np.uint8)
    rle_possible = 8 <= width < 0x8000
    for y in range(height):
        head = data[pos : pos + 4]
        if rle_possible and len(head) == 4 and head[0] == 2 and head[1] == 2 and head[2] < 128:
            if (head[2] << 8) | head[3] != width:
                raise MediaError(
                    "truncated", f"Radiance scanline {y} declares width {(head[2] << 8) | head[3]}, expected {width}"
                )
            pos += 4
            for c in range(4):
                pos = _decode_rle_plane(data, pos, width, plane)
                rgbe[y, :, c] = plane
        else:  # flat scanline
            if pos + 4 * width > len(data):
                raise MediaError("truncated", f"Radiance file ends at scanline {y} of {height}")
            rgbe[y] = np.frombuffer(data, np.uint8, 4 * width, pos).reshape(width, 4)
            pos += 4 * width
    return rgbe


def rgbe_to_float(rgbe: np.ndarray) -> np.ndarray:
    """[..., 4] uint8 RGBE -> [..., 3] float32 (Radiance's colr_color: (m + 0.5) 2^(e-136))."""
    e = rgbe[..., 3:4].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(np.float32(1.0), e - 136), np.float32(0.0)).astype(np.float32)
    return ((rgbe[..., :3].astype(np.float32) + 0.5) * scale).astype(np.float32)


def float_to_rgbe(rgb: np.ndarray) -> np.ndarray:
    """[..., 3] float -> [..., 4] uint8 RGBE (Radiance's setcolr: truncated mantissa)."""
    rgb = np.asarray(rgb, np.float64)
    peak = rgb.max(axis=-1)
    mant, exp = np.frexp(peak)  # peak = mant * 2^exp, mant in [0.5, 1)
    visible = peak >= 1e-38  # below ~2^-128 RGBE stores zero
    scale = np.where(visible, mant * 256.0 / np.where(visible, peak, 1.0), 0.0)
    out = np.zeros(rgb.shape[:-1] + (4,), np.uint8)
    out[..., :3] = np.clip(np.floor(rgb * scale[..., None]), 0, 255).astype(np.uint8)
    out[..., 3] = np.where(visible, np.clip(exp + 128, 0, 255), 0).astype(np.uint8)
    return out


def read_hdr(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> np.ndarray:
    """float32 [H, W, 3] linear RGB from a Radiance .hdr path or bytes."""
    data = read_source(source, limits, "Radiance file")
    height, width, bottom_up, pos = _parse_header(data)
    limits.check_pixels(width, height, "Radiance image")
    rgb = rgbe_to_float(_decode_pixels(data, pos, height, width))
    return rgb[::-1].copy() if bottom_up else rgb


def _encode_rle_plane(plane: np.ndarray, out: bytearray) -> None:
    """Append one byte plane, run-length encoded (runs of >= 4 equal bytes, else literals)."""
    n = plane.size
    change = np.flatnonzero(np.diff(plane.astype(np.int16)) != 0) + 1
    starts = np.concatenate(([0], change))
    lengths = np.diff(np.concatenate((starts, [n])))
    literal_from = 0
    for start, length in zip(starts[lengths >= _MIN_RUN].tolist(), lengths[lengths >= _MIN_RUN].tolist()):
        _append_literals(plane[literal_from:start], out)
        value = int(plane[start])
        while length > 0:
            chunk = min(length, 127)
            if chunk < _MIN_RUN:  # leftover too short for a run
                _append_literals(plane[start : start + chunk], out)
            else:
                out += bytes((128 + chunk, value))
            start += chunk
            length -= chunk
        literal_from = start
    _append_literals(plane[literal_from:], out)


def _append_literals(values: np.ndarray, out: bytearray) -> None:
    for i in range(0, values.size, 128):
        chunk = values[i : i + 128]
        out.append(chunk.size)
        out += chunk.tobytes()


def encode_hdr(array: np.ndarray, rle: bool = True) -> bytes:
    """Radiance .hdr bytes for float [H, W, 3] (top row first). Negative values cannot be
    stored and are clamped to 0 with a warning; NaN/inf are refused ('non_finite')."""
    a = np.asarray(array)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 1 or a.shape[1] < 1:
        raise MediaError("shape_mismatch", f"Radiance image must be [H, W, 3], got shape {a.shape}")
    if not np.isfinite(a).all():
        raise MediaError(
            "non_finite", f"image has {int((~np.isfinite(a)).sum())} NaN/inf values; RGBE cannot store them"
        )
    if (a < 0).any():
        warnings.warn(
            f"clamped {int((a < 0).sum())} negative values to 0 (RGBE has no sign)", UserWarning, stacklevel=2
        )
        a = np.maximum(a, 0)
    height, width = a.shape[:2]
    rgbe = float_to_rgbe(a)
    out = bytearray(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + f"-Y {height} +X {width}\n".encode())
    if not rle or not (8 <= width < 0x8000):
        out += rgbe.tobytes()
        return bytes(out)
    head = bytes((2, 2, width >> 8, width & 0xFF))
    for y in range(height):
        out += head
        for c in range(4):
            _encode_rle_plane(rgbe[y, :, c], out)
    return bytes(out)


def write_hdr(path: str | os.PathLike, array: np.ndarray, rle: bool = True) -> Path:
    """Write `encode_hdr(array, rle)` to `path` atomically."""
    return atomic_write(path, encode_hdr(array, rle))
