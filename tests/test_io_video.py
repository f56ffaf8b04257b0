"""Video decoding under limits (frame budget, stride, subsampling), mp4 writing, corrupt input."""
import io

import av
import numpy as np
import pytest
from hypothesis import given, strategies as st

from core.io import MediaError, MediaLimits, read_video, select_frame_indices, write_video
from core.io.video import video_codec

T, H, W, FPS = 10, 48, 64, 12.5


def smooth_clip() -> np.ndarray:
    """Frames whose brightness encodes the frame index (robust to chroma subsampling)."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    base = 0.3 * x / W + 0.2 * y / H
    return np.stack(
        [np.stack([base + 0.05 * t, base + 0.04 * t, np.full_like(base, 0.1 + 0.06 * t)], -1) for t in range(T)]
    ).astype(np.float32)


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    frames = smooth_clip()
    path = write_video(tmp_path_factory.mktemp("video") / "clip.mp4", frames, FPS)
    return path, frames


def test_written_mp4_reads_back(clip):
    path, frames = clip
    video = read_video(path)
    assert video.frames.shape == (T, H, W, 3) and video.frames.dtype == np.float32
    assert video.fps == pytest.approx(FPS)
    np.testing.assert_array_equal(video.source_frame_indices, np.arange(T))
    assert video.original_frame_count == T and video.warnings == []
    assert np.abs(video.frames - frames).mean() < 0.02
    np.testing.assert_allclose(video.times, np.arange(T) / FPS)


def test_the_same_frames_encode_to_the_same_video(tmp_path):
    """A room scan written twice decodes to the same pixels: with x264's MB-tree the encoder
    decided differently from run to run, so every simulated capture (and each bench on them)
    moved between runs."""
    from core.sim.panorama_room import load_panorama
    from core.sim.room_scan import SAMPLE_PANORAMA, render_scan

    ldr = render_scan(load_panorama(SAMPLE_PANORAMA, 64), yaw0=30.0, seed=3, size=(64, 48)).ldr.numpy()
    a, b = (read_video(write_video(tmp_path / f"{n}.mp4", ldr, 10.0)).frames for n in "ab")
    np.testing.assert_array_equal(a, b)


def test_written_stream_uses_the_reported_codec(clip):
    path, _ = clip
    with av.open(str(path)) as container:
        stream_codec = container.streams.video[0].codec_context.name
    assert stream_codec == {"libx264": "h264", "mpeg4": "mpeg4"}[video_codec()]


def test_bytes_and_path_inputs_agree(clip):
    path, _ = clip
    np.testing.assert_array_equal(read_video(path.read_bytes()).frames, read_video(path).frames)


def test_too_many_frames_subsampled_evenly_or_refused(clip):
    path, frames = clip
    video = read_video(path, MediaLimits(max_frames=4))
    np.testing.assert_array_equal(video.source_frame_indices, [0, 3, 6, 9])
    assert video.original_frame_count == T
    full = read_video(path).frames
    np.testing.assert_array_equal(video.frames, full[[0, 3, 6, 9]])  # same pixels as a full decode
    with pytest.raises(MediaError) as err:
        read_video(path, MediaLimits(max_frames=4), on_too_many="error")
    assert err.value.code == "too_many_frames" and "10 frames" in str(err.value)


def test_frame_stride_and_total_pixel_budget(clip):
    path, _ = clip
    np.testing.assert_array_equal(read_video(path, MediaLimits(frame_stride=3)).source_frame_indices, [0, 3, 6, 9])
    budget = read_video(path, MediaLimits(max_total_pixels=3 * H * W))
    np.testing.assert_array_equal(budget.source_frame_indices, [0, 4, 9])  # round(linspace(0, 9, 3))


def test_frame_size_checked_before_decoding(clip):
    path, _ = clip
    with pytest.raises(MediaError) as err:
        read_video(path, MediaLimits(max_pixels=H * W - 1))
    assert err.value.code == "too_many_pixels"


def test_truncated_mp4(tmp_path):
    rng = np.random.default_rng(0)
    moving = np.stack([np.roll(np.kron(rng.random((8, 8, 3)), np.ones((4, 4, 1))), t, axis=1) for t in range(40)])
    data = write_video(tmp_path / "moving.mp4", moving.astype(np.float32), 10).read_bytes()
    with pytest.raises(MediaError) as err:
        read_video(data[:200])  # cut inside the moov atom
    assert err.value.code == "truncated"
    partial = read_video(data[: int(len(data) * 0.6)])  # moov first: the first frames survive
    assert 0 < partial.frames.shape[0] < 40 and partial.warnings
    np.testing.assert_array_equal(partial.source_frame_indices, np.arange(partial.frames.shape[0]))


@pytest.mark.parametrize(
    "blob,code",
    [(b"", "empty"), (b"\x00" * 1000, "not_media"), (b"\x00\x00\x00\x20ftypisom" + bytes(200), "truncated")],
)
def test_corrupt_inputs_have_specific_codes(blob, code):
    with pytest.raises(MediaError) as err:
        read_video(blob)
    assert err.value.code == code


def test_image_is_not_a_video(tmp_path):
    from core.io import encode_png

    with pytest.raises(MediaError) as err:
        read_video(encode_png(np.zeros((4, 4, 3), np.uint8)))
    assert err.value.code == "not_media"


def test_odd_sizes_padded_and_bad_input_refused(tmp_path):
    video = read_video(write_video(tmp_path / "odd.mp4", np.full((2, 5, 7, 3), 0.5, np.float32), 5))
    assert video.frames.shape == (2, 6, 8, 3)
    for frames, fps in ((np.zeros((4, 4, 3)), 5), (np.zeros((1, 4, 4, 3)), 0.0), (np.full((1, 4, 4, 3), np.nan), 5)):
        with pytest.raises(MediaError):
            write_video(tmp_path / "bad.mp4", frames, fps)


@given(st.integers(1, 2000), st.integers(1, 400), st.integers(1, 7))
def test_select_frame_indices_properties(count, max_frames, stride):
    idx = select_frame_indices(count, 1, MediaLimits(max_frames=max_frames, frame_stride=stride))
    candidates = np.arange(0, count, stride)
    assert 1 <= idx.size <= max_frames and idx.size == min(candidates.size, max_frames)
    assert np.all(np.diff(idx) > 0) and np.all(idx % stride == 0) and idx[0] == 0
    assert idx[-1] == candidates[-1] or idx.size == 1  # the clip's end is kept


def test_select_frame_indices_refuses_frames_bigger_than_total_budget():
    with pytest.raises(MediaError) as err:
        select_frame_indices(10, 1000, MediaLimits(max_total_pixels=999))
    assert err.value.code == "too_many_pixels"


def _mkv(codec: str, fmt: str = "matroska", frames: int = 7) -> bytes:
    buf = io.BytesIO()
    with av.open(buf, "w", format=fmt) as container:
        stream = container.add_stream(codec, rate=15)
        stream.width, stream.height, stream.pix_fmt = 32, 32, "yuv420p"
        for i in range(frames):
            for packet in stream.encode(
                av.VideoFrame.from_ndarray(np.full((32, 32, 3), 30 * i, np.uint8), format="rgb24")
            ):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return buf.getvalue()


def test_webm_without_declared_frame_count_is_counted_then_subsampled():
    data = _mkv("libvpx-vp9", "webm")
    video = read_video(data, MediaLimits(max_frames=3))
    assert video.original_frame_count == 7
    np.testing.assert_array_equal(video.source_frame_indices, [0, 3, 6])
    np.testing.assert_allclose(video.frames[:, 0, 0, 0] * 255, [0, 90, 180], atol=3)


def test_unknown_codec_is_unsupported():
    data = _mkv("libx264")
    assert data.count(b"V_MPEG4/ISO/AVC") == 1
    with pytest.raises(MediaError) as err:
        read_video(data.replace(b"V_MPEG4/ISO/AVC", b"V_LIGHTFIELDXYZ"))  # same length, unknown CodecID
    assert err.value.code == "unsupported_codec"


def test_animated_gif_decodes_as_video():
    from PIL import Image

    frames = [Image.new("RGB", (16, 8), (40 * i, 0, 0)) for i in range(4)]
    buf = io.BytesIO()
    frames[0].save(buf, format="GIF", save_all=True, append_images=frames[1:], duration=100, loop=0)
    video = read_video(buf.getvalue())
    assert video.frames.shape == (4, 8, 16, 3)
    np.testing.assert_allclose(video.frames[:, 0, 0, 0] * 255, [0, 40, 80, 120], atol=2)
