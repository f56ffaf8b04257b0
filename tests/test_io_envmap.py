"""Env map encoding in every format, the tone-mapped PNG preview, loading by content."""
import numpy as np
import pytest

from core.io import MEDIA_TYPES, MediaError, encode_envmap, load_envmap, read_image, save_envmap

GAMMA = 2.4


def _envmap() -> np.ndarray:
    rng = np.random.default_rng(0)
    hdr = (10.0 ** rng.uniform(-6, 6, size=(8, 16, 3))).astype(np.float32)
    hdr[0, 0] = 0.0
    return hdr


@pytest.mark.parametrize("fmt,tolerance", [("exr", 0.0), ("npy", 0.0), ("hdr", 1 / 128)])
def test_lossless_formats_round_trip(tmp_path, fmt, tolerance):
    hdr = _envmap()
    data, media_type = encode_envmap(hdr, fmt)
    assert media_type == MEDIA_TYPES[fmt]
    path = tmp_path / f"map.{fmt}"
    save_envmap(path, hdr)
    for source in (data, path):
        got = load_envmap(source)
        assert got.dtype == np.float32 and got.shape == hdr.shape
        assert np.all(np.abs(got - hdr) <= tolerance * hdr.max(-1, keepdims=True))


def test_png_preview_is_the_papers_tone_map():
    hdr = np.array([[[0.0, 0.25, 1.0], [4.0, 1e-6, 1e6]]], np.float32)
    for ev in (0.0, -2.0, 3.5):
        data, media_type = encode_envmap(hdr, "png", ev=ev)
        assert media_type == "image/png"
        expected = np.clip((2.0**ev * hdr.astype(np.float64)) ** (1 / GAMMA), 0, 1)
        np.testing.assert_allclose(read_image(data), expected, atol=0.5 / 255 + 1e-6)


def test_half_exr_is_smaller_and_close():
    hdr = np.random.default_rng(1).uniform(0, 100, size=(16, 32, 3)).astype(np.float32)
    full, _ = encode_envmap(hdr, "exr")
    half, _ = encode_envmap(hdr, "exr", half=True)
    assert len(half) < len(full)
    np.testing.assert_allclose(load_envmap(half), hdr, rtol=2.0**-10)


def test_load_by_content_not_name(tmp_path):
    data, _ = encode_envmap(_envmap(), "npy")
    path = tmp_path / "looks_like.exr"
    path.write_bytes(data)
    np.testing.assert_array_equal(load_envmap(path), _envmap())


def test_errors_name_the_problem(tmp_path):
    with pytest.raises(MediaError) as err:
        encode_envmap(np.zeros((4, 8)), "exr")
    assert err.value.code == "shape_mismatch" and "(4, 8)" in str(err.value)
    with pytest.raises(MediaError) as err:
        encode_envmap(np.zeros((4, 8, 3)), "jpg")
    assert err.value.code == "unsupported_codec" and "jpg" in str(err.value)
    with pytest.raises(MediaError) as err:
        encode_envmap(np.full((4, 8, 3), np.nan), "npy")
    assert err.value.code == "non_finite"
    with pytest.raises(MediaError) as err:
        load_envmap(b"\x89PNG\r\n\x1a\n rest")
    assert err.value.code == "not_media"
    obj = tmp_path / "obj.npy"
    np.save(obj, np.array([None, 1], dtype=object), allow_pickle=True)
    with pytest.raises(MediaError) as err:
        load_envmap(obj)
    assert err.value.code == "not_media" and "object" in str(err.value)
