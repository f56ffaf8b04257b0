"""What files state about their transfer (core.io.colour.StatedTransfer), read from real files
written here, and 10/12-bit HDR video decoded to code values without passing through 8 bits."""
from __future__ import annotations

import io
import struct
import zlib

import av
import cv2
import numpy as np
import pytest
from PIL import ExifTags, Image, ImageCms, PngImagePlugin

from core.io import StatedTransfer, encode_png, encode_png16, probe_image, probe_video, read_video, write_video
from core.io.images import decode_image
from test_io_metadata import P3_D50, matrix_trc_profile

SIGNATURE = b"\x89PNG\r\n\x1a\n"


def chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def patched_after_ihdr(png: bytes, *chunks: bytes) -> bytes:
    """A PNG with `chunks` spliced in right after its IHDR (8-byte signature + 25-byte IHDR)."""
    assert png[:8] == SIGNATURE and png[12:16] == b"IHDR"
    return png[:33] + b"".join(chunks) + png[33:]


def pillow_png(a: np.ndarray, chunks: dict[bytes, bytes] | None = None, **kw) -> bytes:
    info = PngImagePlugin.PngInfo()
    for kind, payload in (chunks or {}).items():
        info.add(kind, payload)
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, "PNG", pnginfo=info, **kw)
    return buf.getvalue()


def jpeg(a: np.ndarray, **kw) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, "JPEG", quality=95, **kw)
    return buf.getvalue()


def ramp(h: int = 8, w: int = 12) -> np.ndarray:
    a = np.zeros((h, w, 3), np.uint8)
    a[..., 0] = np.arange(w)[None] * 20
    a[..., 1] = np.arange(h)[:, None] * 30
    a[..., 2] = 90
    return a


SRGB_ICC = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
GAMMA_22 = struct.pack(">I", 45455)


# ---------------------------------------------------------------------------------------
# PNG
# ---------------------------------------------------------------------------------------
def test_png_gama_chunk_states_a_power_curve():
    a = ramp()
    stated = decode_image(pillow_png(a, {b"gAMA": GAMMA_22})).stated_transfer
    assert str(stated.transfer) == "gamma:2.2" and stated.source == "PNG gAMA chunk 0.45455"
    assert stated.bit_depth == 8 and stated.primaries is None
    linear = decode_image(pillow_png(a, {b"gAMA": struct.pack(">I", 100000)})).stated_transfer
    assert str(linear.transfer) == "linear" and linear.source == "PNG gAMA chunk 1"
    nonsense = decode_image(pillow_png(a, {b"gAMA": struct.pack(">I", 10000)})).stated_transfer  # gamma 10
    assert nonsense.transfer is None and "outside" in nonsense.source


def test_png_srgb_chunk_wins_over_its_companion_gama():
    decoded = decode_image(pillow_png(ramp(), {b"sRGB": b"\x00", b"gAMA": GAMMA_22}))
    assert decoded.stated_transfer == StatedTransfer(decoded.stated_transfer.transfer, "PNG sRGB chunk", 8, "bt709")
    assert str(decoded.stated_transfer.transfer) == "srgb"
    np.testing.assert_array_equal(np.round(decoded.pixels * 255).astype(np.uint8), ramp())  # values untouched


def test_png_cicp_chunk_patched_in_wins_over_srgb_and_gama():
    a = ramp()
    plain = pillow_png(a, {b"sRGB": b"\x00", b"gAMA": GAMMA_22})
    hlg = patched_after_ihdr(plain, chunk(b"cICP", bytes((9, 18, 0, 1))))  # BT.2020, HLG, RGB, full range
    probe_image(hlg)  # Pillow's verify: the chunk's CRC holds
    decoded = decode_image(hlg)
    stated = decoded.stated_transfer
    assert str(stated.transfer) == "hlg" and stated.primaries == "bt2020" and stated.bit_depth == 8
    assert stated.source.startswith("PNG cICP chunk (transfer 18")
    np.testing.assert_array_equal(np.round(decoded.pixels * 255).astype(np.uint8), a)
    unknown = decode_image(patched_after_ihdr(plain, chunk(b"cICP", bytes((1, 17, 0, 1))))).stated_transfer
    assert unknown.transfer is None and "transfer 17" in unknown.source  # SMPTE 428: not read, said so


