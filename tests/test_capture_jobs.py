"""Real captures through the product (run_job / the CLI): a phone pan without poses, a photo
stored sideways, capture-app exports, and tracking that fails. Issue 13's end-to-end tests."""
from __future__ import annotations

import io
import json
import math
import warnings

import numpy as np
import pytest
import torch
from PIL import ExifTags, Image

from capture_fixtures import panorama_clip, walk_poses, write_nerfstudio, zip_dir
from core.engine.job import run_job
from core.engine.params import JobParams
from core.engine.presets import preset
from core.io.video import write_video
from core.sim.state import pose_from_yaw_pitch

TINY = preset("draft").with_overrides({"distill": {"iterations": 12, "work_height": 24, "warmup_steps": 2,
                                                   "checkpoint_every": 100}})


def _run(path, params: dict, out, depth=None, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return run_job(path, depth, JobParams.model_validate(params), out, config=TINY, **kw)


def test_static_light_phone_pan_is_tracked_and_does_not_vary_in_time(tmp_path):
    """Issue 13's first finding: a 3 s, 10 fps, 60 deg pan across a statically lit room with no
    poses. It must be tracked (not read as a static camera), its lighting must not be read as
    changing, and the env map at a fixed point must change by < 10 % over the clip."""
    poses = [pose_from_yaw_pitch((0, 0, 0), 60 * i / 29, 0) for i in range(30)]
    ldr, _, _ = panorama_clip(poses, 160, 120, pano_height=256, supersample=1)
    video = write_video(tmp_path / "pan.mp4", ldr.numpy(), 10.0)
    seen = []
    result = _run(video, {"fps": 10}, tmp_path / "field", on_capture=seen.append)
    meta = result.artefact.meta
    cap = meta["capture"]
    tracking = cap["metadata"]["tracking"]
    assert tracking["method"] == "rotation" and tracking["camera_moves"] and tracking["frames_dropped"] == []
    assert cap["static_camera"] is False
    assert "tracking" in meta["training"]["stage_timings"]
    assert meta["temporal"]["uses_time"] is False, meta["temporal"]["reason"]
    # the recovered pan: the last camera turned 60 deg about +y (within 1 deg)
    last = np.array(cap["poses"][-1]).reshape(4, 4)
    yaw = math.degrees(math.atan2(last[0, 2], last[2, 2]))
    assert abs(yaw - 60.0) < 1.0, yaw
    # the preview the page uses gets the tracked cameras, so probes stay put in the room
    assert len(seen) == 1 and not seen[0].static_camera
    # the env map at one point over the clip
    x = torch.tensor([0.0, 0.0, -1.0])
    maps = [result.artefact.envmap(x, t, 16)[0] for t in (0.0, 1.45, 2.9)]
    means = torch.stack([m.mean() for m in maps])
    assert float((means.max() - means.min()) / means.mean()) < 0.10


def _jpeg(a: np.ndarray, orientation: int | None = None, focal35: float | None = None) -> bytes:
    ex = Image.Exif()
    if orientation:
        ex[ExifTags.Base.Orientation] = orientation
    if focal35:
        ex.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = focal35
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, "JPEG", quality=100, subsampling=0, exif=ex)
    return buf.getvalue()


