"""Capture loading: images, videos, capture directories, depth files, defaults and errors."""
import json
import math

import numpy as np
import pytest
import torch

from core.camera import Intrinsics
from core.capture.base import CaptureError
from core.capture.depth import ASSUMED_DEPTH_SOURCE, assumed_box_depth, fill_depth_holes
from core.capture.load import capture_from_arrays
from core.capture.params import CaptureParams
from core.capture.prepare import load_prepared_capture
from core.conventions import DEFAULT_HFOV_DEG
from core.io import write_png, write_video
from core.transfer import SRGB


def _image(tmp_path, h=24, w=32, name="img.png"):
    rng = np.random.default_rng(0)
    img = rng.uniform(0.1, 0.9, (h, w, 3)).astype(np.float32)
    path = tmp_path / name
    write_png(path, img)
    return path, img


def test_image_gets_documented_defaults(tmp_path):
    path, img = _image(tmp_path)
    with pytest.warns(UserWarning):
        cap = load_prepared_capture(path)
    assert cap.frames.shape == (1, 24, 32, 3)
    assert np.allclose(cap.frames[0].numpy(), img, atol=1 / 255)
    assert cap.intrinsics.hfov_deg == pytest.approx(DEFAULT_HFOV_DEG)
    assert torch.equal(cap.poses[0], torch.eye(4, dtype=torch.float64))
    assert cap.depth_source == ASSUMED_DEPTH_SOURCE and any("assum" in w for w in cap.warnings)
    assert cap.times.tolist() == [0.0] and cap.static_camera
    assert torch.isfinite(cap.depth).all() and (cap.depth > 0).all()


def test_assumed_box_depth_is_the_box():
    k = Intrinsics.from_hfov(64, 48, 60.0)
    d = assumed_box_depth(k, half_width=2.5, floor=1.5, ceiling=1.5, back=4.0)
    # the image centre looks straight at the back wall
    assert d[24, 32] == pytest.approx(4.0)
    # bottom-centre pixel hits the floor: y = -1.5 at planar depth s = 1.5 / (-ray_y)
    v = 47.5
    ray_y = -(v - k.cy) / k.fy
    assert d[47, 32] == pytest.approx(min(4.0, 1.5 / -ray_y), rel=1e-5)
    assert (d <= 4.0 + 1e-5).all()


def test_given_intrinsics_fps_depth_npz_and_poses(tmp_path):
    path, _ = _image(tmp_path)
    depth = np.full((24, 32), 2.0, np.float32)
    np.savez(tmp_path / "d.npz", depth=depth)
    pose = np.eye(4)
    pose[:3, 3] = [1, 2, 3]
    params = CaptureParams(
        intrinsics={"fx": 30, "fy": 31, "cx": 16, "cy": 12}, poses=[pose.reshape(-1).tolist()], fps=5
    )
    cap = load_prepared_capture(path, tmp_path / "d.npz", params)
    assert (cap.intrinsics.fx, cap.intrinsics.fy) == (30, 31)
    assert torch.allclose(cap.depth, torch.full((1, 24, 32), 2.0))
    assert cap.camera(0).position.tolist() == [1, 2, 3]
    assert cap.depth_source.startswith("file:")


def test_depth_size_mismatch_names_both_sizes(tmp_path):
    path, _ = _image(tmp_path)
    np.savez(tmp_path / "d.npz", depth=np.ones((20, 30), np.float32))
    with pytest.raises(CaptureError) as exc:
        load_prepared_capture(path, tmp_path / "d.npz")
    assert exc.value.field == "depth" and "30x20" in str(exc.value) and "32x24" in str(exc.value)


@pytest.mark.parametrize("bad", [np.zeros((24, 32)), np.full((24, 32), np.nan), -np.ones((24, 32))])
def test_depth_without_valid_pixels(tmp_path, bad):
    path, _ = _image(tmp_path)
    np.savez(tmp_path / "d.npz", depth=bad.astype(np.float32))
    with pytest.raises(CaptureError) as exc:
        load_prepared_capture(path, tmp_path / "d.npz")
    assert exc.value.field == "depth"


def test_mostly_invalid_depth_is_filled_with_a_warning():
    d = torch.full((1, 16, 16), float("nan"))
    d[0, :3, :3] = 2.0
    d[0, 10:, 10:] = 4.0
    cap = capture_from_arrays(torch.rand(1, 16, 16, 3), d)
    assert torch.isfinite(cap.depth).all()
    assert cap.depth.min() >= 2.0 and cap.depth.max() <= 4.0
    assert cap.depth[0, 0, 0] == 2.0 and cap.depth[0, 15, 15] == 4.0
    assert any("holes filled" in w for w in cap.warnings)


def test_fill_depth_holes_keeps_valid_pixels():
    d = torch.tensor([[1.0, float("nan"), 3.0], [float("inf"), 0.0, -1.0]])
    f = fill_depth_holes(d)
    assert f[0, 0] == 1.0 and f[0, 2] == 3.0
    assert torch.isfinite(f).all() and (f >= 1.0).all() and (f <= 3.0).all()