def test_16_bit_png_with_cicp_pq_reports_16_bits():
    rgb = (np.arange(4 * 6 * 3).reshape(4, 6, 3) * 900).astype(np.uint16)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    decoded = decode_image(patched_after_ihdr(buf.tobytes(), chunk(b"cICP", bytes((9, 16, 0, 1)))))
    stated = decoded.stated_transfer
    assert (str(stated.transfer), stated.bit_depth, stated.primaries) == ("pq", 16, "bt2020")
    np.testing.assert_array_equal(np.round(decoded.pixels * 65535).astype(np.uint16), rgb)


def test_png_icc_profiles_win_over_gama():
    a = ramp()
    srgb = decode_image(pillow_png(a, {b"gAMA": GAMMA_22}, icc_profile=SRGB_ICC)).stated_transfer
    assert str(srgb.transfer) == "srgb" and srgb.source == "PNG ICC profile 'sRGB built-in'"
    p3 = matrix_trc_profile(P3_D50, 2.2, "Display P3 test")
    converted = decode_image(pillow_png(a, {b"gAMA": GAMMA_22}, icc_profile=p3)).stated_transfer
    assert str(converted.transfer) == "srgb" and converted.primaries == "bt709"
    assert converted.source == "ICC profile 'Display P3 test' converted to sRGB"


def test_untagged_png_states_nothing():
    buf = io.BytesIO()
    Image.fromarray(ramp()).save(buf, "PNG")
    stated = decode_image(buf.getvalue()).stated_transfer
    assert stated.transfer is None and stated.source.startswith("PNG states no transfer") and stated.bit_depth == 8


# ---------------------------------------------------------------------------------------
# JPEG
# ---------------------------------------------------------------------------------------
def test_jpeg_with_an_srgb_icc_profile():
    stated = decode_image(jpeg(ramp(), icc_profile=SRGB_ICC)).stated_transfer
    assert str(stated.transfer) == "srgb" and stated.source == "JPEG ICC profile 'sRGB built-in'"
    assert stated.bit_depth == 8 and stated.primaries == "bt709"


def test_jpeg_exif_color_space():
    exif = Image.Exif()
    exif.get_ifd(ExifTags.IFD.Exif)[0xA001] = 1
    stated = decode_image(jpeg(ramp(), exif=exif)).stated_transfer
    assert str(stated.transfer) == "srgb" and stated.source == "EXIF ColorSpace sRGB"
    exif.get_ifd(ExifTags.IFD.Exif)[0xA001] = 0xFFFF  # "uncalibrated" (Adobe RGB cameras) states nothing
    uncalibrated = decode_image(jpeg(ramp(), exif=exif)).stated_transfer
    assert uncalibrated.transfer is None and "uncalibrated" in uncalibrated.source


def test_untagged_jpeg_states_nothing():
    stated = decode_image(jpeg(ramp())).stated_transfer
    assert stated.transfer is None and stated.source.startswith("JPEG states no transfer")
    assert stated.bit_depth == 8 and stated.primaries is None


# ---------------------------------------------------------------------------------------
# PNG writers
# ---------------------------------------------------------------------------------------
def test_our_pngs_state_the_engines_convention_by_default():
    png = encode_png(np.full((3, 4, 3), 0.5, np.float32))
    assert png[33:49] == chunk(b"gAMA", struct.pack(">I", 41667))  # right after IHDR, CRC included
    stated = decode_image(png).stated_transfer
    assert stated.transfer.is_convention and str(stated.transfer) == "gamma:2.4"


@pytest.mark.parametrize("transfer,chunk_type,primaries", [
    ("srgb", b"sRGB", "bt709"), ("gamma:2.2", b"gAMA", None), ("linear", b"gAMA", None),
    ("gamma:1.8", b"gAMA", None), ("hlg", b"cICP", "bt709"), ("pq", b"cICP", "bt709"),
    ("rec709", b"cICP", "bt709"),
])
def test_png_writers_state_what_they_are_asked_to(transfer, chunk_type, primaries):
    a = np.random.default_rng(1).random((5, 7, 3)).astype(np.float32)
    png = encode_png(a, transfer=transfer)
    assert png[37:41] == chunk_type
    probe_image(png)  # CRCs hold
    decoded = decode_image(png)
    assert str(decoded.stated_transfer.transfer) == transfer and decoded.stated_transfer.primaries == primaries
    np.testing.assert_array_equal(np.round(decoded.pixels * 255), np.round(a * 255))  # values as given
    png16 = encode_png16(np.round(a * 65535).astype(np.uint16), transfer=transfer)
    assert str(decode_image(png16).stated_transfer.transfer) == transfer


