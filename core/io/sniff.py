"""Identify media by magic bytes, never by file name (names are user-controlled and lie)."""
from __future__ import annotations

from typing import BinaryIO, Literal, Optional

import numpy as np

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
EXR_MAGIC = b"\x76\x2f\x31\x01"
NPY_MAGIC = b"\x93NUMPY"
ZIP_MAGIC = b"PK\x03\x04"
# ISO-BMFF brands that hold still images, not video
_STILL_BRANDS = {b"heic", b"heix", b"heim", b"heis", b"mif1", b"msf1", b"avif", b"avis"}
_QUICKTIME_ATOMS = {b"moov", b"mdat", b"wide", b"free", b"skip", b"pnot"}
_BMP_DIB_SIZES = {12, 40, 52, 56, 64, 108, 124}


def _is_bmp(data: bytes) -> bool:
    return len(data) >= 18 and data[:2] == b"BM" and int.from_bytes(data[14:18], "little") in _BMP_DIB_SIZES


def sniff_image(data: bytes) -> Optional[str]:
    """Image format name ('png', 'jpeg', 'webp', 'bmp', 'tiff', 'gif', 'heif') or None."""
    if data.startswith(PNG_MAGIC):
        return "png"
    if data.startswith(b"\xff\xd8\xff"):
        return "jpeg"
    if len(data) >= 12 and data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "webp"
    if _is_bmp(data):
        return "bmp"
    if data[:4] in (b"II*\x00", b"MM\x00*"):
        return "tiff"
    if data[:6] in (b"GIF87a", b"GIF89a"):
        return "gif"
    if len(data) >= 12 and data[4:8] == b"ftyp" and data[8:12] in _STILL_BRANDS:
        return "heif"
    return None


def sniff_video(data: bytes) -> Optional[str]:
    """Container name ('mp4', 'matroska', 'avi', 'mpeg', 'ogg') or None."""
    if len(data) >= 12 and data[4:8] == b"ftyp":
        return None if data[8:12] in _STILL_BRANDS else "mp4"
    if len(data) >= 8 and data[4:8] in _QUICKTIME_ATOMS:  # old QuickTime .mov without ftyp
        return "mp4"
    if data.startswith(b"\x1a\x45\xdf\xa3"):  # EBML: WebM / Matroska
        return "matroska"
    if len(data) >= 12 and data[:4] == b"RIFF" and data[8:12] == b"AVI ":
        return "avi"
    if data[:4] in (b"\x00\x00\x01\xba", b"\x00\x00\x01\xb3"):
        return "mpeg"
    if data.startswith(b"OggS"):
        return "ogg"
    return None


def sniff_media(data: bytes) -> Literal["image", "video"] | None:
    """'image' or 'video' from the first bytes of a file (16 are enough), else None."""
    if sniff_image(data) is not None:
        return "image"
    if sniff_video(data) is not None:
        return "video"
    return None


def sniff_depth(data: bytes) -> Literal["npz", "npy", "exr", "png"] | None:
    """Depth container from magic bytes: an .npz is a zip archive, an .npy has NumPy's magic."""
    if data.startswith(ZIP_MAGIC) or data.startswith(b"PK\x05\x06"):  # second: empty zip
        return "npz"
    if data.startswith(NPY_MAGIC):
        return "npy"
    if data.startswith(EXR_MAGIC):
        return "exr"
    if data.startswith(PNG_MAGIC):
        return "png"
    return None


def sniff_hdr_image(data: bytes) -> Literal["exr", "hdr", "npy"] | None:
    """Linear HDR image container: OpenEXR, Radiance RGBE, or a NumPy array."""
    if data.startswith(EXR_MAGIC):
        return "exr"
    if data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE"):
        return "hdr"
    if data.startswith(NPY_MAGIC):
        return "npy"
    return None


def npy_header(fp: BinaryIO) -> tuple[tuple, np.dtype]:
    """(shape, dtype) from an .npy stream's header, without reading the array data, so
    callers can refuse object arrays and oversized shapes before any allocation."""
    version = np.lib.format.read_magic(fp)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(fp)
    else:  # 2.0 and 3.0 share the 4-byte header length (3.0 only allows utf-8 field names)
        shape, _, dtype = np.lib.format.read_array_header_2_0(fp)
    return tuple(shape), dtype