def test_the_same_walk_video_uploaded_twice_gets_the_same_answer(tmp_path):
    """A walk without poses goes through structure from motion (COLMAP), whose stages varied
    from run to run on two threads (core.tracking.sfm): a user resubmitting a video got other
    poses and another field. Now the poses and the env maps are identical."""
    ldr, _, _ = panorama_clip(walk_poses(10), 192, 144, centre=(0.0, 0.0, -1.0), pano_height=256, supersample=1)
    noisy = (
        torch.round((ldr + 0.02 * torch.randn(ldr.shape, generator=torch.Generator().manual_seed(7))).clamp(0, 1) * 255)
        / 255
    )
    video = write_video(tmp_path / "walk.mp4", noisy.numpy(), 10.0)
    a, b = (_run(video, {"fps": 10}, tmp_path / name).artefact for name in ("a", "b"))
    assert a.meta["capture"]["metadata"]["tracking"]["method"] == "sfm:pycolmap"
    # 9 or 10 of the 10 frames register, as the encoder's rate control leaves the noise; the same both times
    assert len(a.meta["capture"]["poses"]) >= 9 and a.meta["capture"]["poses"] == b.meta["capture"]["poses"]
    assert a.meta["capture"]["metadata"]["tracking"]["frames_kept"] == b.meta["capture"]["metadata"]["tracking"][
        "frames_kept"]
    for x, t in (((0.0, 0.0, 0.0), 0.0), ((0.3, -0.2, -1.0), 0.5)):
        assert torch.equal(a.envmap(torch.tensor(x), t, 16)[0], b.envmap(torch.tensor(x), t, 16)[0])


def test_rotated_exif_jpeg_gives_the_same_field_as_its_upright_twin(tmp_path):
    ldr, _, _ = panorama_clip([pose_from_yaw_pitch((0, 0, 0), 40, 0)], 64, 48, hfov=70.0, pano_height=128)
    upright = (ldr[0].numpy() * 255).round().astype(np.uint8)
    (tmp_path / "upright.jpg").write_bytes(_jpeg(upright, focal35=24))
    (tmp_path / "sideways.jpg").write_bytes(_jpeg(np.rot90(upright, 1).copy(), orientation=6, focal35=24))
    a = _run(tmp_path / "upright.jpg", {}, tmp_path / "a").artefact
    b = _run(tmp_path / "sideways.jpg", {}, tmp_path / "b").artefact
    for art in (a, b):
        cap = art.meta["capture"]
        assert (cap["width"], cap["height"]) == (64, 48)
        assert "FocalLengthIn35mmFilm" in cap["metadata"]["intrinsics_source"]  # EXIF, not the 60 deg guess
        assert not any("assuming a centred pinhole" in w for w in cap["warnings"])
    assert any("orientation 6" in n for n in b.meta["capture"]["metadata"]["applied"])
    assert a.meta["capture"]["intrinsics"] == b.meta["capture"]["intrinsics"]
    for x in ((0.0, 0.0, -1.0), (0.5, -0.3, -2.0)):
        ea, eb = a.envmap(torch.tensor(x), 0.0, 16)[0], b.envmap(torch.tensor(x), 0.0, 16)[0]
        assert float((ea - eb).abs().mean() / ea.abs().mean()) < 0.02


@pytest.fixture(scope="module")
def walk_capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("ns")
    poses = walk_poses(6)
    ldr, depth, intr = panorama_clip(poses, 80, 60, pano_height=128, supersample=1)
    return write_nerfstudio(root / "scan", ldr.numpy(), depth.numpy(), intr, [p.numpy() for p in poses]), poses


@pytest.mark.parametrize("as_zip", [False, True], ids=["directory", "zip"])
def test_nerfstudio_capture_through_the_cli(tmp_path, walk_capture, as_zip):
    from cli.main import main

    root, poses = walk_capture
    source = root
    if as_zip:
        source = tmp_path / "scan.zip"
        source.write_bytes(zip_dir(root, "scan/"))
    out = tmp_path / "field"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["estimate", str(source), "-o", str(out), "--iterations", "6", "--quiet",
                     "--params", json.dumps({"fps": 5})]) == 0
    cap = json.loads((out / "lightfield.json").read_text())["capture"]
    assert cap["frames"] == 6 and cap["metadata"]["poses_source"] == "nerfstudio transforms.json"
    assert "tracking" not in cap["metadata"]  # the app's poses are used, not re-estimated
    assert np.allclose(np.array(cap["poses"]).reshape(-1, 4, 4), torch.stack(poses).numpy(), atol=1e-9)
    assert cap["depth_source"].startswith("file:nerfstudio")
    assert cap["metadata"]["nerfstudio"]["camera_model"] == "PINHOLE"


