"""Depth files: npz/npy (no pickle), EXR, 16-bit PNG millimetres; invalid -> NaN."""
import io
import zipfile

import numpy as np
import pytest

from core.io import (
    MediaError,
    MediaLimits,
    encode_depth_png16,
    encode_exr,
    encode_png,
    encode_png16,
    read_depth,
    write_depth_npz,
)


def _npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def test_png16_millimetres_become_metres_with_zero_as_nan(tmp_path):
    mm = np.array([[0, 1, 1500], [65535, 2000, 0]], np.uint16)
    path = tmp_path / "depth.png"
    path.write_bytes(encode_png16(mm))
    d = read_depth(path)
    assert d.dtype == np.float32 and d.shape == (2, 3)
    assert np.isnan(d[0, 0]) and np.isnan(d[1, 2])
    np.testing.assert_allclose(d[[0, 0, 1, 1], [1, 2, 0, 1]], [0.001, 1.5, 65.535, 2.0], rtol=1e-6)


def test_png16_depth_writer_round_trips_to_the_millimetre():
    d = np.array([[0.5, np.nan, 3.1234], [-1.0, 65.5, 0.0]], np.float32)
    got = read_depth(encode_depth_png16(d))
    valid = np.isfinite(d) & (d > 0)
    np.testing.assert_array_equal(np.isnan(got), ~valid)
    assert np.all(np.abs(got[valid] - d[valid]) <= 0.0005 + 1e-6)
    with pytest.raises(MediaError) as err:
        encode_depth_png16(np.full((2, 2), 70.0))
    assert err.value.code == "invalid_depth" and "65.535" in str(err.value)


def test_8bit_and_colour_png_depth_refused():
    with pytest.raises(MediaError) as err:
        read_depth(encode_png(np.full((4, 4), 100, np.uint8)))
    assert err.value.code == "wrong_bit_depth" and "16-bit" in str(err.value)
    with pytest.raises(MediaError) as err:
        read_depth(encode_png16(np.ones((4, 4, 3), np.uint16)))
    assert err.value.code == "invalid_depth" and "single-channel" in str(err.value)


def test_npz_round_trip_and_invalid_values_become_nan(tmp_path):
    d = np.random.default_rng(0).uniform(0.1, 10, size=(3, 5, 7)).astype(np.float32)
    d[0, 0, 0], d[1, 1, 1], d[2, 2, 2], d[0, 4, 6] = 0.0, -2.0, np.inf, np.nan
    got = read_depth(write_depth_npz(tmp_path / "d.npz", d))
    assert got.shape == (3, 5, 7)
    invalid = ~(np.isfinite(d) & (d > 0))
    assert invalid.sum() == 4
    np.testing.assert_array_equal(np.isnan(got), invalid)
    np.testing.assert_array_equal(got[~invalid], d[~invalid])


def test_float64_overflowing_float32_is_invalid_not_inf():
    got = read_depth(_npz(depth=np.array([[1e300, 2.0]], np.float64)))
    assert np.isnan(got[0, 0]) and got[0, 1] == 2.0


def test_npz_with_pickled_objects_is_refused():
    for blob in (_npz(depth=np.array([{"x": 1}, None], dtype=object)), _npz(depth=np.array([[1, "a"]], dtype=object))):
        with pytest.raises(MediaError) as err:
            read_depth(blob)
        assert err.value.code == "invalid_depth" and "object" in str(err.value)


def test_npz_other_keys_and_bad_arrays_refused():
    cases = [
        (_npz(depth=np.ones((2, 2)), extra=np.ones(1)), "invalid_depth"),
        (_npz(disparity=np.ones((2, 2))), "invalid_depth"),
        (_npz(depth=np.ones(5)), "invalid_depth"),
        (_npz(depth=np.ones((2, 2), bool)), "invalid_depth"),
        (_npz(depth=np.ones((2, 2)))[:40], "truncated"),
        (b"", "empty"),
        (b"just text", "not_media"),
    ]
    for blob, code in cases:
        with pytest.raises(MediaError) as err:
            read_depth(blob)
        assert err.value.code == code


def test_npz_zip_bomb_refused_from_array_header(monkeypatch):
    buf = io.BytesIO()
    np.savez_compressed(buf, depth=np.zeros((5000, 5000), np.float32))  # 100 MB inflates from ~100 KB
    data = buf.getvalue()
    assert len(data) < 1_000_000

    def forbidden(*args, **kwargs):
        raise AssertionError("array data was decompressed")

    monkeypatch.setattr(np, "load", forbidden)
    with pytest.raises(MediaError) as err:
        read_depth(data, MediaLimits(max_pixels=1000 * 1000))
    assert err.value.code == "too_many_pixels"


def test_frame_limit_applies_to_depth_sequences():
    with pytest.raises(MediaError) as err:
        read_depth(_npz(depth=np.ones((5, 2, 2), np.float32)), MediaLimits(max_frames=4))
    assert err.value.code == "too_many_frames"


def test_exr_prefers_z_channel_then_first():
    z = np.full((3, 4), 2.5, np.float32)
    other = np.zeros((3, 4, 2), np.float32)
    both = np.concatenate([other, z[..., None]], -1)
    np.testing.assert_array_equal(read_depth(encode_exr(both, channel_names=["A", "B", "Z"])), z)
    np.testing.assert_array_equal(read_depth(encode_exr(z, channel_names=["distance"])), z)


def test_format_chosen_by_content_not_name(tmp_path):
    path = tmp_path / "depth.png"  # actually an npz
    path.write_bytes(_npz(depth=np.full((2, 3), 4.0)))
    np.testing.assert_array_equal(read_depth(path), np.full((2, 3), 4.0, np.float32))
    assert zipfile.is_zipfile(path)
