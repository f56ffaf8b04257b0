"""What a file says about its colour: the transfer (curve), bit depth and primaries it states,
and the same statements written into the files the product makes.

`StatedTransfer` is read from the FILE only (`transfer` None: the file states nothing it can be
read by); deciding what to assume when it says nothing is the caller's (core.capture). The
rules, highest precedence first:

* **PNG** (the PNG 3rd edition's order, cICP > iCCP > sRGB > gAMA): a `cICP` chunk (H.273 code
  points: primaries, transfer, matrix, full-range flag) -> `transfer_from_h273`; an ICC profile
  whose description names sRGB -> srgb; any other readable ICC profile is converted to sRGB on
  decoding (core.io.metadata.to_srgb), so the pixels are then sRGB; an `sRGB` chunk -> srgb; a
  `gAMA` chunk g -> ``gamma:1/g`` (g = 0.45455 is decoded with gamma 2.2; g = 1 is linear);
  then EXIF ColorSpace as below.
* **JPEG and the other still formats**: an ICC profile as above; else the EXIF ColorSpace tag
  (0xA001) = 1 -> srgb (0xFFFF, "uncalibrated", states nothing).
* **Video**: the stream's colour description (H.264/HEVC VUI, or the container's `colr` box),
  transfer characteristics -> `transfer_from_h273`, colour primaries 1 -> bt709, 9 -> bt2020;
  the bit depth is the decoded pixel format's.

`primaries` is "bt709" (also for sRGB), "bt2020", or None (not stated, or another gamut).
Nothing here converts a gamut: the pixels keep the file's primaries.

Writing (`png_colour_chunks`, `h273_transfer_code`): a PNG names its transfer with an sRGB chunk
(srgb, with the gAMA 0.45455 that the PNG specification recommends beside it for older
readers), a gAMA chunk (gamma:G -> 1/G, linear -> 1) or, for curves gAMA cannot express
(rec709, hlg, pq), a cICP chunk. A video names it with an H.273 code; gamma curves other than
2.2 and 2.8 have none (2, unspecified, is written).
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np
from PIL import ExifTags

from core.transfer import MAX_GAMMA, MIN_GAMMA, Transfer, parse_transfer, transfer_from_h273

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
EXIF_COLOR_SPACE = 0xA001
PNG_GAMMA_SCALE = 100_000

# ffmpeg's names (av_color_transfer_name) of the H.273 transfer characteristics
H273_TRANSFER_NAMES = {
    1: "bt709", 2: "unspecified", 4: "bt470m", 5: "bt470bg", 6: "smpte170m", 7: "smpte240m", 8: "linear",
    9: "log100", 10: "log316", 11: "iec61966-2-4", 12: "bt1361e", 13: "iec61966-2-1", 14: "bt2020-10",
    15: "bt2020-12", 16: "smpte2084", 17: "smpte428", 18: "arib-std-b67",
}
# transfer -> the H.273 code written for it (the inverse of core.transfer.H273_TRANSFERS)
H273_CODES = {"rec709": 1, "gamma:2.2": 4, "gamma:2.8": 5, "linear": 8, "srgb": 13, "pq": 16, "hlg": 18}
H273_UNSPECIFIED = 2
H273_PRIMARIES = {1: "bt709", 9: "bt2020"}
PRIMARIES_CODES = {"bt709": 1, "bt2020": 9}
# H.273 matrix coefficients -> (Kr, Kb): BT.709, BT.601 (470BG, 170M), BT.2020 non-constant luminance
MATRIX_KR_KB = {1: (0.2126, 0.0722), 5: (0.299, 0.114), 6: (0.299, 0.114), 9: (0.2627, 0.0593)}
_CODEC_NAMES = {"h264": "H.264", "hevc": "HEVC", "vp9": "VP9", "vp8": "VP8", "av1": "AV1", "prores": "ProRes",
                "mpeg4": "MPEG-4", "gif": "GIF"}


@dataclass(frozen=True)
class StatedTransfer:
    """What a file states about its samples: the transfer (None: nothing this product can
    read), where that was read (`source`, for the job's metadata), the bit depth of the stored
    samples (8, 10, 12, 16) and the primaries ("bt709", "bt2020" or None)."""

    transfer: Transfer | None
    source: str
    bit_depth: int = 8
    primaries: str | None = None

    def as_dict(self) -> dict:
        return {"transfer": None if self.transfer is None else str(self.transfer), "source": self.source,
                "bit_depth": self.bit_depth, "primaries": self.primaries}


def h273_transfer_name(code: int) -> str:
    return H273_TRANSFER_NAMES.get(int(code), "reserved")


def _srgb(source: str, bit_depth: int) -> StatedTransfer:
    return StatedTransfer(Transfer("srgb"), source, bit_depth, "bt709")


# ---------------------------------------------------------------------------------------
# Still images
# ---------------------------------------------------------------------------------------
def png_chunks(data: bytes, names: tuple[bytes, ...] = (b"cICP", b"iCCP", b"sRGB", b"gAMA")) -> dict[bytes, bytes]:
    """The payload of the first chunk of each type in `names` before the image data (where the
    PNG specification puts colour chunks); CRCs are not checked here (Pillow checks them)."""
    found: dict[bytes, bytes] = {}
    pos = len(PNG_SIGNATURE)
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        if kind in (b"IDAT", b"IEND") or pos + 12 + length > len(data):
            break
        if kind in names and kind not in found:
            found[kind] = data[pos + 8:pos + 8 + length]
        pos += 12 + length
    return found


def _gamma_statement(payload: bytes, bit_depth: int) -> StatedTransfer | None:
    if len(payload) != 4:
        return None
    stored = int.from_bytes(payload, "big")
    text = f"{stored / PNG_GAMMA_SCALE:.5f}".rstrip("0").rstrip(".")
    source = f"PNG gAMA chunk {text}"
    if stored <= 0:
        return None
    gamma = PNG_GAMMA_SCALE / stored
    if abs(gamma - 1.0) < 1e-3:
        return StatedTransfer(Transfer("linear"), source, bit_depth)
    gamma = round(gamma, 3)  # 0.45455 -> 2.2, 0.41667 -> 2.4: the 5 stored digits' precision
    if not (MIN_GAMMA <= gamma <= MAX_GAMMA):
        return StatedTransfer(None, f"{source} (decoding gamma {gamma:g} outside [{MIN_GAMMA:g}, {MAX_GAMMA:g}]; "
                              "not used)", bit_depth)
    return StatedTransfer(Transfer("gamma", gamma), source, bit_depth)


def _cicp_statement(payload: bytes, bit_depth: int) -> StatedTransfer | None:
    if len(payload) != 4:
        return None
    primaries, trc, _matrix, full_range = payload
    transfer = transfer_from_h273(trc)
    source = (f"PNG cICP chunk (transfer {trc} ({h273_transfer_name(trc)}), primaries {primaries}"
              + ("" if full_range else ", narrow range") + ")")
    if transfer is None:
        source += ": not a transfer this product reads"
    return StatedTransfer(transfer, source, bit_depth, H273_PRIMARIES.get(primaries))


def exif_color_space(image) -> int | None:
    """EXIF ColorSpace (0xA001, in the Exif IFD) of an opened Pillow image, or None."""
    try:
        value = image.getexif().get_ifd(ExifTags.IFD.Exif).get(EXIF_COLOR_SPACE)
    except Exception:  # a malformed EXIF block states nothing
        return None
    return value if isinstance(value, int) else None


def image_stated_transfer(data: bytes, image_format: str | None, meta, bit_depth: int,
                          icc_converted: bool, color_space: int | None) -> StatedTransfer:
    """What a still image states (module doc). `meta` is its core.io.metadata.ImageMetadata,
    `icc_converted` whether decoding converted its ICC profile to sRGB, `color_space` its EXIF
    ColorSpace (`exif_color_space`)."""
    fmt = (image_format or "image").upper()
    chunks = png_chunks(data) if data.startswith(PNG_SIGNATURE) else {}
    if b"cICP" in chunks:
        stated = _cicp_statement(chunks[b"cICP"], bit_depth)
        if stated is not None:
            return stated
    if meta.icc_description is not None:
        if meta.icc_is_srgb:
            return _srgb(f"{fmt} ICC profile {meta.icc_description!r}", bit_depth)
        if icc_converted:
            return _srgb(f"ICC profile {meta.icc_description!r} converted to sRGB", bit_depth)
        return StatedTransfer(None, f"{fmt} ICC profile {meta.icc_description!r} (not sRGB, not converted: "
                              "its curve is not read)", bit_depth)
    if b"sRGB" in chunks:
        return _srgb("PNG sRGB chunk", bit_depth)
    if b"gAMA" in chunks:
        stated = _gamma_statement(chunks[b"gAMA"], bit_depth)
        if stated is not None:
            return stated
    if color_space == 1:
        return _srgb("EXIF ColorSpace sRGB", bit_depth)
    what = ("no cICP, iCCP, sRGB or gAMA chunk" if fmt == "PNG" else "no ICC profile")
    what += ", EXIF ColorSpace uncalibrated" if color_space == 0xFFFF else ", no EXIF ColorSpace sRGB"
    return StatedTransfer(None, f"{fmt} states no transfer ({what})", bit_depth)


# ---------------------------------------------------------------------------------------
# Writing PNG colour chunks
# ---------------------------------------------------------------------------------------
def png_chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def png_colour_chunks(transfer: str | Transfer) -> bytes:
    """The chunk(s) that state `transfer` in a PNG (module doc)."""
    t = transfer if isinstance(transfer, Transfer) else parse_transfer(transfer)
    if t.name == "srgb":
        return png_chunk(b"sRGB", b"\x00") + png_chunk(b"gAMA", struct.pack(">I", 45455))
    if t.name in ("gamma", "linear"):
        gamma = 1.0 if t.name == "linear" else float(t.gamma)
        return png_chunk(b"gAMA", struct.pack(">I", round(PNG_GAMMA_SCALE / gamma)))
    # rec709, hlg, pq: BT.709 primaries, RGB (matrix 0), full range
    return png_chunk(b"cICP", bytes((1, H273_CODES[t.name], 0, 1)))


def insert_after_ihdr(png: bytes, chunks: bytes) -> bytes:
    """`chunks` inserted right after the IHDR chunk (the first, 13 bytes long) of `png`."""
    at = len(PNG_SIGNATURE) + 8 + 13 + 4
    if not png.startswith(PNG_SIGNATURE) or png[12:16] != b"IHDR":
        raise ValueError("not a PNG starting with its IHDR chunk")
    return png[:at] + chunks + png[at:]


# ---------------------------------------------------------------------------------------
# Video
# ---------------------------------------------------------------------------------------
def h273_transfer_code(transfer: Transfer | None) -> int:
    """The H.273 transfer characteristics code written for `transfer` (2, unspecified, for
    None and for gamma curves that H.273 has no code for, e.g. the engine's gamma:2.4)."""
    return H273_UNSPECIFIED if transfer is None else H273_CODES.get(str(transfer), H273_UNSPECIFIED)


def colour_tag(frame, codec_context, name: str) -> int:
    """An H.273 colour tag (color_trc, color_primaries, colorspace) of the decoded PyAV frame,
    else of the codec context; 2 (unspecified) when neither states one (0, reserved, skipped)."""
    for holder in (frame, codec_context):
        value = int(getattr(holder, name, 0) or 0) if holder is not None else 0
        if value not in (0, H273_UNSPECIFIED):
            return value
    return H273_UNSPECIFIED


def video_stated_transfer(codec_context, frame) -> StatedTransfer:
    """What a video stream states: the decoded frame's colour tags, else the codec context's."""
    def tag(name: str) -> int:
        return colour_tag(frame, codec_context, name)

    codec = _CODEC_NAMES.get(codec_context.name, codec_context.name.upper())
    bits = frame.format.components[0].bits if frame is not None else 8
    bit_depth = int(bits) if bits and bits > 8 else 8
    trc, primaries = tag("color_trc"), tag("color_primaries")
    primaries_name = H273_PRIMARIES.get(primaries)
    if trc == H273_UNSPECIFIED:
        return StatedTransfer(None, f"{codec} stream states no colour transfer characteristics", bit_depth,
                              primaries_name)
    transfer = transfer_from_h273(trc)
    source = f"{codec} stream colour transfer characteristics {trc} ({h273_transfer_name(trc)})"
    if transfer is None:
        source += ": not a transfer this product reads"
    return StatedTransfer(transfer, source, bit_depth, primaries_name)


def _kr_kb(matrix: int, primaries: int) -> tuple[float, float]:
    if matrix in MATRIX_KR_KB:
        return MATRIX_KR_KB[matrix]
    return MATRIX_KR_KB[9] if primaries == 9 else MATRIX_KR_KB[1]  # unspecified: by the primaries


def _upsample_chroma(c: np.ndarray, height: int, width: int) -> np.ndarray:
    """Chroma plane -> full size, bilinear with H.264/HEVC's default siting (chroma_sample_loc
    0: horizontally co-sited with the even luma columns, vertically between the two rows)."""
    if c.shape[1] < width:  # horizontal subsampling
        nxt = np.concatenate([c[:, 1:], c[:, -1:]], axis=1)
        c = np.stack([c, 0.5 * (c + nxt)], axis=2).reshape(c.shape[0], -1)
    if c.shape[0] < height:  # vertical subsampling
        prev = np.concatenate([c[:1], c[:-1]], axis=0)
        nxt = np.concatenate([c[1:], c[-1:]], axis=0)
        c = np.stack([0.75 * c + 0.25 * prev, 0.75 * c + 0.25 * nxt], axis=1).reshape(-1, c.shape[1])
    return c[:height, :width]


def yuv_planes_to_rgb(y: np.ndarray, cb: np.ndarray, cr: np.ndarray, bits: int, matrix: int,
                      primaries: int, full_range: bool) -> np.ndarray:
    """float32 [H, W, 3] R'G'B' code values in [0, 1] from integer Y'CbCr planes (chroma at any
    of 4:2:0, 4:2:2, 4:4:4), by H.273's equations: limited range Y' = (D / 2^(n-8) - 16) / 219,
    C = (D / 2^(n-8) - 128) / 224; full range Y' = D / (2^n - 1), C = (D - 2^(n-1)) / (2^n - 1).
    (swscale scales 10-bit limited range as 8-bit levels x 1023/255, reading reference white
    940 as 1019/1023; this does not.)"""
    height, width = y.shape
    if full_range:
        top = float(2 ** bits - 1)
        luma = y.astype(np.float32) / top
        to_c = lambda c: (c.astype(np.float32) - 2 ** (bits - 1)) / top  # noqa: E731
    else:
        step = float(2 ** (bits - 8))
        luma = (y.astype(np.float32) / step - 16.0) / 219.0
        to_c = lambda c: (c.astype(np.float32) / step - 128.0) / 224.0  # noqa: E731
    b_diff = _upsample_chroma(to_c(cb), height, width)
    r_diff = _upsample_chroma(to_c(cr), height, width)
    kr, kb = _kr_kb(matrix, primaries)
    r = luma + 2.0 * (1.0 - kr) * r_diff
    b = luma + 2.0 * (1.0 - kb) * b_diff
    g = (luma - kr * r - kb * b) / (1.0 - kr - kb)
    return np.clip(np.stack([r, g, b], axis=-1), 0.0, 1.0).astype(np.float32)


def rgb_to_yuv420_planes(rgb: np.ndarray, bits: int, matrix: int, primaries: int = 1
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """uint16 limited-range Y'CbCr 4:2:0 planes (the inverse of `yuv_planes_to_rgb`) from
    float R'G'B' code values [H, W, 3] in [0, 1] (H, W even), chroma sited as H.264/HEVC's
    default: [1, 2, 1] / 4 horizontally about the even columns, the mean of each row pair."""
    kr, kb = _kr_kb(matrix, primaries)
    x = np.clip(np.asarray(rgb, np.float64), 0.0, 1.0)
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    luma = kr * r + (1.0 - kr - kb) * g + kb * b
    b_diff = (b - luma) / (2.0 * (1.0 - kb))
    r_diff = (r - luma) / (2.0 * (1.0 - kr))
    step = 2.0 ** (bits - 8)
    top = 2 ** bits - 1

    def down(c: np.ndarray) -> np.ndarray:
        c = 0.5 * (c[0::2] + c[1::2])
        left = np.concatenate([c[:, 1:2], c[:, 1:-1:2]], axis=1)  # column 2j - 1 (mirrored at the edge)
        return 0.25 * left + 0.5 * c[:, 0::2] + 0.25 * c[:, 1::2]

    def code(v: np.ndarray, scale: float, offset: float) -> np.ndarray:
        return np.clip(np.round((scale * v + offset) * step), 0, top).astype(np.uint16)

    return code(luma, 219.0, 16.0), code(down(b_diff), 224.0, 128.0), code(down(r_diff), 224.0, 128.0)