def test_when_tracking_fails_the_job_still_succeeds_with_a_labelled_static_camera(tmp_path, monkeypatch):
    """The OpenCV tracker alone (LIGHTFIELD_SFM=opencv) cannot start on this small walk: the job
    is not refused, it says so and treats the camera as static."""
    monkeypatch.setenv("LIGHTFIELD_SFM", "opencv")
    ldr, _, _ = panorama_clip(walk_poses(12), 160, 120, pano_height=256)
    video = write_video(tmp_path / "walk.mp4", ldr.numpy(), 10.0)
    # the clip is encoded in the engine's convention: said so, it tracks as it was made to
    meta = _run(video, {"fps": 10, "transfer": "gamma:2.4"}, tmp_path / "field").artefact.meta
    cap = meta["capture"]
    assert cap["metadata"]["tracking"]["method"] == "failed:static-fallback"
    assert cap["static_camera"] is True
    assert any("camera tracking failed" in w for w in cap["warnings"])


def test_tracking_off_keeps_the_static_camera_and_says_so(tmp_path):
    poses = [pose_from_yaw_pitch((0, 0, 0), 20 * i / 5, 0) for i in range(6)]
    ldr, _, _ = panorama_clip(poses, 64, 48, pano_height=128, supersample=1)
    video = write_video(tmp_path / "pan.mp4", ldr.numpy(), 5.0)
    cap = _run(video, {"tracking": "off"}, tmp_path / "field").artefact.meta["capture"]
    assert cap["static_camera"] is True and cap["metadata"]["tracking"]["method"] == "off"


def test_given_poses_without_depth_get_the_assumed_room_fixed_in_the_world(tmp_path):
    from core.capture.params import CaptureParams
    from core.capture.prepare import load_prepared_capture
    from core.tracking.room import assumed_room

    poses = [pose_from_yaw_pitch((0.2 * i, 0, 0), 30 * i, 0) for i in range(4)]
    ldr, _, _ = panorama_clip(poses, 48, 36, pano_height=64, supersample=1)
    video = write_video(tmp_path / "moving.mp4", ldr.numpy(), 4.0)
    params = CaptureParams(poses=[p.reshape(-1).tolist() for p in poses])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cap = load_prepared_capture(video, params=params)
    assert cap.metadata["poses_source"] == "params" and "tracking" not in cap.metadata
    assert "world-fixed" in cap.depth_source and cap.metadata["room"]["source"] == "assumed"
    box = assumed_room(first_camera=poses[0])
    for i in (0, 3):  # every frame sees the same room, not one that turns with it
        assert torch.allclose(cap.depth[i], box.depth(cap.camera(i)))


def test_a_job_with_given_poses_and_no_depth_uses_the_world_fixed_room(tmp_path):
    poses = [pose_from_yaw_pitch((0.2 * i, 0, 0), 30 * i, 0) for i in range(4)]
    ldr, _, _ = panorama_clip(poses, 48, 36, pano_height=64, supersample=1)
    video = write_video(tmp_path / "moving.mp4", ldr.numpy(), 4.0)
    meta = _run(video, {"poses": [p.reshape(-1).tolist() for p in poses]}, tmp_path / "field").artefact.meta
    assert "world-fixed" in meta["capture"]["depth_source"]
    assert "tracking" not in meta["training"]["stage_timings"]  # nothing was tracked


