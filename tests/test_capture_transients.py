"""Something moving through a static camera's view (a person walking through) is painted out,
not read as the light changing; a change of light, an exposure, a light switching late in the
clip, are left alone (core/capture/transients.py; docs/captures.md)."""
import math
import warnings

import pytest
import torch

from core.capture.config import capture_config
from core.capture.load import capture_from_arrays
from core.capture.params import CaptureParams
from core.capture.prepare import load_prepared_capture
from core.capture.temporal import detect_temporal
from core.capture.transients import transient_mask, without_transients
from core.conventions import inverse_tonemap, tonemap

T, H, W = 16, 72, 96


def room_lights() -> tuple[torch.Tensor, torch.Tensor]:
    """Two linear images [H, W, 3] of one textured room: what the light that stays gives it,
    and what a lamp at the right adds (a broad blob); albedo with posters and a floor."""
    g = torch.Generator().manual_seed(3)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    albedo = 0.35 + 0.3 * torch.nn.functional.avg_pool2d(torch.rand(1, 3, H, W, generator=g), 5, 1, 2)[0].permute(
        1, 2, 0
    )
    albedo[10:30, 15:40] = torch.tensor([0.7, 0.2, 0.15])  # a poster
    albedo[50:, :] *= 0.5  # the floor
    stay = albedo * (0.08 + 0.1 * (1 - yy))[..., None]
    lamp = albedo * (0.25 * torch.exp(-((xx - 0.8) ** 2 + (yy - 0.4) ** 2) / 0.05))[..., None]
    return stay, lamp


def frames_of(linear: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """8-bit LDR frames [T, H, W, 3] of linear frames with a little sensor noise."""
    g = torch.Generator().manual_seed(seed)
    ldr = tonemap(linear) + 0.01 * torch.randn(linear.shape, generator=g)
    return torch.round(ldr.clamp(0, 1) * 255) / 255


def lit(lamp_course) -> torch.Tensor:
    stay, lamp = room_lights()
    return torch.stack([stay + float(lamp_course(t)) * lamp for t in range(T)])


def walk_through(
    linear: torch.Tensor, brightness: float, first: int = 3, last: int = 12
) -> tuple[torch.Tensor, torch.Tensor]:
    """The clip with a textured figure (a sixth of the width, 70 % of the height) walking left to
    right over frames first..last; and where it is [T, H, W]."""
    g = torch.Generator().manual_seed(7)
    out, where = linear.clone(), torch.zeros(T, H, W, dtype=torch.bool)
    pw, ph = W // 6, int(H * 0.7)
    coat = (brightness * (0.7 + 0.6 * torch.rand(ph, pw, 3, generator=g)))
    for t in range(first, last + 1):
        x0 = round((t - first) / (last - first) * (W - pw))
        out[t, H - ph:, x0:x0 + pw] = coat
        where[t, H - ph:, x0:x0 + pw] = True
    return out, where


def static_capture(frames: torch.Tensor):
    n = frames.shape[0]
    return capture_from_arrays(frames, torch.full((n, H, W), 3.0), fps=4.0)


def iou(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a & b).sum()) / float((a | b).sum())


@pytest.mark.parametrize("brightness", [0.003, 0.5], ids=["dark-coat", "bright-coat"])
def test_a_person_walking_through_is_found_and_painted_out(brightness):
    steady = lit(lambda t: 1.0)
    walked, where = walk_through(steady, brightness)
    capture = static_capture(frames_of(walked))
    assert detect_temporal(capture).uses_time, "the figure reads as the light changing when left in"
    mask, evidence = transient_mask(capture)
    assert iou(mask, where) > 0.6 and float((mask & where).sum() / where.sum()) > 0.85
    cleaned = without_transients(capture, CaptureParams())
    assert not detect_temporal(cleaned).uses_time
    assert cleaned.metadata["transients"]["frames_with_transients"] >= 9
    assert any("moved through the view" in w for w in cleaned.warnings)
    clean = inverse_tonemap(frames_of(steady))
    before = (inverse_tonemap(capture.frames) - clean)[where].abs().mean()
    after = (inverse_tonemap(cleaned.frames) - clean)[where].abs().mean()
    assert after < 0.25 * before


