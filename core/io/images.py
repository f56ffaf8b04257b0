"""LDR image decoding with limits, and PNG writing (8 and 16 bit).

Pillow opens files lazily: `Image.open` parses only the header, so the pixel count is
checked against `MediaLimits.max_pixels` before anything is decoded (decompression bombs).
Pillow's own bomb guard (`Image.MAX_IMAGE_PIXELS`) is kept as a second line of defence and
raised, never lowered, to the largest limit in use. 16-bit PNGs are decoded with OpenCV
because Pillow truncates 16-bit colour PNGs to 8 bits. Pixels come back UPRIGHT (the EXIF
orientation applied, as a viewer shows them) and in sRGB (an embedded non-sRGB ICC profile
converted); `decode_image` also returns the file's metadata, what was applied (core.io.metadata
has the rules) and what the file states about its transfer (`stated_transfer`, core.io.colour).

PNGs written here say what their values are: by default a gAMA chunk of 1/2.4 (the engine's
convention, core.conventions, so they read back as gamma:2.4), or the `transfer` asked for
(core.io.colour.png_colour_chunks). 16-bit PNGs hold data (depth) unless a transfer is given.
"""
from __future__ import annotations

import io
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from core.io.colour import (
    StatedTransfer,
    exif_color_space,
    image_stated_transfer,
    insert_after_ihdr,
    png_colour_chunks,
)
from core.io.exr import atomic_write
from core.io.limits import DEFAULT_LIMITS, MediaError, MediaLimits, Source, read_source
from core.io.metadata import (
    ImageMetadata,
    describe_orientation,
    image_metadata,
    orient_array,
    orient_image,
    orientation_swaps_axes,
    to_srgb,
)
from core.io.sniff import PNG_MAGIC, sniff_image
from core.transfer import CONVENTION, Transfer

try:
    _ENV_MAX_PIXELS = MediaLimits.from_env().max_pixels
except ValueError:  # a bad variable is reported where limits are built, not at import
    _ENV_MAX_PIXELS = DEFAULT_LIMITS.max_pixels
Image.MAX_IMAGE_PIXELS = max(Image.MAX_IMAGE_PIXELS or 0, _ENV_MAX_PIXELS)


def _png_bit_depth(data: bytes) -> int:
    """Bit depth from the IHDR chunk (always the first chunk, at a fixed offset)."""
    return data[24] if data.startswith(PNG_MAGIC) and len(data) > 24 else 0


def _open_checked(data: bytes, limits: MediaLimits) -> Image.Image:
    fmt = sniff_image(data)
    if fmt is None:
        raise MediaError("not_media", "not a supported image (unrecognised magic bytes)")
    if limits.max_pixels > (Image.MAX_IMAGE_PIXELS or 0):
        Image.MAX_IMAGE_PIXELS = limits.max_pixels
    try:
        image = Image.open(io.BytesIO(data))
    except Image.DecompressionBombError as exc:
        raise MediaError("too_many_pixels", f"image declares too many pixels ({exc})") from None
    except Exception as exc:  # UnidentifiedImageError, SyntaxError from broken headers, ...
        if fmt == "heif":
            raise MediaError(
                "unsupported_codec", "HEIF/AVIF images are not supported; convert to PNG or JPEG"
            ) from None
        raise MediaError("truncated", f"{fmt.upper()} header is corrupt or truncated") from exc
    width, height = image.size
    limits.check_pixels(width, height, f"{fmt.upper()} image")
    return image