def test_preview_of_a_pan_whose_tracking_dropped_a_frame_composites_into_the_frames_the_job_kept(tmp_path):
    """A frame tracking cannot register (noise) is left out of the job; `lightfield preview`
    loads the input again and must composite into the same 15 frames, cameras, exposures and
    room depth the job estimated from (it used to refuse: 15 poses for 16 frames)."""
    from cli.preview import render_preview
    from core.capture.reload import reload_capture
    from core.io.video import read_video

    poses = [pose_from_yaw_pitch((0, 0, 0), 40 * i / 15, 0) for i in range(16)]
    ldr, _, _ = panorama_clip(poses, 160, 120, pano_height=256, supersample=1)
    ldr = ldr.numpy().copy()
    ldr[9] = np.random.default_rng(0).random(ldr[9].shape)  # nothing in it to register
    video = write_video(tmp_path / "pan.mp4", ldr, 10.0)
    seen = []
    result = _run(video, {"fps": 10}, tmp_path / "field", on_capture=seen.append)
    record = result.artefact.meta["capture"]
    assert record["metadata"]["tracking"]["frames_dropped"] == [9] and record["frames"] == 15
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = reload_capture(video, None, record)
    job = seen[0]
    assert again.num_frames == 15 and torch.equal(again.times, job.times)
    assert torch.equal(again.frames, job.frames)
    assert torch.allclose(again.poses, job.poses, atol=1e-9)
    assert torch.allclose(again.depth, job.depth, atol=1e-5) and again.depth_source == job.depth_source
    assert again.intrinsics.as_dict() == pytest.approx(job.intrinsics.as_dict(), abs=1e-6)
    out = render_preview(tmp_path / "field", video, tmp_path / "preview.mp4")
    assert read_video(out).frames.shape[0] == 15
    png = render_preview(tmp_path / "field", video, tmp_path / "preview.png", frame=14)
    assert png.is_file()


def test_preview_refuses_an_input_that_is_not_the_one_estimated(tmp_path):
    from core.capture.base import CaptureError
    from core.capture.reload import reload_capture

    poses = [pose_from_yaw_pitch((0, 0, 0), 20 * i / 5, 0) for i in range(6)]
    ldr, _, _ = panorama_clip(poses, 64, 48, pano_height=128, supersample=1)
    video = write_video(tmp_path / "pan.mp4", ldr.numpy(), 5.0)
    other = write_video(tmp_path / "short.mp4", ldr.numpy()[:4], 5.0)
    record = _run(video, {"tracking": "off"}, tmp_path / "field").artefact.meta["capture"]
    with warnings.catch_warnings(), pytest.raises(CaptureError, match="estimated from 6"):
        warnings.simplefilter("ignore")
        reload_capture(other, None, record)


def test_preview_refuses_a_record_whose_poses_do_not_fit_its_frames(tmp_path):
    from core.capture.base import CaptureError
    from core.capture.reload import reload_capture

    poses = [pose_from_yaw_pitch((0, 0, 0), 0.0, 0.0)] * 3
    ldr, _, _ = panorama_clip(poses, 32, 24, pano_height=64, supersample=1)
    video = write_video(tmp_path / "still.mp4", ldr.numpy(), 5.0)
    record = {"frames": 3, "fps": 5.0, "duration_s": 0.4, "poses": [[1.0] * 16] * 2}
    with warnings.catch_warnings(), pytest.raises(CaptureError, match="do not describe 3 frames"):
        warnings.simplefilter("ignore")
        reload_capture(video, None, record)


def test_the_whole_job_runs_at_the_configured_torch_threads_and_restores_them(tmp_path):
    """distill.threads holds from the capture stage (tracking) to the end: two intra-op threads
    cost a room scan's job 79 s of CPU against 49 s on a 2-core box (docs/engine.md, "Device").
    The caller's setting comes back."""
    img = tmp_path / "room.png"
    Image.fromarray((np.random.default_rng(0).random((48, 64, 3)) * 255).astype(np.uint8)).save(img)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        seen = []
        _run(img, {}, tmp_path / "field", on_capture=lambda c: seen.append(torch.get_num_threads()))
        assert seen == [1] and TINY.distill.threads == 1
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
