"""Radiance RGBE: round trips within RGBE precision, RLE == flat, real Poly Haven files."""
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from core.io import MediaError, MediaLimits, encode_hdr, read_hdr, write_hdr
from core.io.hdr import float_to_rgbe, rgbe_to_float

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "assets" / "sample_panorama.hdr"
SHARED_HDRI = REPO.parent / "shared" / "hdri"
RGBE_STEP = 1.0 / 128.0  # one mantissa step relative to the pixel's largest channel (m >= 128)


def _within_rgbe_precision(decoded, original):
    peak = original.max(axis=-1, keepdims=True)
    return np.all(np.abs(decoded - original) <= RGBE_STEP * peak + 1e-37)


def test_round_trip_spanning_twelve_decades(tmp_path):
    rng = np.random.default_rng(0)
    a = (10.0 ** rng.uniform(-6, 6, size=(16, 40, 3))).astype(np.float32)
    a[0, :8] = 5.0  # runs long enough to be run-length encoded
    a[1, 0] = 0.0
    b = read_hdr(write_hdr(tmp_path / "a.hdr", a))
    assert b.dtype == np.float32 and b.shape == a.shape
    assert _within_rgbe_precision(b, a)
    assert np.all(b[1, 0] == 0.0)


def test_rle_and_flat_encodings_decode_identically():
    a = np.random.default_rng(1).gamma(0.5, 2.0, size=(12, 64, 3)).astype(np.float32)
    a[:, 10:50] = [0.25, 0.5, 1.0]  # long runs
    rle, flat = encode_hdr(a, rle=True), encode_hdr(a, rle=False)
    assert len(rle) < len(flat)
    np.testing.assert_array_equal(read_hdr(rle), read_hdr(flat))


def test_our_files_read_identically_by_opencv(tmp_path):
    a = np.random.default_rng(2).gamma(0.5, 3.0, size=(10, 33, 3)).astype(np.float32)
    path = write_hdr(tmp_path / "x.hdr", a)
    theirs = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1]
    # cv2 decodes m * 2^(e-136), Radiance (m + 0.5) * 2^(e-136): half a step apart at most
    assert _within_rgbe_precision(theirs, read_hdr(path))


def _real_panoramas():
    files = sorted(SHARED_HDRI.glob("*.hdr"))[:2] if SHARED_HDRI.is_dir() else []
    return [SAMPLE] + files


@pytest.mark.parametrize("path", _real_panoramas(), ids=lambda p: p.name)
def test_real_poly_haven_file_matches_opencv(path):
    ours = read_hdr(path)
    theirs = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float32)
    assert ours.shape == theirs.shape and ours.shape[1] == 2 * ours.shape[0]
    assert np.isfinite(ours).all() and (ours > 0).all()
    peak = theirs.max(axis=-1, keepdims=True)
    assert np.all(np.abs(ours - theirs) <= 0.5 * RGBE_STEP * peak + 1e-30)


def test_real_file_re_encodes_bit_exactly():
    a = read_hdr(SAMPLE)
    np.testing.assert_array_equal(read_hdr(encode_hdr(a)), a)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.0, 1e30, allow_nan=False), min_size=3, max_size=3))
def test_rgbe_codec_property(rgb):
    a = np.array(rgb, np.float32)[None]
    assert _within_rgbe_precision(rgbe_to_float(float_to_rgbe(a)), a)


def test_bottom_up_files_are_flipped():
    a = np.arange(2 * 8 * 3, dtype=np.float32).reshape(2, 8, 3) + 1
    data = encode_hdr(a, rle=False).replace(b"-Y 2 +X 8", b"+Y 2 +X 8")
    assert read_hdr(data)[0, 0, 0] == pytest.approx(read_hdr(encode_hdr(a))[1, 0, 0])


def test_corrupt_and_unsupported_inputs():
    data = encode_hdr(np.random.default_rng(3).random((20, 32, 3), dtype=np.float32))
    cases = [
        (data[: len(data) // 2], "truncated"),
        (data.replace(b"32-bit_rle_rgbe", b"32-bit_rle_xyze"), "unsupported_codec"),
        (data.replace(b"-Y 20 +X 32", b"+X 32 -Y 20"), "unsupported_codec"),
        (b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n", "truncated"),
        (b"P6 not radiance", "not_media"),
        (b"", "empty"),
    ]
    for blob, code in cases:
        with pytest.raises(MediaError) as err:
            read_hdr(blob)
        assert err.value.code == code, blob[:40]
    with pytest.raises(MediaError) as err:
        read_hdr(data, MediaLimits(max_pixels=100))
    assert err.value.code == "too_many_pixels"


def test_write_refuses_non_finite_and_clamps_negative():
    with pytest.raises(MediaError) as err:
        encode_hdr(np.full((2, 8, 3), np.nan, np.float32))
    assert err.value.code == "non_finite"
    with pytest.warns(UserWarning, match="negative"):
        b = read_hdr(encode_hdr(np.array([[[-1.0, 2.0, 3.0]]], np.float32)))
    assert b[0, 0, 0] < 2.0 * RGBE_STEP * 3.0 and b[0, 0, 2] == pytest.approx(3.0, rel=RGBE_STEP)
