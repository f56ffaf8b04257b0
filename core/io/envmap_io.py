"""Encode, save and load equirectangular HDR environment maps.

Formats: 'exr' (float32, or half with `half=True`), 'hdr' (Radiance RGBE, ~1% precision),
'npy' (float32, exact) and 'png' (an LDR preview tone-mapped with the project's tone map
`core.conventions.tonemap` at exposure `ev`; not invertible above white).
"""
from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from core.exposure import to_uint8, tonemap
from core.io.exr import atomic_write, encode_exr, read_exr
from core.io.hdr import encode_hdr, read_hdr
from core.io.images import encode_png
from core.io.limits import DEFAULT_LIMITS, MediaError, MediaLimits, read_source
from core.io.sniff import npy_header, sniff_hdr_image

EnvmapFormat = Literal["exr", "hdr", "png", "npy"]
MEDIA_TYPES: dict[str, str] = {
    "exr": "image/x-exr",
    "hdr": "image/vnd.radiance",
    "png": "image/png",
    "npy": "application/x-npy",
}


def _check_envmap(hdr: np.ndarray) -> np.ndarray:
    a = np.asarray(hdr)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 1 or a.shape[1] < 1:
        raise MediaError("shape_mismatch", f"env map must be [H, W, 3], got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise MediaError("shape_mismatch", f"env map must be real-valued, got dtype {a.dtype}")
    return a.astype(np.float32, copy=False)


def tonemapped_preview(hdr: np.ndarray, ev: float = 0.0) -> np.ndarray:
    """uint8 [H, W, 3] preview: the paper's tone map at exposure `ev`, rounded."""
    return to_uint8(tonemap(torch.from_numpy(np.ascontiguousarray(hdr)), float(ev))).numpy()


def encode_envmap(hdr: np.ndarray, fmt: EnvmapFormat, ev: float = 0.0, half: bool = False,
                  attributes: dict | None = None, compress: bool = True) -> tuple[bytes, str]:
    """-> (file bytes, media type). `ev` only affects 'png'; `half`, `attributes` (EXR
    header attributes, e.g. `core.export.metadata.envmap_attributes`) and `compress` only 'exr'."""
    a = _check_envmap(hdr)
    if fmt == "exr":
        data = encode_exr(a, half=half, attributes=attributes, compress=compress)
    elif fmt == "hdr":
        data = encode_hdr(a)
    elif fmt == "png":
        if not np.isfinite(ev):
            raise MediaError("non_finite", f"ev must be finite, got {ev}")
        data = encode_png(tonemapped_preview(a, ev))
    elif fmt == "npy":
        if not np.isfinite(a).all():
            raise MediaError("non_finite", f"env map has {int((~np.isfinite(a)).sum())} NaN/inf values")
        buf = io.BytesIO()
        np.save(buf, a, allow_pickle=False)
        data = buf.getvalue()
    else:
        raise MediaError("unsupported_codec", f"env map format must be one of {sorted(MEDIA_TYPES)}, got {fmt!r}")
    return data, MEDIA_TYPES[fmt]


def save_envmap(
    path: str | os.PathLike,
    hdr: np.ndarray,
    fmt: EnvmapFormat | None = None,
    ev: float = 0.0,
    half: bool = False,
    attributes: dict | None = None,
) -> Path:
    """Write an env map atomically; `fmt` defaults to the path's suffix."""
    path = Path(path)
    fmt = fmt or path.suffix.lower().lstrip(".")
    data, _ = encode_envmap(hdr, fmt, ev=ev, half=half, attributes=attributes)  # type: ignore[arg-type]
    return atomic_write(path, data)


def _load_npy(data: bytes) -> np.ndarray:
    try:
        _, dtype = npy_header(io.BytesIO(data))
        if dtype.hasobject:
            raise MediaError("not_media", f".npy env map holds Python objects (dtype {dtype}), not numbers")
        return np.load(io.BytesIO(data), allow_pickle=False)
    except MediaError:  # a ValueError too: let it through unchanged
        raise
    except (ValueError, EOFError, OSError) as exc:
        raise MediaError("truncated", f".npy env map is truncated or corrupt ({exc})") from None


def load_envmap(source: str | os.PathLike | bytes, limits: MediaLimits = DEFAULT_LIMITS) -> np.ndarray:
    """float32 [H, W, 3] from EXR, Radiance .hdr or .npy, chosen by content, not name."""
    data = read_source(source, limits, "env map")
    kind = sniff_hdr_image(data)
    if kind == "exr":
        a = read_exr(data, limits)
    elif kind == "hdr":
        a = read_hdr(data, limits)
    elif kind == "npy":  # uncompressed, so read_source's byte limit bounds the allocation
        a = _load_npy(data)
    else:
        raise MediaError("not_media", "env map must be OpenEXR, Radiance .hdr or .npy")
    a = _check_envmap(a)
    return np.ascontiguousarray(a)