@pytest.mark.parametrize("course,name", [
    (lambda t: 1.0 if t < 8 else 0.0, "lamp off at the middle"),
    (lambda t: 1.0 if t < 13 else 0.0, "lamp off in the last three frames"),
    (lambda t: 1.0 - 0.06 * t, "lamp dimming"),
    (lambda t: 0.0 if t < 5 else 1.0, "lamp on"),
])
def test_a_change_of_light_is_not_a_transient(course, name):
    capture = static_capture(frames_of(lit(course)))
    mask, evidence = transient_mask(capture)
    assert evidence["looked"] and not bool(mask.any()), (name, evidence)
    assert detect_temporal(without_transients(capture)).uses_time, name


def test_an_exposure_and_a_dimmed_room_are_not_transients():
    room = lit(lambda t: 1.0)
    scale = torch.tensor([1.0] * 8 + [0.5] * 8)[:, None, None, None]  # the room halved, or the exposure down a stop
    mask, _ = transient_mask(static_capture(frames_of(room * scale)))
    assert not bool(mask.any())
    ramp = 2.0 ** (torch.arange(T) / 8.0)[:, None, None, None]  # an auto-exposure drifting up two stops
    mask, _ = transient_mask(static_capture(frames_of(room * ramp)))
    assert not bool(mask.any())


def test_a_person_during_a_light_switch_is_found_and_the_switch_kept():
    walked, where = walk_through(lit(lambda t: 1.0 if t < 8 else 0.0), 0.003)
    capture = static_capture(frames_of(walked))
    mask, _ = transient_mask(capture)
    assert iou(mask, where) > 0.6
    cleaned = without_transients(capture)
    assert detect_temporal(cleaned).uses_time  # the lamp still switched off
    _, lamp = room_lights()
    near = torch.nn.functional.max_pool2d(where[:, None].float(), 9, 1, 4)[:, 0] > 0  # the mask grows at its edge
    lamp_only = (lamp.mean(-1) > 0.05)[None].expand(T, -1, -1) & ~near
    assert float(mask[lamp_only].float().mean()) < 0.02


def test_what_is_not_looked_at():
    walked, _ = walk_through(lit(lambda t: 1.0), 0.003)
    frames = frames_of(walked)
    few = static_capture(frames[:capture_config().transients.min_frames - 1])
    assert without_transients(few).frames.equal(few.frames)
    assert "fewer than" in without_transients(few).metadata["transients"]["reason"]
    capture = static_capture(frames)
    kept = without_transients(capture, CaptureParams(transients="keep"))
    assert kept.frames.equal(capture.frames) and "transients" not in kept.metadata
    with pytest.raises(ValueError):
        CaptureParams(transients="erase")


