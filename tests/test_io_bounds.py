"""Issue 45 at the library level (core.io, core.capture.probe: what the API's upload check and the
worker both run): every size a file declares is checked before anything is allocated, and what
the worker would refuse, the probe refuses, with the same code, naming the field and its range.

Memory bounds here are loose guards ("nothing proportional to the declared size"), measured
with tracemalloc; the measured costs are in bench/upload_cost.py."""
from __future__ import annotations

import io
import time
import tracemalloc
import zipfile

import numpy as np
import pytest

import bench.hostile_inputs as h
from core.capture.probe import probe_capture
from core.io import MediaError, MediaLimits, probe_depth, probe_video, read_depth, read_video, select_frame_indices
from core.io.archive import ArchiveError, ZipFiles
from core.io.jsonbounds import JsonBudget, load_json, structure
from core.io.nerfstudio import MAX_INDEX_FRAMES, inspect_nerfstudio

MB = 1 << 20


def peak_bytes(fn, *args, **kwargs):
    """(result or raised exception, peak bytes Python allocated while fn ran)."""
    tracemalloc.start()
    try:
        try:
            out = fn(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - the caller checks what was raised
            out = exc
        return out, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


# -- declared sizes -----------------------------------------------------------------------------------
def test_a_huge_declared_frame_count_allocates_nothing_proportional():
    """Issue: 2e9 declared frames made select_frame_indices ask for 14.9 GiB (np.arange)."""
    picked, peak = peak_bytes(select_frame_indices, 2_000_000_000, 64 * 48, MediaLimits())
    assert len(picked) == 300 and picked[0] == 0 and picked[-1] == 1_999_999_999
    assert peak < 1 * MB
    np.testing.assert_array_equal(select_frame_indices(10, 4, MediaLimits(frame_stride=3)), [0, 3, 6, 9])


def test_an_mp4_whose_stts_declares_1e8_samples_is_counted_not_believed(tmp_path):
    """Issue: a 37 KB MP4 declaring 1e8 samples was accepted while the API grew by 760 MB."""
    bomb = h.mp4_declaring(tmp_path / "bomb.mp4", 10**8)
    assert bomb.stat().st_size < 64 * 1024
    header, peak = peak_bytes(probe_video, bomb)
    assert not isinstance(header, Exception), header
    assert header.frame_count == 6 and any("declares 100000000 frames" in w for w in header.warnings)
    assert peak < 20 * MB
    video = read_video(bomb)  # the worker reads what the file holds
    assert video.original_frame_count == 6 and video.frames.shape[0] == 6


# -- zips: entry counts before zipfile parses the directory -----------------------------------------
@pytest.fixture
def zipfile_parse_forbidden(monkeypatch):
    def forbidden(self, *args, **kwargs):
        raise AssertionError("zipfile parsed the central directory")

    monkeypatch.setattr(zipfile.ZipFile, "_RealGetContents", forbidden)


def test_a_zip_with_too_many_entries_is_refused_from_its_end_record(zipfile_parse_forbidden):
    """Issue: 1M empty entries were refused (413) only after 18 s and +565 MB (zipfile builds a
    ZipInfo per entry first)."""
    data = h.zip_with_entries(20_500)
    with pytest.raises(ArchiveError) as err:
        ZipFiles(data)
    assert err.value.code == "too_large" and "20502 entries" in str(err.value)


def test_a_zip_lying_about_its_entry_count_is_refused_while_walking(zipfile_parse_forbidden):
    data = h.zip_lying_about_entries(20_500, declared=3)
    with pytest.raises(ArchiveError) as err:
        ZipFiles(data)
    assert err.value.code == "too_large" and "more than 20000 entries" in str(err.value)


def test_a_depth_npz_with_many_members_is_refused_before_zipfile_reads_it(zipfile_parse_forbidden):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for i in range(200):
            z.writestr(f"a{i}.npy", b"")
    with pytest.raises(MediaError) as err:
        read_depth(buf.getvalue())
    assert err.value.code == "too_large"


# -- transforms.json: size, depth, containers, frames ----------------------------------------------
def test_json_structure_is_measured_without_parsing():
    assert structure(b'{"a": [1, {"b": "[[[[\\"]]"}], "c": []}') == (3, 4)
    with pytest.raises(MediaError, match="nests arrays/objects 100001 deep"):
        load_json(h.nested_index(100_000), "x.json")
    with pytest.raises(MediaError, match="holds 2000002 arrays/objects"):
        load_json(h.container_bomb_index(2_000_000), "x.json", JsonBudget(max_bytes=64 * MB))
    with pytest.raises(MediaError, match="bytes, more than"):
        load_json(b" " * 100, "x.json", JsonBudget(max_bytes=10))
    assert load_json(b'{"a": [1, 2]}', "x.json") == {"a": [1, 2]}


@pytest.mark.parametrize("index, code, named", [
    (h.nested_index(100_000), "too_large", "deep"),  # issue: RecursionError -> 500
    (h.container_bomb_index(2_000_000), "too_large", "arrays/objects"),  # issue: +1.5 GB, 33 s
    (b'{"frames": []}' + b" " * (9 * MB), "too_large", "bytes"),  # over the index's byte limit: not read
    (h.many_frames_index(100_000), "too_large", "bytes"),  # issue: 33 s, another upload waited 22 s
    (h.many_frames_index(40_000), "too_large", "arrays/objects"),
    (h.many_frames_index(12_000), "too_many_frames", str(MAX_INDEX_FRAMES)),
])
def test_hostile_indexes_are_refused_within_budget(index, code, named):
    data = h.capture_zip(index)
    t0 = time.monotonic()
    err, peak = peak_bytes(inspect_nerfstudio, data)
    assert isinstance(err, ArchiveError), err
    assert err.code == code and named in str(err) and "transforms.json" in str(err)
    assert peak < 100 * MB, peak / MB
    assert time.monotonic() - t0 < 5  # was 33 s; a guard against quadratic work, not a benchmark


def test_ten_thousand_frames_are_checked_at_once():
    index = h.capture_index(frames=1)
    index["frames"] = [{"file_path": "images/0.png", "transform_matrix": h.EYE}] * 10_000
    info = inspect_nerfstudio(h.capture_zip(index, {"images/0.png": h.png_bytes()}))
    assert info["frames"] == 10_000 and len(info["kept"]) == 300
    index["frames"][7777] = {"file_path": "images/0.png", "transform_matrix": [[2, 0, 0, 0], *h.EYE[1:]]}
    with pytest.raises(ArchiveError) as err:
        inspect_nerfstudio(h.capture_zip(index, {"images/0.png": h.png_bytes()}))
    assert err.value.field == "transforms.json: frames[7777].transform_matrix"


# -- what the worker refuses, the probe refuses: capture-app zips -----------------------------------
OUTSIDE = [
    ({"frames": [{"file_path": "images/0.png", "transform_matrix": [[1, 0, 0, 1e300], *h.EYE[1:]]}]},
     "invalid_poses", "frames[0].transform_matrix", "+-10000 m"),
    ({"fl_x": 1e308}, "invalid_intrinsics", "fl_x", "1 to 170 deg"),
    ({"fl_x": 1e-300}, "invalid_intrinsics", "fl_x", "1 to 170 deg"),
    ({"cx": 1e308}, "invalid_intrinsics", "cx", "-32 to 96 px"),
    ({"camera_model": "OPENCV", "k1": 1e300}, "invalid_intrinsics", "k1", "[-10, 10]"),
    ({"camera_model": "OPENCV", "p2": 3.0}, "invalid_intrinsics", "p2", "[-1, 1]"),
]


@pytest.mark.parametrize("edit, code, key, allowed", OUTSIDE, ids=[o[2] + str(i) for i, o in enumerate(OUTSIDE)])
def test_capture_values_outside_their_range_are_refused_naming_key_and_range(tmp_path, edit, code, key, allowed):
    """Issue: accepted at submission, failed (or produced garbage) in the worker."""
    path = tmp_path / "cap.zip"
    path.write_bytes(h.capture_zip(h.capture_index() | edit))
    with pytest.raises(MediaError) as err:
        probe_capture(path)
    assert err.value.code == code and f"transforms.json: {key}" in str(err.value) and allowed in str(err.value)
    from core.capture.load import load_capture

    with pytest.raises(ValueError) as late:  # the worker: the same code
        load_capture(path)
    assert getattr(late.value, "code", None) == code


def test_a_png_bomb_has_the_same_code_alone_and_in_a_zip(tmp_path):
    """Issue: 413 too_many_pixels alone, 415 not_media (DecompressionBombError) inside a zip."""
    alone = tmp_path / "bomb.png"
    alone.write_bytes(h.png_bomb())
    inside = tmp_path / "bomb.zip"
    index = h.capture_index(frames=1)
    del index["w"], index["h"]  # the image's own header gives the size
    inside.write_bytes(h.capture_zip(index, {"images/0.png": h.png_bomb()}))
    codes = []
    for path in (alone, inside):
        with pytest.raises(MediaError) as err:
            probe_capture(path)
        codes.append(err.value.code)
    assert codes == ["too_many_pixels", "too_many_pixels"]


def test_truncated_images_are_refused_alone_and_in_a_zip(tmp_path):
    """Issue: a truncated JPEG passed the upload check (its header is intact) and failed the job."""
    alone = tmp_path / "cut.jpg"
    alone.write_bytes(h.truncated_jpeg())
    first = tmp_path / "first.zip"
    first.write_bytes(h.capture_zip(h.capture_index(), {"images/0.png": h.truncated_jpeg(),
                                                        "images/1.png": h.png_bytes()}))
    later = tmp_path / "later.zip"
    later.write_bytes(h.capture_zip(h.capture_index(), {"images/0.png": h.png_bytes(),
                                                        "images/1.png": h.truncated_jpeg()}))
    for path, named in ((alone, "JPEG"), (first, "frames[0].file_path"), (later, "frames[1].file_path")):
        with pytest.raises(MediaError) as err:
            probe_capture(path)
        assert err.value.code == "truncated" and named in str(err.value), (path.name, err.value)
    whole = tmp_path / "ok.jpg"
    whole.write_bytes(h.jpeg_bytes())
    assert probe_capture(whole).frames == 1


# -- depth: range, Fortran stacks, bombs ---------------------------------------------------------------
@pytest.mark.parametrize("metres", [3e38, 1e20, 2e4])
def test_depth_beyond_ten_km_is_refused_by_probe_and_reader(metres):
    """Issue: 3e38 m ended in an IndexError at index -2^63 in the worker; 1e20 m gave a field
    with +-1e20 m bounds and no warning."""
    depth = np.full((48, 64), 2.0, np.float32)
    depth[10, 10] = metres
    data = h.npz(depth)
    for reader in (probe_depth, read_depth):
        with pytest.raises(MediaError) as err:
            reader(data)
        assert err.value.code == "invalid_depth" and "(0, 10000] m" in str(err.value)
    np.testing.assert_allclose(read_depth(h.npz(np.full((4, 4), 9999.0, np.float32))), 9999.0)


def test_a_fortran_ordered_depth_stack_is_probed_a_block_at_a_time():
    """Issue: a Fortran-ordered stack was read whole to get its first map."""
    data = h.fortran_depth(60, 400, 400)  # 38 MB of float32
    (shape, first), peak = peak_bytes(probe_depth, data)
    assert shape == (60, 400, 400)
    stack = np.load(io.BytesIO(data))
    np.testing.assert_array_equal(first, stack[0])
    assert peak < 16 * MB, peak / MB


def test_a_fortran_npz_bomb_is_refused_before_inflating():
    """Issue: a 1.17 MB .npz whose header says Fortran order, 100 x 1000 x 1000 float64, took
    the API to +1.5 GB before its 422 (C order: nothing)."""
    data = h.fortran_npz_bomb((40, 500, 500))
    assert len(data) < 2 * MB
    for reader in (probe_depth, read_depth):
        err, peak = peak_bytes(reader, data)
        assert isinstance(err, MediaError) and err.code == "too_large" and "zip bomb" in str(err), err
        assert peak < 16 * MB


# -- variable frame rate ------------------------------------------------------------------------------
def test_variable_frame_rate_uses_presentation_timestamps_and_warns(tmp_path):
    """Issue: an MKV stamped unevenly over 9 s was read as index / fps (0.9 s), silently."""
    stamps = [0.0, 0.1, 0.2, 1.5, 3.0, 3.1, 5.0, 7.0, 8.5, 9.0]
    video = read_video(h.vfr_mkv(tmp_path / "vfr.mkv", stamps))
    np.testing.assert_allclose(video.times, stamps, atol=1e-3)
    assert any("variable frame rate" in w for w in video.warnings)
    from core.capture.load import load_capture
    from core.capture.params import CaptureParams

    capture = load_capture(tmp_path / "vfr.mkv")
    np.testing.assert_allclose(capture.times.numpy(), stamps, atol=1e-3)
    assert any("variable frame rate" in w for w in capture.warnings)
    fixed = load_capture(tmp_path / "vfr.mkv", params=CaptureParams(fps=2.0))  # an explicit rate wins
    np.testing.assert_allclose(fixed.times.numpy(), np.arange(10) / 2.0)


def test_an_even_clip_has_no_warning_and_the_same_times(tmp_path):
    video = read_video(h.tiny_mp4(tmp_path / "even.mp4"))
    np.testing.assert_allclose(video.times, np.arange(6) / 6.0, atol=1e-6)
    assert not any("variable" in w for w in video.warnings)