def test_16_bit_pngs_are_data_unless_told():
    png = encode_png16(np.full((4, 4), 1500, np.uint16))  # depth in millimetres: no colour chunk
    assert not any(kind in png for kind in (b"gAMA", b"sRGB", b"cICP", b"iCCP"))
    assert decode_image(png).stated_transfer.transfer is None


def test_a_bad_transfer_is_refused():
    with pytest.raises(ValueError, match="transfer"):
        encode_png(np.zeros((2, 2, 3), np.float32), transfer="gamma:9")


# ---------------------------------------------------------------------------------------
# Video
# ---------------------------------------------------------------------------------------
P = 32  # patch size: flat patches, compared away from their edges (chroma subsampling, ringing)


def patches(seed: int = 0, h: int = 64, w: int = 128) -> np.ndarray:
    """Flat coloured patches whose values lie half-way between 8-bit codes."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w, 3), np.float32)
    for r in range(0, h, P):
        for c in range(0, w, P):
            img[r:r + P, c:c + P] = (rng.integers(20, 235, 3) + 0.5) / 255.0
    return img


def flat_error(decoded: np.ndarray, truth: np.ndarray, margin: int = 8) -> float:
    """Largest difference in units of 1/1023 over the patches' interiors."""
    h, w = truth.shape[:2]
    return max(float(np.abs(decoded[r + margin:r + P - margin, c + margin:c + P - margin]
                            - truth[r + margin:r + P - margin, c + margin:c + P - margin]).max())
               for r in range(0, h, P) for c in range(0, w, P)) * 1023.0


@pytest.mark.parametrize("codec,name", [("libx264", "H.264"), ("libx265", "HEVC")])
@pytest.mark.parametrize("transfer,code,trc_name", [("hlg", 18, "arib-std-b67"), ("pq", 16, "smpte2084")])
def test_10_bit_hdr_video_keeps_its_codes(tmp_path, codec, name, transfer, code, trc_name):
    img = patches()
    frames = np.stack([img, img[::-1].copy()])
    path = write_video(tmp_path / "hdr.mp4", frames, 10.0, crf=6, transfer=transfer, bit_depth=10,
                       primaries="bt2020", codec=codec)
    with av.open(str(path)) as container:  # the stream says it (what other players read)
        ctx = container.streams.video[0].codec_context
        assert (ctx.pix_fmt, ctx.color_trc, ctx.color_primaries, ctx.colorspace) == ("yuv420p10le", code, 9, 9)
    video = read_video(path)
    stated = video.stated_transfer
    assert str(stated.transfer) == transfer and stated.bit_depth == 10 and stated.primaries == "bt2020"
    assert stated.source == f"{name} stream colour transfer characteristics {code} ({trc_name})"
    assert probe_video(path).stated_transfer == stated
    assert video.frames.dtype == np.float32 and video.frames.shape == frames.shape
    ten = max(flat_error(video.frames[k], frames[k]) for k in range(2))
    assert ten <= 2.5, ten  # within ~2 codes of 1023
    eight = flat_error(read_video(write_video(tmp_path / "sdr.mp4", frames, 10.0, crf=6, transfer=transfer,
                                              primaries="bt2020", codec=codec)).frames[0], img)
    assert eight >= 2.0 * ten and eight > 4.0, (eight, ten)  # 8 bits are clearly coarser