def test_a_video_upload_is_cleaned_on_load(tmp_path):
    """The real path: an H.264 file with no parameters, loaded and tracked as a job does."""
    from core.io.video import write_video

    walked, _ = walk_through(lit(lambda t: 1.0), 0.003)
    video = write_video(tmp_path / "walk.mp4", frames_of(walked).numpy(), 4.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        capture = load_prepared_capture(video, params=CaptureParams(fps=4.0))
    assert capture.static_camera
    assert capture.metadata["transients"]["frames_with_transients"] >= 9
    assert not detect_temporal(capture).uses_time
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        kept = load_prepared_capture(video, params=CaptureParams(fps=4.0, transients="keep"))
    assert detect_temporal(kept).uses_time


def test_a_job_on_a_video_with_a_passer_by_reads_static_light_and_previews_the_upload(tmp_path):
    """run_job as the CLI and the worker call it: the field gets no time input, the artefact
    records what was painted out, and the preview keeps the frames as uploaded."""
    from core.engine.job import run_job
    from core.engine.params import JobParams
    from core.engine.presets import preset
    from core.io.video import write_video

    walked, where = walk_through(lit(lambda t: 1.0), 0.003)
    video = write_video(tmp_path / "walk.mp4", frames_of(walked).numpy(), 4.0)
    tiny = preset("draft").with_overrides({"distill": {"iterations": 8, "work_height": 24, "warmup_steps": 2,
                                                       "checkpoint_every": 1000}})
    seen = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run_job(video, None, JobParams.model_validate({"fps": 4.0}), tmp_path / "out", config=tiny,
                         on_capture=seen.append)
    meta = result.artefact.meta
    assert meta["temporal"]["uses_time"] is False
    assert meta["capture"]["metadata"]["transients"]["frames_with_transients"] >= 9
    assert any("moved through the view" in w for w in meta["capture"]["warnings"])
    preview = seen[0].frames
    assert float((preview[where] - frames_of(walked)[where]).abs().mean()) < 0.05  # the figure is still there


def test_a_patterned_passer_by_in_front_of_a_plain_wall_leaves_the_camera_still(tmp_path):
    """Camera motion detection: the passer-by's features outnumber the wall's, so the median
    displacement of matched features is theirs; the wall's features that stayed put say the
    camera did not move (tracking.motion.still_min)."""
    from core.io.video import write_video
    from core.tracking.config import TrackingConfig, using_tracking

    g = torch.Generator().manual_seed(5)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    wall = (0.1 + 0.08 * xx + 0.04 * yy)[..., None].expand(H, W, 3).clone()
    for cx, cy in ((0.15, 0.2), (0.5, 0.15), (0.85, 0.25), (0.3, 0.5), (0.7, 0.55), (0.1, 0.7), (0.9, 0.7),
                   (0.5, 0.8)):  # a few picture frames
        wall[(((xx - cx).abs() < 0.05) & ((yy - cy).abs() < 0.06))] = torch.tensor([0.02, 0.02, 0.03])
    room = wall[None].expand(T, -1, -1, -1).clone()
    checks = (torch.rand(H // 4, W // 18, generator=g) > 0.5).float().repeat_interleave(3, 0).repeat_interleave(3, 1)
    pattern = (0.03 + 0.5 * checks)[..., None].expand(-1, -1, 3)  # a checked shirt: many corners
    pw, ph = pattern.shape[1], pattern.shape[0]
    where = torch.zeros(T, H, W, dtype=torch.bool)
    for t in range(2, 14):
        x0 = round((t - 2) / 11 * (W - pw))
        room[t, H - ph:, x0:x0 + pw] = pattern
        where[t, H - ph:, x0:x0 + pw] = True
    video = write_video(tmp_path / "shirt.mp4", frames_of(room).numpy(), 4.0)

    def loaded():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return load_prepared_capture(video, params=CaptureParams(fps=4.0))

    assert loaded().static_camera
    with using_tracking(TrackingConfig.model_validate({"motion": {"still_min": 10**9}})):  # every match's median
        assert not loaded().static_camera


def _pan(n: int = T):
    from capture_fixtures import panorama_clip
    from core.sim.state import pose_from_yaw_pitch

    poses = [pose_from_yaw_pitch((0, 0, 0), 60 * i / (n - 1), 3 * math.sin(i / 3)) for i in range(n)]
    ldr, depth, intr = panorama_clip(poses, W, H, pano_height=256, supersample=1)
    return inverse_tonemap(ldr), depth, intr, torch.stack([torch.as_tensor(p, dtype=torch.float64) for p in poses])


def test_a_person_crossing_a_pan_is_painted_from_the_neighbouring_frames():
    """A moving camera (poses and depth given): each frame against the median of it and its
    neighbours warped into it. The figure walks against the room's drift in the frame; walking
    with it (the camera following them) it covers a point of the room for most of the window
    and little of it is found (one-off: recall 0.01, against 0.83 crossing the other way)."""
    lin, depth, intr, poses = _pan()
    walked, where = walk_through(lin.flip(2), 0.003)  # right to left, against the room's drift in the frame
    walked, where = walked.flip(2), where.flip(2)
    raw = capture_from_arrays(frames_of(walked), depth, intrinsics=intr, poses=poses, fps=4.0)
    assert detect_temporal(raw).uses_time, "the figure reads as the light changing when left in"
    mask, evidence = transient_mask(raw)
    assert evidence["camera"] == "moving" and iou(mask, where) > 0.5
    cleaned = without_transients(raw)
    assert not detect_temporal(cleaned).uses_time
    assert any("neighbouring frames" in w for w in cleaned.warnings)


@pytest.mark.parametrize("change", ["halved", "pool-off", "walk"])
def test_a_moving_camera_without_passers_by_is_left_alone(change):
    from capture_fixtures import panorama_clip, walk_poses

    lin, depth, intr, poses = _pan()
    if change == "halved":
        lin = lin * torch.tensor([1.0] * 8 + [0.5] * 8)[:, None, None, None]
    elif change == "pool-off":  # a lamp's pool of light on the room's wall (in the panorama), off from frame 8
        from capture_fixtures import PANORAMA
        from core.camera import Camera
        from core.sim.panorama_room import PanoramaRoom, load_panorama
        from core.tracking.room import assumed_room

        pano = load_panorama(PANORAMA, 256)
        ph, pw = pano.shape[:2]
        yy, xx = torch.meshgrid(torch.linspace(0, 1, ph), torch.linspace(0, 1, pw), indexing="ij")
        lit_pano = pano * (1 + 2.0 * torch.exp(-((xx - 0.5) ** 2 + (yy - 0.55) ** 2) / 0.004))[..., None]
        room = PanoramaRoom(lit_pano, assumed_room(), torch.zeros(3))
        before = torch.stack([room.render(Camera(intr, p), 1)[0] for p in poses[:8]])
        lin = torch.cat((before, lin[8:]))
    else:
        walk = walk_poses(T)
        ldr, depth, intr = panorama_clip(walk, W, H, pano_height=256, supersample=1)
        lin, poses = inverse_tonemap(ldr), torch.stack([torch.as_tensor(p, dtype=torch.float64) for p in walk])
    capture = capture_from_arrays(frames_of(lin), depth, intrinsics=intr, poses=poses, fps=4.0)
    mask, evidence = transient_mask(capture)
    assert evidence["looked"] and float(mask.float().mean()) < 0.002, (change, evidence)


def test_a_still_camera_taken_for_moving_is_not_given_a_turn_from_its_pixels(monkeypatch):
    """Where the motion test is fooled (someone walking through a still view: the features say
    'moving'), neither the features nor the pixels must invent a turn: the photometric track of
    such a clip does not agree with itself (tracking.track.direct_min_matched_share), so the
    camera stays static instead of a garbage rotation that drops frames."""
    from core.camera import Intrinsics
    from core.tracking import track as tracking
    from core.tracking.motion import MotionDecision

    walked, _ = walk_through(lit(lambda t: 1.0), 0.003)
    frames = frames_of(walked)
    monkeypatch.setattr(
        tracking, "detect_motion", lambda features, width: MotionDecision(True, 1.0, 0.01, "forced", {})
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = tracking.track_camera(frames, Intrinsics.from_hfov(frames.shape[2], frames.shape[1], 60.0))
    assert result.method in ("failed:static-fallback", "static") or (
        result.method == "rotation" and len(result.kept) == frames.shape[0]
        and float(result.poses[:, :3, :3].diagonal(dim1=1, dim2=2).sum(-1).min()) > 2.99)  # no turn invented