def test_pose_count_and_nonfinite_poses():
    frames = torch.rand(3, 8, 8, 3)
    with pytest.raises(CaptureError) as exc:
        capture_from_arrays(frames, poses=torch.eye(4, dtype=torch.float64).expand(2, 4, 4))
    assert exc.value.field == "poses" and "2 poses for 3 frames" in str(exc.value)
    p = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    p[1, 0, 3] = math.nan
    with pytest.raises(CaptureError) as exc:
        capture_from_arrays(frames, poses=p)
    assert exc.value.field == "poses"


def test_params_pose_count_mismatch_on_image(tmp_path):
    path, _ = _image(tmp_path)
    params = CaptureParams(poses=[np.eye(4).reshape(-1).tolist()] * 2)
    with pytest.raises(CaptureError) as exc:
        load_prepared_capture(path, params=params)
    assert exc.value.field == "poses"


def test_depth_frame_count_mismatch():
    with pytest.raises(CaptureError) as exc:
        capture_from_arrays(torch.rand(3, 8, 8, 3), torch.ones(2, 8, 8))
    assert exc.value.field == "depth"
    cap = capture_from_arrays(torch.rand(3, 8, 8, 3), torch.ones(8, 8))  # [H, W] broadcasts
    assert cap.depth.shape == (3, 8, 8)


def test_unknown_input_and_missing_file(tmp_path):
    bad = tmp_path / "notes.txt"
    bad.write_text("hello")
    with pytest.raises(CaptureError) as exc:
        load_prepared_capture(bad)
    assert exc.value.field == "input"
    with pytest.raises(CaptureError):
        load_prepared_capture(tmp_path / "missing.png")


def test_video_times_and_max_frames(tmp_path):
    frames = np.stack([np.full((16, 16, 3), i / 10, np.float32) for i in range(6)])
    path = write_video(tmp_path / "v.mp4", frames, fps=5)
    with pytest.warns(UserWarning, match="assum"):
        cap = load_prepared_capture(path, params=CaptureParams(max_frames=3))
    assert cap.num_frames == 3 and cap.fps == pytest.approx(5)
    # evenly subsampled frames keep their source times
    assert cap.times[0] == 0.0 and cap.times[-1] > cap.times[1] > 0
    assert cap.duration <= 1.0 + 1e-6


def test_capture_directory(tmp_path):
    T, H, W = 2, 12, 16
    (tmp_path / "frames").mkdir()
    names = []
    for i in range(T):
        write_png(tmp_path / "frames" / f"{i:05d}.png", np.full((H, W, 3), 0.2 * (i + 1), np.float32))
        names.append(f"frames/{i:05d}.png")
    np.savez(tmp_path / "depth.npz", depth=np.full((T, H, W), 3.0, np.float32))
    poses = [np.eye(4).reshape(-1).tolist() for _ in range(T)]
    poses[1][3] = 0.5  # x translation of the second camera
    index = {"format": "lightfield-capture", "version": 1, "fps": 4, "frame_count": T,
             "intrinsics": {"fx": 20, "fy": 20, "cx": 8, "cy": 6, "width": W, "height": H},
             "poses": poses, "frames": names, "depth": "depth.npz", "future_key": 1}
    (tmp_path / "capture.json").write_text(json.dumps(index))
    cap = load_prepared_capture(tmp_path)
    assert cap.num_frames == T and cap.fps == 4 and cap.times.tolist() == [0.0, 0.25]
    assert cap.intrinsics.fx == 20 and not cap.static_camera
    assert cap.camera(1).position[0] == pytest.approx(0.5)
    assert cap.depth_source == "file:depth.npz"


def test_resized_keeps_nearest_depth_and_scales_intrinsics():
    d = torch.full((1, 8, 8), 4.0)
    d[0, 0, 0] = 1.0  # a thin near object
    cap = capture_from_arrays(torch.rand(1, 8, 8, 3), d).resized(4)
    assert cap.depth.shape == (1, 4, 4) and cap.depth[0, 0, 0] == 1.0 and cap.depth[0, 3, 3] == 4.0
    assert cap.intrinsics.width == 4 and cap.intrinsics.fx == pytest.approx(
        capture_from_arrays(torch.rand(1, 8, 8, 3), d).intrinsics.fx / 2
    )


def test_capture_directory_with_bad_intrinsics(tmp_path):
    (tmp_path / "frames").mkdir()
    write_png(tmp_path / "frames" / "0.png", np.full((8, 8, 3), 0.5, np.float32))
    index = {"format": "lightfield-capture", "version": 1, "fps": 4, "frame_count": 1, "frames": ["frames/0.png"],
             "intrinsics": {"fx": 0.0, "fy": 10, "cx": 4, "cy": 4, "width": 8, "height": 8}}
    (tmp_path / "capture.json").write_text(json.dumps(index))
    with pytest.raises(CaptureError) as exc:
        load_prepared_capture(tmp_path)
    assert exc.value.field == "intrinsics" and "fx" in str(exc.value)
    (tmp_path / "capture.json").write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(CaptureError, match="not a lightfield capture"):
        load_prepared_capture(tmp_path)


