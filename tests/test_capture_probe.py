"""The upload check reads headers, not pixels: core.io's probes and core.capture.probe accept
and refuse what the full decoders and load_capture accept and refuse, for one frame's cost."""
import io
import warnings

import numpy as np
import pytest

import core.io.video as video_module
from core.camera import CameraError
from core.capture.base import CaptureError
from core.capture.params import CaptureParams
from core.capture.prepare import load_prepared_capture
from core.capture.probe import probe_capture
from core.io import MediaError, MediaLimits, probe_depth, probe_image, probe_video, write_png, write_video

H, W = 24, 32


@pytest.fixture(scope="module")
def media(tmp_path_factory):
    root = tmp_path_factory.mktemp("probe")
    rng = np.random.default_rng(0)
    frames = rng.random((8, H, W, 3)).astype(np.float32)
    return {"image": write_png(root / "a.png", frames[0]), "video": write_video(root / "v.mp4", frames, fps=8.0),
            "root": root}


def _npz(root, name: str, depth: np.ndarray):
    buf = io.BytesIO()
    np.savez(buf, depth=depth)
    (root / name).write_bytes(buf.getvalue())
    return root / name


def test_a_long_video_is_probed_from_its_header_and_one_frame(tmp_path, monkeypatch):
    path = write_video(tmp_path / "long.mp4", np.full((400, H, W, 3), 0.5, np.float32), fps=30.0)
    decoded = []
    frames_of = video_module._decoded_frames

    def counted(*a, **k):
        for frame in frames_of(*a, **k):
            decoded.append(1)
            yield frame

    monkeypatch.setattr(video_module, "_decoded_frames", counted)
    header = probe_video(path, MediaLimits(max_frames=50))
    assert (header.width, header.height, header.frame_count, len(header.selected)) == (W, H, 400, 50)
    assert header.fps == pytest.approx(30.0) and len(decoded) == 1


def test_probes_refuse_what_the_decoders_refuse(media, tmp_path):
    video = media["video"].read_bytes()
    (tmp_path / "cut.mp4").write_bytes(video[: len(video) // 4])
    with pytest.raises(MediaError) as info:
        probe_video(tmp_path / "cut.mp4")
    assert info.value.code == "truncated"
    with pytest.raises(MediaError, match="too_many_pixels|pixels") as info:
        probe_video(media["video"], MediaLimits(max_pixels=W * H - 1))
    assert info.value.code == "too_many_pixels"
    png = media["image"].read_bytes()
    with pytest.raises(MediaError) as info:
        probe_image(png[: len(png) // 3])
    assert info.value.code == "truncated"
    assert probe_image(png) == (W, H)
    with pytest.raises(MediaError) as info:
        probe_image(png, MediaLimits(max_pixels=10))
    assert info.value.code == "too_many_pixels"


def test_depth_probe_reads_the_header_and_the_first_map_only(media):
    stack = np.full((8, H, W), 2.0, np.float32)
    stack[0, 0, 0] = -1.0
    shape, first = probe_depth(_npz(media["root"], "stack.npz", stack))
    assert shape == (8, H, W) and first.shape == (H, W) and np.isnan(first[0, 0]) and first[1, 1] == 2.0
    shape, first = probe_depth(_npz(media["root"], "fortran.npz", np.asfortranarray(stack)))
    assert shape == (8, H, W) and np.isnan(first[0, 0]) and first[1, 1] == 2.0
    np.save(media["root"] / "one.npy", stack[1])
    shape, first = probe_depth(media["root"] / "one.npy")
    assert shape == (H, W) and np.all(first == 2.0)
    with pytest.raises(MediaError) as info:
        probe_depth(_npz(media["root"], "big.npz", np.ones((4, 64, 64), np.float32)), MediaLimits(max_pixels=100))
    assert info.value.code == "too_many_pixels"


CASES = {
    "image": ("image", None, {}),
    "video": ("video", None, {}),
    "video, budget": ("video", None, {"max_frames": 3}),
    "video, depth per frame": ("video", np.full((8, H, W), 2.0, np.float32), {}),
    "video, poses per frame": ("video", None, {"poses": [np.eye(4).ravel().tolist()] * 8, "max_frames": 4}),
    "image, intrinsics": ("image", np.full((H, W), 3.0, np.float32), {"intrinsics": {"hfov_deg": 70}}),
}
BAD = {
    "depth size": ("image", np.ones((10, 10), np.float32), {}, "depth"),
    "depth count": ("video", np.ones((3, H, W), np.float32), {}, "depth"),
    "depth all invalid": ("image", np.full((H, W), np.nan, np.float32), {}, "depth"),
    "pose count": ("image", None, {"poses": [np.eye(4).ravel().tolist()] * 2}, "poses"),
    "exposure count": ("video", None, {"frame_ev": [0.0, -1.0]}, "frame_ev"),
    "exposure out of range": ("image", None, {"frame_ev": [40.0]}, "params"),
    "pose not finite rows": ("video", None, {"poses": [[float("nan")] * 16] * 8}, "params"),
    "intrinsics": ("image", None, {"intrinsics": {"fx": -5.0, "fy": 5.0, "cx": 1.0, "cy": 1.0}}, "params"),
}


@pytest.mark.parametrize("case", CASES)
def test_probe_capture_sees_what_load_capture_loads(media, case):
    kind, depth, params = CASES[case]
    depth_path = None if depth is None else _npz(media["root"], f"{case}.npz", depth)
    header = probe_capture(media[kind], depth_path, CaptureParams(**params))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # assumed depth / intrinsics
        cap = load_prepared_capture(media[kind], depth_path, CaptureParams(**params))
    assert (header.frames, header.width, header.height) == (cap.num_frames, cap.width, cap.height)


@pytest.mark.parametrize("case", BAD)
def test_probe_capture_refuses_what_load_capture_refuses(media, case):
    kind, depth, params, field = BAD[case]
    depth_path = None if depth is None else _npz(media["root"], f"bad-{case}.npz", depth)
    try:
        params = CaptureParams(**params)
    except ValueError:
        assert field == "params"  # refused by the schema before any loading
        return
    errors = []
    for check in (probe_capture, load_prepared_capture):
        with pytest.raises((CaptureError, CameraError)) as info, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            check(media[kind], depth_path, params)
        errors.append(getattr(info.value, "field", "intrinsics"))
    assert errors == [field, field]
