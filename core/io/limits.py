"""Resource limits for decoding untrusted media, and the one error type I/O raises.

Every user-triggerable I/O failure raises `MediaError` with a stable `.code` (see
`ERROR_CODES`); the HTTP service maps codes to 4xx statuses via `HTTP_STATUS`. Limits are
checked from headers *before* pixel data is decoded, so a tiny file that declares a huge
image (a decompression bomb) is refused without allocating it.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Union

Source = Union[str, os.PathLike, bytes, bytearray, memoryview]

# code -> suggested HTTP status (413 = too big, 415 = not a supported media type, 422 = bad content)
HTTP_STATUS: dict[str, int] = {
    "empty": 422,
    "not_found": 422,
    "truncated": 422,
    "not_media": 415,
    "unsupported_codec": 415,
    "wrong_bit_depth": 422,
    "invalid_depth": 422,
    "too_many_pixels": 413,
    "too_many_frames": 413,
    "too_large": 413,
    "non_finite": 422,
    "shape_mismatch": 422,
    "invalid_poses": 422,  # a capture file's poses outside the range a capture may state (core.camera)
    "invalid_intrinsics": 422,  # a capture file's intrinsics or distortion outside theirs
}
ERROR_CODES = tuple(HTTP_STATUS)

MiB = 1024 * 1024


class MediaError(ValueError):
    """A file cannot be read or written as asked. `.code` is one of `ERROR_CODES`."""

    def __init__(self, code: str, message: str):
        if code not in HTTP_STATUS:
            raise ValueError(f"unknown MediaError code {code!r}")
        super().__init__(message)
        self.code = code

    @property
    def http_status(self) -> int:
        return HTTP_STATUS[self.code]


@dataclass(frozen=True)
class MediaLimits:
    """What a decoder may accept. `max_pixels` is per frame; `max_total_pixels` bounds
    T*H*W over all decoded frames (the float32 result takes 12 bytes per pixel, so the
    default 1e8 caps a decoded video at ~1.2 GB). `frame_stride` keeps every n-th frame."""

    max_bytes: int = 200 * MiB
    max_pixels: int = 4096 * 4096
    max_frames: int = 300
    frame_stride: int = 1
    max_total_pixels: int = 100_000_000

    def __post_init__(self):
        for name in ("max_bytes", "max_pixels", "max_frames", "frame_stride", "max_total_pixels"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"MediaLimits.{name} must be a positive integer, got {value!r}")

    @classmethod
    def from_env(cls, environ: dict[str, str] | None = None) -> "MediaLimits":
        """Defaults overridden by LIGHTFIELD_MAX_BYTES / _MAX_PIXELS / _MAX_FRAMES /
        _MAX_TOTAL_PIXELS / _FRAME_STRIDE (plain integers)."""
        env = os.environ if environ is None else environ
        names = {
            "max_bytes": "LIGHTFIELD_MAX_BYTES",
            "max_pixels": "LIGHTFIELD_MAX_PIXELS",
            "max_frames": "LIGHTFIELD_MAX_FRAMES",
            "max_total_pixels": "LIGHTFIELD_MAX_TOTAL_PIXELS",
            "frame_stride": "LIGHTFIELD_FRAME_STRIDE",
        }
        kwargs = {}
        for field, var in names.items():
            raw = env.get(var)
            if raw is None or raw.strip() == "":
                continue
            try:
                kwargs[field] = int(raw)
            except ValueError:
                raise ValueError(f"environment variable {var} must be an integer, got {raw!r}") from None
        return cls(**kwargs)

    def check_bytes(self, n: int, what: str = "file") -> None:
        if n == 0:
            raise MediaError("empty", f"{what} is empty (0 bytes)")
        if n > self.max_bytes:
            raise MediaError("too_large", f"{what} is {n} bytes, more than the limit of {self.max_bytes} bytes")

    def check_pixels(self, width: int, height: int, what: str = "image") -> None:
        if width <= 0 or height <= 0:
            raise MediaError("not_media", f"{what} declares an invalid size {width}x{height}")
        if width * height > self.max_pixels:
            raise MediaError(
                "too_many_pixels",
                f"{what} is {width}x{height} = {width * height} pixels, more than the limit of {self.max_pixels}",
            )


DEFAULT_LIMITS = MediaLimits()


def read_source(source: Source, limits: MediaLimits = DEFAULT_LIMITS, what: str = "file") -> bytes:
    """Bytes of a path or bytes-like input, refusing empty and oversized input before reading."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        data = bytes(source)
        limits.check_bytes(len(data), what)
        return data
    path = existing_file(source, what)
    limits.check_bytes(path.stat().st_size, f"{what} {str(path)!r}")
    return path.read_bytes()


def existing_file(source: str | os.PathLike, what: str = "file") -> Path:
    path = Path(source)
    if not path.is_file():
        raise MediaError("not_found", f"{what} {str(path)!r} does not exist or is not a regular file")
    return path
