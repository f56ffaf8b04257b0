"""LDR image decoding with limits, and PNG 8/16-bit writing."""
import io
import struct
import zlib

import cv2
import numpy as np
import pytest
from PIL import Image, ImageFile

from core.io import MediaError, MediaLimits, encode_png, encode_png16, read_image, read_png16, write_png, write_png16


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def bomb_png(width: int, height: int) -> bytes:
    """A tiny, valid-looking PNG whose header declares width x height RGB pixels."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    idat = zlib.compress(bytes(64 * 1024), 9)  # far less data than declared
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


@pytest.fixture
def no_decoding(monkeypatch):
    """Fail the test if any pixel decoder runs."""

    def forbidden(*args, **kwargs):
        raise AssertionError("pixel data was decoded")

    monkeypatch.setattr(ImageFile.ImageFile, "load", forbidden)
    monkeypatch.setattr(cv2, "imdecode", forbidden)


def test_png8_round_trip_is_exact_for_uint8(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 256, size=(17, 23, 3), dtype=np.uint8)
    got = read_image(write_png(tmp_path / "a.png", rgb))
    assert got.dtype == np.float32 and got.shape == (17, 23, 3)
    np.testing.assert_array_equal(np.round(got * 255).astype(np.uint8), rgb)


def test_png8_float_input_is_rounded_and_clipped():
    ldr = np.array([[[0.0, 0.5, 1.0], [-0.2, 1.7, 0.25]]], np.float32)
    got = read_image(encode_png(ldr))
    np.testing.assert_allclose(got, np.clip(ldr, 0, 1), atol=0.5 / 255 + 1e-7)


def test_png16_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 65536, size=(9, 11, 3), dtype=np.uint16)
    grey = rng.integers(0, 65536, size=(9, 11), dtype=np.uint16)
    np.testing.assert_array_equal(read_png16(write_png16(tmp_path / "c.png", rgb)), rgb)
    np.testing.assert_array_equal(read_png16(write_png16(tmp_path / "g.png", grey)), grey)
    # read_image keeps the 16-bit precision (Pillow alone would truncate colour to 8 bits)
    np.testing.assert_allclose(read_image(tmp_path / "c.png"), rgb / 65535.0, atol=1e-6)


def test_grey_is_expanded_and_alpha_dropped():
    grey = np.array([[0, 128, 255]], np.uint8)
    np.testing.assert_allclose(read_image(encode_png(grey))[0, 1], [128 / 255] * 3, rtol=1e-6)
    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 200, 0  # fully transparent red: colour kept, alpha ignored
    got = read_image(encode_png(rgba))
    assert got.shape == (2, 2, 3) and np.allclose(got[..., 0], 200 / 255)


@pytest.mark.parametrize("fmt", ["JPEG", "WEBP", "BMP", "TIFF"])
def test_other_formats_decode_close_to_source(fmt):
    ramp = np.linspace(0, 255, 32, dtype=np.float32)
    rgb = np.stack(np.broadcast_arrays(ramp[None, :], ramp[:, None], np.full((32, 32), 77.0)), -1).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format=fmt, quality=95)
    got = read_image(buf.getvalue())
    assert got.shape == (32, 32, 3)
    assert np.abs(got * 255 - rgb).mean() < 3.0


def test_decompression_bomb_refused_before_decoding(no_decoding):
    data = bomb_png(20_000, 20_000)
    assert len(data) < 1000
    with pytest.raises(MediaError) as err:
        read_image(data)  # default limit: 4096 x 4096
    assert err.value.code == "too_many_pixels"
    with pytest.raises(MediaError) as err:
        read_image(bomb_png(100, 101), MediaLimits(max_pixels=100 * 100))
    assert err.value.code == "too_many_pixels" and "100x101" in str(err.value)


def test_corrupt_inputs_have_specific_codes(tmp_path):
    ramp = np.random.default_rng(2).integers(0, 256, size=(64, 64, 3), dtype=np.uint8)
    png = encode_png(ramp)
    cases = [
        (png[: len(png) // 2], "truncated"),
        (png[:30], "truncated"),
        (b"", "empty"),
        (np.random.default_rng(3).bytes(4096), "not_media"),
    ]
    for blob, code in cases:
        with pytest.raises(MediaError) as err:
            read_image(blob)
        assert err.value.code == code
    with pytest.raises(MediaError) as err:
        read_image(png, MediaLimits(max_bytes=len(png) - 1))
    assert err.value.code == "too_large"
    with pytest.raises(MediaError) as err:
        read_image(tmp_path / "missing.png")
    assert err.value.code == "not_found"
    with pytest.raises(MediaError) as err:
        read_image(tmp_path)  # a directory
    assert err.value.code == "not_found"


def test_16bit_grey_tiff_and_float_tiff():
    grey = np.array([[0, 32768, 65535]], np.uint16)
    buf = io.BytesIO()
    Image.fromarray(grey).save(buf, format="TIFF")
    np.testing.assert_allclose(read_image(buf.getvalue())[0, :, 0], grey[0] / 65535.0, rtol=1e-6)
    buf = io.BytesIO()
    Image.fromarray(np.full((2, 2), 3.5, np.float32)).save(buf, format="TIFF")
    with pytest.raises(MediaError) as err:
        read_image(buf.getvalue())
    assert err.value.code == "unsupported_codec"


def test_read_by_content_not_by_name(tmp_path):
    path = tmp_path / "video.mp4"
    path.write_bytes(encode_png(np.full((4, 4, 3), 0.5, np.float32)))
    assert read_image(path).shape == (4, 4, 3)


def test_png16_refuses_8bit_and_floats():
    with pytest.raises(MediaError) as err:
        read_png16(encode_png(np.zeros((3, 3), np.uint8)))
    assert err.value.code == "wrong_bit_depth" and "8-bit" in str(err.value)
    with pytest.raises(MediaError):
        encode_png16(np.zeros((3, 3), np.float32))
    with pytest.raises(MediaError):
        encode_png16(np.full((3, 3), 70000, np.int64))
    with pytest.raises(MediaError) as err:
        encode_png(np.full((2, 2, 3), np.nan, np.float32))
    assert err.value.code == "non_finite"
