"""The web page's server side without a browser: the stored capture preview and probe placement."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from core.camera import Camera, Intrinsics
from jobs.capture_preview import (
    META_FILE,
    TENSORS_FILE,
    CapturePreview,
    preview_dir,
    preview_from_capture,
    save_preview,
    write_capture_preview,
)
from service.stored_preview import PreviewError, load_preview
from service.ui_probes import ProbeError, fallback_depth, locate, pixel_of, place, radius_ratio, surface_depth

W, H = 64, 48
WALL = 3.0


def rotation_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def make_preview(depth: np.ndarray | None = None, frames: int = 3, fps: float = 4.0) -> CapturePreview:
    """A camera turned 30 deg about +y and moved to (1, 1.5, 2), facing a wall at planar depth 3 m."""
    pose = np.eye(4)
    pose[:3, :3] = rotation_y(30.0)
    pose[:3, 3] = (1.0, 1.5, 2.0)
    if depth is None:
        depth = np.full((frames, H, W), WALL, np.float32)
    rng = np.random.default_rng(0)
    return CapturePreview(
        frames=rng.integers(0, 256, (frames, H, W, 3), dtype=np.uint8), depth=depth.astype(np.float32),
        poses=np.repeat(pose[None], frames, 0), times=(np.arange(frames) / fps).astype(np.float32),
        intrinsics=Intrinsics.from_hfov(W, H, 60.0).as_dict(), fps=fps, depth_source="test", source_frames=frames)


# ---------------------------------------------------------------------------------------
# Probe placement
# ---------------------------------------------------------------------------------------
@settings(max_examples=40, deadline=None)
@given(u=st.floats(0.0, 1.0), v=st.floats(0.0, 1.0), depth=st.floats(0.05, 50.0))
def test_probe_lies_on_the_clicked_pixels_ray_at_the_requested_planar_depth(u, v, depth):
    preview = make_preview()
    p = place(preview, u, v, t=0.0, depth=depth)
    pu, pv, pz = preview.camera(0).project(torch.tensor([p.x], dtype=torch.float64))
    assert (float(pu[0]), float(pv[0])) == pytest.approx(pixel_of(u, v, W, H), abs=1e-4)
    assert float(pz[0]) == pytest.approx(depth, rel=1e-5)
    assert p.depth == depth and p.surface_depth == pytest.approx(WALL)


def test_default_depth_puts_the_ball_just_in_front_of_the_surface():
    preview = make_preview()
    p = place(preview, 0.3, 0.6, t=0.0)
    assert p.depth == p.default_depth
    gap = WALL - (p.depth + p.radius)  # nearest point of the ball along the axis vs the wall
    assert 0.0 < gap < 0.5 * p.radius
    assert p.radius == pytest.approx(radius_ratio(preview.camera(0)) * p.depth, rel=1e-5)


def test_surface_depth_falls_back_to_neighbours_then_to_the_frame():
    depth = np.full((H, W), np.nan, np.float32)
    depth[10:13, 20:23] = [[2.0, 2.0, 2.0], [2.0, np.nan, 4.0], [4.0, 4.0, 4.0]]
    assert surface_depth(depth, 21.5, 11.5) == pytest.approx(3.0)  # median of the 8 valid neighbours
    assert surface_depth(depth, 20.5, 10.5) == 2.0  # the pixel's own value when valid
    assert surface_depth(depth, 50.5, 40.5) is None
    assert fallback_depth(depth) == pytest.approx(3.0)
    assert fallback_depth(np.full((H, W), np.nan, np.float32)) == 2.0


def test_probe_over_a_hole_uses_the_frames_depth_and_says_the_surface_is_unknown():
    depth = np.full((1, H, W), np.nan, np.float32)
    depth[0, :, :8] = 5.0
    p = place(make_preview(depth, frames=1), 0.9, 0.5, t=0.0)
    assert p.surface_depth is None
    assert p.default_depth < 5.0 and np.isfinite(p.x).all()
    p = place(make_preview(np.full((1, H, W), -1.0, np.float32), frames=1), 0.5, 0.5, t=0.0)
    assert p.surface_depth is None and p.default_depth < 2.0


@pytest.mark.parametrize("kw, field", [
    ({"u": 1.5}, "u"), ({"u": float("nan")}, "u"), ({"v": -0.1}, "v"),
    ({"depth": 0.0}, "depth"), ({"depth": -2.0}, "depth"), ({"depth": float("inf")}, "depth"),
])
def test_bad_probe_requests_name_the_field(kw, field):
    args = {"u": 0.5, "v": 0.5, "depth": None, **kw}
    with pytest.raises(ProbeError, match=rf"^{field}"):
        place(make_preview(), args["u"], args["v"], 0.0, args["depth"])


def test_probe_uses_the_frame_nearest_in_time():
    preview = make_preview(frames=5, fps=4.0)  # t = 0, .25, .5, .75, 1
    assert [preview.nearest_frame(t) for t in (-3.0, 0.1, 0.13, 0.74, 9.0)] == [0, 0, 1, 3, 4]
    assert place(preview, 0.5, 0.5, t=0.6).frame_index == 2


def test_a_world_probe_is_found_again_in_the_frames_of_a_moving_camera():
    """Camera translating along +x by 0.5 m per frame, looking along -z (analytic projection)."""
    preview = make_preview(frames=3)
    poses = np.repeat(np.eye(4)[None], 3, 0)
    poses[:, 0, 3] = [0.0, 0.5, 1.0]
    preview = CapturePreview(**{**preview.__dict__, "poses": poses})
    p0 = place(preview, 0.5, 0.5, t=0.0, depth=2.0)
    assert p0.x == pytest.approx((0.0, 0.0, -2.0), abs=1e-5)
    again = locate(preview, p0.x, t=0.0)
    assert (again.u, again.v, again.depth, again.visible) == pytest.approx((0.5, 0.5, 2.0, True), abs=1e-6)
    assert again.radius == pytest.approx(p0.radius, rel=1e-5)
    fx = preview.intrinsics["fx"]
    later = locate(preview, p0.x, t=0.25)  # frame 1: the point is 0.5 m to the camera's left
    assert later.frame_index == 1 and later.visible
    assert later.u == pytest.approx(0.5 - fx * 0.5 / 2.0 / W, abs=1e-6) and later.depth == pytest.approx(2.0)
    assert later.surface_depth == pytest.approx(WALL)


def test_probes_behind_the_camera_or_off_the_frame_are_not_visible():
    preview = make_preview()
    camera = preview.camera(0)
    behind = (camera.c2w[:3, :3] @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) + camera.position).tolist()
    p = locate(preview, behind, 0.0)
    assert not p.visible and p.u is None and p.depth < 0 and p.radius == 0.0
    aside = (camera.c2w[:3, :3] @ torch.tensor([50.0, 0.0, -1.0], dtype=torch.float64) + camera.position).tolist()
    p = locate(preview, aside, 0.0)
    assert not p.visible and p.u > 1.0 and p.surface_depth is None
    with pytest.raises(ProbeError, match="^x"):
        locate(preview, (0.0, float("nan"), 0.0), 0.0)


# ---------------------------------------------------------------------------------------
# Stored preview
# ---------------------------------------------------------------------------------------
def test_preview_round_trips_and_reads_single_frames(tmp_path):
    depth = np.full((3, H, W), 2.5, np.float32)
    depth[1, :4, :4] = np.nan
    preview = make_preview(depth)
    save_preview(preview, tmp_path)
    stored = load_preview(tmp_path)
    assert (stored.num_frames, stored.height, stored.width) == (3, H, W)
    for i in range(3):
        np.testing.assert_array_equal(stored.frame(i), preview.frames[i])
        np.testing.assert_allclose(stored.depth_map(i), preview.depth[i], rtol=1e-3)  # float16 on disk
    assert np.isnan(stored.depth_map(1)[:4, :4]).all()
    np.testing.assert_array_equal(stored.poses, preview.poses)
    np.testing.assert_array_equal(stored.times, preview.times)
    assert stored.intrinsics == preview.intrinsics and stored.fps == preview.fps
    p_mem, p_disk = place(preview, 0.2, 0.7, 0.3), place(stored, 0.2, 0.7, 0.3)
    assert p_disk.x == pytest.approx(p_mem.x, rel=1e-3)


def test_saving_again_replaces_the_preview_atomically(tmp_path):
    save_preview(make_preview(frames=2), tmp_path)
    save_preview(make_preview(frames=4), tmp_path)
    assert load_preview(tmp_path).num_frames == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["preview"]  # no temporary siblings left


def test_damaged_previews_are_refused(tmp_path):
    from core.integrity import seal_document
    from service.stored_preview import PreviewCorrupt

    with pytest.raises(FileNotFoundError):
        load_preview(tmp_path)
    save_preview(make_preview(), tmp_path)
    tensors = preview_dir(tmp_path) / TENSORS_FILE
    data = tensors.read_bytes()
    tensors.write_bytes(data[: len(data) // 2])
    with pytest.raises(PreviewCorrupt, match="checksum mismatch"):
        load_preview(tmp_path)
    # issue 14: flipped bytes inside the frames parsed fine and /frame served garbage
    save_preview(make_preview(), tmp_path)
    flipped = bytearray(tensors.read_bytes())
    flipped[-200:-100] = bytes(b ^ 0xFF for b in flipped[-200:-100])
    tensors.write_bytes(bytes(flipped))
    with pytest.raises(PreviewCorrupt, match="capture.safetensors: checksum mismatch"):
        load_preview(tmp_path)
    save_preview(make_preview(), tmp_path)
    meta_path = preview_dir(tmp_path) / META_FILE
    meta = json.loads(meta_path.read_text())
    meta_path.write_text(json.dumps({**meta, "fps": 99.0}))  # edited without a new checksum
    with pytest.raises(PreviewCorrupt, match="capture.json: checksum mismatch"):
        load_preview(tmp_path)
    meta_path.write_text(json.dumps({**meta, "version": 99}))
    with pytest.raises(PreviewError, match="version"):
        load_preview(tmp_path)
    meta_path.write_text(json.dumps(seal_document({**meta, "intrinsics": {**meta["intrinsics"], "width": W + 1}})))
    with pytest.raises(PreviewError, match="intrinsics"):
        load_preview(tmp_path)
    legacy = {k: v for k, v in meta.items() if k not in ("tensors_sha256", "document_sha256")}
    meta_path.write_text(json.dumps({**legacy, "version": 1}))  # written before checksums: still read
    assert load_preview(tmp_path).num_frames == make_preview().num_frames


def test_preview_from_capture_bounds_size_and_keeps_first_and_last_frames():
    from core.capture.load import capture_from_arrays

    frames = torch.rand(10, 90, 120, 3)
    depth = torch.full((10, 90, 120), 2.0)
    depth[:, 0, 0] = float("nan")
    cap = capture_from_arrays(frames, depth, fps=5.0)
    p = preview_from_capture(cap, max_height=30, max_frames=4)
    assert p.frames.shape == (4, 30, 40, 3) and p.frames.dtype == np.uint8
    np.testing.assert_allclose(p.times, [0.0, 0.6, 1.2, 1.8], atol=1e-6)  # frames 0, 3, 6, 9
    assert p.intrinsics["width"] == 40 and p.intrinsics["fx"] == pytest.approx(cap.intrinsics.fx / 3)
    assert np.nanmin(p.depth) == pytest.approx(2.0) and p.source_frames == 10
    assert Camera(Intrinsics(**p.intrinsics), torch.eye(4, dtype=torch.float64)).intrinsics.hfov_deg == pytest.approx(
        cap.intrinsics.hfov_deg)


def test_worker_hook_stores_the_capture_as_the_engine_loads_it_once(tmp_path):
    from core.capture.prepare import load_prepared_capture
    from core.engine.params import JobParams
    from core.io.images import write_png

    image = np.zeros((30, 40, 3), np.float32)
    image[:, 20:] = 1.0
    params = JobParams(intrinsics={"hfov_deg": 90.0})
    with pytest.warns(UserWarning):  # the assumed depth
        first = load_prepared_capture(write_png(tmp_path / "a.png", image), None, params)
        second = load_prepared_capture(write_png(tmp_path / "b.png", 1.0 - image), None, params)
    write_capture_preview(first, tmp_path / "job")
    stored = load_preview(tmp_path / "job")
    assert stored.num_frames == 1 and stored.frame(0)[0, 0].tolist() == [0, 0, 0]
    assert stored.intrinsics["fx"] == pytest.approx(20.0)  # hfov 90 deg over 40 px
    assert np.isfinite(stored.depth_map(0)).any()  # the engine's assumed depth, not nothing
    write_capture_preview(second, tmp_path / "job")  # a re-delivered job keeps its preview
    assert load_preview(tmp_path / "job").frame(0)[0, 0].tolist() == [0, 0, 0]