def probe_image(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> tuple[int, int]:
    """(width, height) of an image `read_image` accepts, upright (EXIF orientation applied),
    from its header under `limits`, with the file's structure verified (Pillow's verify: PNG
    chunk CRCs, truncation) but no pixel decoded. Refuses with the same MediaError codes as
    read_image for what that reveals."""
    data = read_source(source, limits, "image")
    image = _open_checked(data, limits)
    _check_sample_format(image, data)
    try:
        image.verify()
    except Image.DecompressionBombError as exc:
        raise MediaError("too_many_pixels", str(exc)) from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise MediaError("truncated", f"{image.format} data is truncated or corrupt ({exc})") from None
    w, h = image.size
    with Image.open(io.BytesIO(data)) as again:  # verify() spends the image: EXIF from a fresh header parse
        swap = orientation_swaps_axes(image_metadata(again).orientation)
        if again.format != "PNG":  # verify() reads PNG chunks to the end, other formats not at all
            _decode_to_the_end(again)
    return (h, w) if swap else (w, h)


def _decode_to_the_end(image: Image.Image) -> None:
    """Decode every byte of the image data, as decode_image will, so that a truncated or corrupt
    file is refused now ('truncated'). A JPEG is decoded at 1/8 scale (its DCT scaling reads all
    the entropy-coded data but makes 1/64 of the pixels): a 16 Mpx photo costs ~1 MB, not 48."""
    try:
        if image.format == "JPEG":
            image.draft("RGB", (max(1, image.size[0] // 8), max(1, image.size[1] // 8)))
        image.load()
    except Image.DecompressionBombError as exc:
        raise MediaError("too_many_pixels", str(exc)) from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise MediaError("truncated", f"{image.format} data is truncated or corrupt ({exc})") from None


def check_complete(data: bytes) -> None:
    """Refuse ('truncated') a JPEG or PNG whose end is missing, from its markers alone (no
    decode): a PNG must hold its IEND chunk, a JPEG an end-of-image marker after its last scan
    (markers cannot occur inside entropy-coded data, where 0xFF bytes are stuffed). For the
    frames of a capture beyond the first, which the upload check does not decode."""
    fmt = sniff_image(data)
    if fmt == "png" and data.rfind(b"IEND\xaeB`\x82") < 0:
        raise MediaError("truncated", "PNG data is truncated (no IEND chunk)")
    if fmt == "jpeg":
        last_scan = data.rfind(b"\xff\xda")
        if last_scan < 0 or data.find(b"\xff\xd9", last_scan) < 0:
            raise MediaError("truncated", "JPEG data is truncated (no end-of-image marker after its last scan)")


def _check_sample_format(image: Image.Image, data: bytes) -> None:
    if image.mode in ("I", "F") and not (image.format == "PNG" and _png_bit_depth(data) == 16):
        # 32-bit integer / float samples: no defined white level
        raise MediaError(
            "unsupported_codec",
            f"{image.format} with 32-bit {image.mode!r} samples is not an LDR image; send HDR as EXR or .hdr",
        )


def _decode_png16(data: bytes) -> np.ndarray:
    """uint16 [H, W] or [H, W, 3|4] in RGB(A) order."""
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if decoded is None:
        raise MediaError("truncated", "16-bit PNG data is truncated or corrupt")
    if decoded.ndim == 3:
        decoded = cv2.cvtColor(decoded, cv2.COLOR_BGRA2RGBA if decoded.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return decoded


def _to_rgb(array: np.ndarray) -> np.ndarray:
    if array.ndim == 2:
        return np.repeat(array[..., None], 3, axis=-1)
    return array[..., :3]


@dataclass
class DecodedImage:
    pixels: np.ndarray  # float32 [H, W, 3] in [0, 1], upright, sRGB
    metadata: ImageMetadata
    stored_size: tuple[int, int]  # (width, height) as stored, before orientation
    applied: list[str] = field(default_factory=list)  # what was done to the stored pixels
    stated_transfer: StatedTransfer | None = None  # what the file states (always set by decode_image)


def decode_image(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> DecodedImage:
    """float32 [H, W, 3] in [0, 1] from PNG (8/16 bit), JPEG, WebP, BMP, TIFF, GIF (first
    frame), upright and in sRGB, with the file's metadata. Alpha is dropped (not composited),
    grey is expanded to RGB."""
    data = read_source(source, limits, "image")
    image = _open_checked(data, limits)
    meta = image_metadata(image)
    applied = [describe_orientation(meta.orientation) + ": turned upright"] if meta.orientation != 1 else []
    color_space = exif_color_space(image)

    def stated(bit_depth: int, icc_converted: bool) -> StatedTransfer:
        return image_stated_transfer(data, image.format, meta, bit_depth, icc_converted, color_space)

    if image.format == "PNG" and _png_bit_depth(data) == 16:
        if meta.icc_description is not None and not meta.icc_is_srgb:
            applied.append(f"ICC profile {meta.icc_description!r} of a 16-bit PNG not converted (values used as sRGB)")
        pixels = orient_array(_to_rgb(_decode_png16(data)), meta.orientation).astype(np.float32) / np.float32(65535.0)
        return DecodedImage(pixels, meta, image.size, applied, stated(16, False))
    _check_sample_format(image, data)
    try:
        image.load()
        if image.mode.startswith("I;16"):  # 16-bit grey TIFF
            grey = orient_array(np.asarray(image, np.float32) / np.float32(65535.0), meta.orientation)
            return DecodedImage(_to_rgb(grey), meta, image.size, applied, stated(16, False))
        converted, note = to_srgb(image, meta)
        if note:
            applied.append(note)
        rgb = orient_image(converted.convert("RGB"), meta.orientation)
    except Image.DecompressionBombError as exc:
        raise MediaError("too_many_pixels", str(exc)) from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise MediaError("truncated", f"{image.format} data is truncated or corrupt ({exc})") from None
    return DecodedImage(np.asarray(rgb, np.float32) / np.float32(255.0), meta, image.size, applied,
                        stated(8, converted is not image))


def read_image(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> np.ndarray:
    """`decode_image(...).pixels`: upright sRGB float32 [H, W, 3] in [0, 1]."""
    return decode_image(source, limits).pixels


def _check_image_array(array: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(array)
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (1, 3, 4))) or a.shape[0] < 1 or a.shape[1] < 1:
        raise MediaError("shape_mismatch", f"{what} must be [H, W] or [H, W, 1|3|4], got shape {a.shape}")
    return a[..., 0] if a.ndim == 3 and a.shape[2] == 1 else a


def _to_bgr(a: np.ndarray) -> np.ndarray:
    if a.ndim == 2:
        return a
    return cv2.cvtColor(a, cv2.COLOR_RGBA2BGRA if a.shape[2] == 4 else cv2.COLOR_RGB2BGR)


def _png_bytes(a: np.ndarray, transfer: str | Transfer | None = None) -> bytes:
    """PNG bytes of a checked uint8/uint16 RGB(A) or grey array (cv2 wants BGR order), with the
    chunks that state `transfer` (None: none) right after IHDR."""
    ok, buf = cv2.imencode(".png", _to_bgr(np.ascontiguousarray(a)))
    if not ok:
        raise MediaError("shape_mismatch", f"PNG encoder refused an array of shape {a.shape}")
    png = buf.tobytes()
    return png if transfer is None else insert_after_ihdr(png, png_colour_chunks(transfer))


UNTAGGED = "untagged"  # encode_png: no colour chunk (data packed in an image: glTF's RGBD faces)


def encode_png(ldr: np.ndarray, transfer: str | Transfer | None = None) -> bytes:
    """8-bit PNG bytes from float in [0, 1] (clipped, rounded) or uint8, RGB(A) or grey.
    `transfer` states what the values are: None, the engine's convention (gamma:2.4), writes a
    gAMA chunk of 1/2.4 (0.41667); 'srgb' an sRGB chunk (rendering intent 0, with gAMA 0.45455);
    'gamma:G' gAMA 1/G; 'linear' gAMA 1; 'rec709', 'hlg', 'pq' a cICP chunk (core.io.colour);
    UNTAGGED none (values that are data, not light: glTF validators warn on colour chunks).
    The values are written as given, never converted."""
    a = _check_image_array(ldr, "PNG image")
    if a.dtype != np.uint8:
        a = a.astype(np.float32)
        if not np.isfinite(a).all():
            raise MediaError("non_finite", f"PNG image has {int((~np.isfinite(a)).sum())} NaN/inf values")
        a = np.round(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8)
    return _png_bytes(a, None if transfer == UNTAGGED else CONVENTION if transfer is None else transfer)


def write_png(path: str | os.PathLike, ldr: np.ndarray, transfer: str | Transfer | None = None) -> Path:
    """Write an 8-bit PNG (see `encode_png`) atomically."""
    return atomic_write(path, encode_png(ldr, transfer))


def encode_png16(array: np.ndarray, transfer: str | Transfer | None = None) -> bytes:
    """16-bit PNG bytes from uint16 [H, W] or [H, W, 3|4] (RGB order). Other integer dtypes
    are accepted if every value fits in 0..65535; floats are refused (scale them first).
    `transfer` as in `encode_png`, except that None writes no colour chunk: a 16-bit PNG here
    is data (depth in millimetres) unless a transfer says it is an image."""
    a = _check_image_array(array, "16-bit PNG image")
    if a.dtype != np.uint16:
        if not np.issubdtype(a.dtype, np.integer):
            raise MediaError("shape_mismatch", f"16-bit PNG needs integer values, got dtype {a.dtype}")
        if a.size and (a.min() < 0 or a.max() > 65535):
            raise MediaError("shape_mismatch", f"16-bit PNG values must be in 0..65535, got {a.min()}..{a.max()}")
        a = a.astype(np.uint16)
    return _png_bytes(a, transfer)


def write_png16(path: str | os.PathLike, array: np.ndarray, transfer: str | Transfer | None = None) -> Path:
    """Write a 16-bit PNG (see `encode_png16`) atomically."""
    return atomic_write(path, encode_png16(array, transfer))


def read_png16(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> np.ndarray:
    """uint16 [H, W] (grey) or [H, W, 3|4] (RGB order) from a 16-bit PNG; an 8-bit PNG is
    refused with code 'wrong_bit_depth' (it cannot hold 16-bit data such as depth)."""
    data = read_source(source, limits, "16-bit PNG")
    if not data.startswith(PNG_MAGIC):
        raise MediaError("not_media", "not a PNG file (bad magic bytes)")
    _open_checked(data, limits)
    depth = _png_bit_depth(data)
    if depth != 16:
        raise MediaError("wrong_bit_depth", f"PNG has {depth}-bit samples; a 16-bit PNG is required")
    return _decode_png16(data)