# ---------------------------------------------------------------------------------------
# Limits reach every decoder, and GIFs are videos
# ---------------------------------------------------------------------------------------
def _depth_npz(path, h, w, value=2.0):
    np.savez(path, depth=np.full((h, w), value, np.float32))
    return path


def test_image_over_the_pixel_limit_is_refused(tmp_path):
    from core.io import MediaError, MediaLimits

    path, _ = _image(tmp_path, h=24, w=32)  # 768 pixels
    with pytest.raises(MediaError) as exc:
        load_prepared_capture(path, limits=MediaLimits(max_pixels=700))
    assert exc.value.code == "too_many_pixels"
    with pytest.warns(UserWarning):
        assert load_prepared_capture(path, limits=MediaLimits(max_pixels=768)).frames.shape == (1, 24, 32, 3)


def test_depth_file_is_read_under_the_limits(tmp_path):
    from core.io import MediaError, MediaLimits

    path, _ = _image(tmp_path, h=16, w=16)
    big = _depth_npz(tmp_path / "big.npz", 24, 32)  # a bomb-like depth: more pixels than allowed
    with pytest.raises(MediaError) as exc:  # refused by the pixel limit, before any size comparison
        load_prepared_capture(path, big, limits=MediaLimits(max_pixels=700))
    assert exc.value.code == "too_many_pixels"
    small = _depth_npz(tmp_path / "small.npz", 16, 16)
    with pytest.raises(MediaError) as exc:
        load_prepared_capture(path, small, limits=MediaLimits(max_bytes=small.stat().st_size - 1))
    assert exc.value.code == "too_large"


def test_capture_directory_depth_obeys_the_limits(tmp_path):
    from core.io import MediaError, MediaLimits

    write_png(tmp_path / "f.png", np.full((12, 16, 3), 0.5, np.float32))
    depth = _depth_npz(tmp_path / "depth.npz", 12, 16)
    (tmp_path / "capture.json").write_text(json.dumps(
        {"format": "lightfield-capture", "version": 1, "frames": ["f.png"], "depth": "depth.npz"}))
    frame_bytes = (tmp_path / "f.png").stat().st_size
    assert depth.stat().st_size > frame_bytes  # so max_bytes between the two refuses only the depth
    with pytest.raises(MediaError) as exc:
        load_prepared_capture(tmp_path, limits=MediaLimits(max_bytes=frame_bytes))
    assert exc.value.code == "too_large" and "depth" in str(exc.value)


def test_limits_default_to_the_environment(tmp_path, monkeypatch):
    from core.io import MediaError

    path, _ = _image(tmp_path, h=24, w=32)
    monkeypatch.setenv("LIGHTFIELD_MAX_PIXELS", "700")
    with pytest.raises(MediaError) as exc:
        load_prepared_capture(path)
    assert exc.value.code == "too_many_pixels" and "700" in str(exc.value)


def _gif(path, values, duration_ms=100, hw=(24, 32)):
    from PIL import Image

    frames = [Image.fromarray(np.full((*hw, 3), v, np.uint8)) for v in values]
    frames[0].save(path, save_all=len(frames) > 1, append_images=frames[1:], duration=duration_ms, loop=0)
    return path


def test_animated_gif_is_read_as_a_video(tmp_path):
    path = _gif(tmp_path / "clip.gif", (30, 120, 220), duration_ms=100)
    with pytest.warns(UserWarning):
        cap = load_prepared_capture(path)
    assert cap.num_frames == 3 and cap.fps == pytest.approx(10.0)
    assert cap.times.tolist() == pytest.approx([0.0, 0.1, 0.2])
    means = cap.frames.mean(dim=(1, 2, 3))  # a GIF states no curve: its codes are read as sRGB
    assert torch.allclose(means, SRGB.to_convention(torch.tensor([30, 120, 220]) / 255.0), atol=2 / 255)
    assert cap.metadata["transfer"]["curve"] == "srgb"


def test_gif_obeys_frame_and_pixel_limits(tmp_path):
    from core.io import MediaError, MediaLimits

    path = _gif(tmp_path / "clip.gif", (10, 60, 110, 160, 210, 250))
    with pytest.warns(UserWarning):
        cap = load_prepared_capture(path, params=CaptureParams(max_frames=3))
    assert cap.num_frames == 3 and cap.times[-1] > cap.times[0]  # evenly subsampled, source times kept
    with pytest.raises(MediaError) as exc:
        load_prepared_capture(path, limits=MediaLimits(max_pixels=700))
    assert exc.value.code == "too_many_pixels"