@pytest.mark.parametrize("full_range", [False, True])
def test_10_bit_reference_levels_decode_by_the_standard(tmp_path, full_range):
    """Y'CbCr written by hand (H.273's equations, BT.2020 NCL), losslessly encoded: reference
    white (940 limited, 1023 full) decodes to 1, black to 0 and a colour to its R'G'B', which
    swscale's rgb48le does not do (it reads 940 as 1019/1023)."""
    kr, kb = 0.2627, 0.0593
    colours = np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.75, 0.25, 0.5], [0.1, 0.6, 0.9]])
    h, w = 16, 16 * len(colours)
    planes = [np.zeros((h, w), np.uint16), np.zeros((h // 2, w // 2), np.uint16), np.zeros((h // 2, w // 2), np.uint16)]
    for k, (r, g, b) in enumerate(colours):
        y = kr * r + (1 - kr - kb) * g + kb * b
        cb, cr = (b - y) / (2 * (1 - kb)), (r - y) / (2 * (1 - kr))
        if full_range:
            codes = (round(1023 * y), round(1023 * cb + 512), round(1023 * cr + 512))
        else:
            codes = (round(4 * (219 * y + 16)), round(4 * (224 * cb + 128)), round(4 * (224 * cr + 128)))
        planes[0][:, 16 * k:16 * k + 16] = codes[0]
        planes[1][:, 8 * k:8 * k + 8] = codes[1]
        planes[2][:, 8 * k:8 * k + 8] = codes[2]
    buf = io.BytesIO()
    with av.open(buf, "w", format="mp4") as container:
        stream = container.add_stream("libx265", rate=10)
        stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p10le"
        ctx = stream.codec_context
        ctx.color_trc, ctx.color_primaries, ctx.colorspace, ctx.color_range = 18, 9, 9, 2 if full_range else 1
        stream.options = {"x265-params": "lossless=1:log-level=error:bframes=0"}
        frame = av.VideoFrame(w, h, "yuv420p10le")
        for plane, values in zip(frame.planes, planes):
            padded = np.zeros((plane.height, plane.line_size // 2), np.uint16)
            padded[:, : values.shape[1]] = values
            plane.update(padded.tobytes())
        for packet in [*stream.encode(frame), *stream.encode()]:
            packet.dts = packet.pts  # no B-frames; this libx265 wrapper can leave DTS unset (core.io.video)
            container.mux(packet)
    video = read_video(buf.getvalue())
    got = video.frames[0, 8, 8::16]  # each patch's centre
    np.testing.assert_allclose(got, colours, atol=1.5 / 1023)
    assert video.stated_transfer.bit_depth == 10 and str(video.stated_transfer.transfer) == "hlg"


def test_8_bit_h264_tagged_bt709_keeps_the_8_bit_path(tmp_path):
    img = patches(seed=2, h=32, w=64)
    path = write_video(tmp_path / "sdr.mp4", np.stack([img, img]), 10.0, transfer="rec709")
    video = read_video(path)
    stated = video.stated_transfer
    assert str(stated.transfer) == "rec709" and stated.bit_depth == 8 and stated.primaries == "bt709"
    assert stated.source == "H.264 stream colour transfer characteristics 1 (bt709)"
    with av.open(str(path)) as container:
        first = next(container.decode(video=0))
        assert (first.format.name, first.color_trc, first.colorspace) == ("yuv420p", 1, 1)
        expected = first.to_ndarray(format="rgb24").astype(np.float32) / np.float32(255.0)
    np.testing.assert_array_equal(video.frames[0], expected)  # today's rgb24 / 255, exactly
    assert flat_error(video.frames[0], img) < 16.0  # and the BT.709 matrix it was written with


def test_untagged_8_bit_video_is_written_as_before_and_states_nothing(tmp_path):
    path = write_video(tmp_path / "plain.mp4", np.stack([patches(seed=3, h=32, w=64)] * 2), 10.0)
    with av.open(str(path)) as container:
        ctx = container.streams.video[0].codec_context
        assert (ctx.color_trc, ctx.color_primaries, ctx.colorspace) == (2, 2, 2)
    stated = read_video(path).stated_transfer
    assert stated.transfer is None and stated.source == "H.264 stream states no colour transfer characteristics"
    assert stated.bit_depth == 8


def test_12_bit_hevc_and_gamma_24_without_a_code(tmp_path):
    img = patches(seed=4, h=32, w=64)
    path = write_video(tmp_path / "deep.mp4", np.stack([img, img]), 10.0, crf=6, transfer="gamma:2.4",
                       bit_depth=12, codec="libx265")
    video = read_video(path)
    assert video.stated_transfer.bit_depth == 12 and video.stated_transfer.transfer is None  # H.273 has no 2.4
    assert flat_error(video.frames[0], img) <= 2.5


def test_write_video_refuses_what_it_cannot_write(tmp_path):
    frames = np.zeros((1, 8, 8, 3), np.float32)
    with pytest.raises(ValueError, match="10-bit"):
        write_video(tmp_path / "a.mp4", frames, 10.0, bit_depth=10, codec="mpeg4")
    with pytest.raises(ValueError, match="bit_depth"):
        write_video(tmp_path / "a.mp4", frames, 10.0, bit_depth=9)
    with pytest.raises(ValueError, match="primaries"):
        write_video(tmp_path / "a.mp4", frames, 10.0, primaries="p3")
    with pytest.raises(ValueError, match="transfer"):
        write_video(tmp_path / "a.mp4", frames, 10.0, transfer="log")
