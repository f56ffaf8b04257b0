"""OpenEXR round trips (float32 and half), overflow policy, corrupt input."""
import warnings

import numpy as np
import pytest

from core.io import HalfOverflowWarning, MediaError, MediaLimits, encode_exr, read_exr, read_exr_channels, write_exr

HALF_EPS = 2.0**-10  # half has 10 explicit mantissa bits


def _hard_map() -> np.ndarray:
    rng = np.random.default_rng(0)
    a = rng.uniform(0.0, 2.0, size=(9, 14, 3)).astype(np.float32)
    a[0, 0] = 1e-6
    a[0, 1] = 6e4
    a[1, 0] = [0.0, 1e-6, 6e4]
    return a


def test_float32_round_trip_is_exact(tmp_path):
    a = _hard_map()
    path = write_exr(tmp_path / "a.exr", a)
    b = read_exr(path)
    assert b.dtype == np.float32 and b.shape == a.shape
    np.testing.assert_array_equal(b, a)


def test_half_round_trip_within_half_precision(tmp_path):
    a = _hard_map()
    b = read_exr(write_exr(tmp_path / "h.exr", a, half=True))
    normal = a >= 2.0**-14  # smallest normal half
    assert np.all(np.abs(b - a)[normal] <= HALF_EPS * a[normal])
    # 1e-6 is a half subnormal: absolute spacing 2^-24
    assert abs(b[0, 0, 0] - 1e-6) <= 2.0**-24
    assert b[0, 0, 0] > 0 and abs(b[0, 1, 0] - 6e4) <= 6e4 * HALF_EPS


def test_half_overflow_clamps_with_warning_or_refuses():
    a = np.array([[[1e6, -1e6, 1.0]]], np.float32)
    with pytest.warns(HalfOverflowWarning):
        b = read_exr(encode_exr(a, half=True))
    np.testing.assert_array_equal(b[0, 0], [65504.0, -65504.0, 1.0])
    with pytest.raises(MediaError) as err:
        encode_exr(a, half=True, on_overflow="error")
    assert err.value.code == "non_finite"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(read_exr(encode_exr(a)), a)  # float32 needs no clamp


def test_non_finite_refused_unless_allowed():
    a = np.ones((2, 3, 3), np.float32)
    a[1, 2, 0] = np.nan
    a[0, 0, 1] = np.inf
    with pytest.raises(MediaError) as err:
        encode_exr(a)
    assert err.value.code == "non_finite" and "2 NaN/inf" in str(err.value)
    b = read_exr(encode_exr(a, allow_non_finite=True))
    assert np.isnan(b[1, 2, 0]) and np.isposinf(b[0, 0, 1])


def test_single_channel_named_and_read_back():
    z = np.arange(12, dtype=np.float32).reshape(3, 4)
    channels = read_exr_channels(encode_exr(z, channel_names=["Z"]))
    assert list(channels) == ["Z"]
    np.testing.assert_array_equal(channels["Z"], z)
    assert read_exr(encode_exr(z)).shape == (3, 4, 1)


def test_rgba_drops_alpha_and_keeps_rgb_order():
    a = np.stack([np.full((2, 2), v, np.float32) for v in (1, 2, 3, 4)], -1)
    np.testing.assert_array_equal(read_exr(encode_exr(a))[0, 0], [1, 2, 3])


def test_corrupt_inputs_have_specific_codes():
    data = encode_exr(np.random.default_rng(1).random((64, 80, 3), dtype=np.float32))
    for cut, code in ((len(data) // 2, "truncated"), (20, "truncated")):
        with pytest.raises(MediaError) as err:
            read_exr(data[:cut])
        assert err.value.code == code
    for blob, code in ((b"", "empty"), (b"definitely not an exr file", "not_media")):
        with pytest.raises(MediaError) as err:
            read_exr(blob)
        assert err.value.code == code


def test_pixel_limit_checked_from_header():
    data = encode_exr(np.zeros((40, 50, 3), np.float32))
    with pytest.raises(MediaError) as err:
        read_exr(data, MediaLimits(max_pixels=40 * 50 - 1))
    assert err.value.code == "too_many_pixels" and "40" in str(err.value)


def test_bad_shapes_refused():
    for bad in (np.zeros((2, 2, 2, 2)), np.zeros((0, 3, 3)), np.array([["a"]])):
        with pytest.raises(MediaError) as err:
            encode_exr(bad)
        assert err.value.code == "shape_mismatch"
