"""The job's self-check (core.engine.self_check): frames re-rendered from a field at their own
cameras and times, against the constant map's residual. A field that explains the frames is
graded so; one that misreads them (a track 90 deg off, a wrong exposure course) is graded worse
than a constant map."""
from __future__ import annotations

import math

import torch

from core.camera import Camera, Intrinsics
from core.capture.load import capture_from_arrays
from core.conventions import tonemap
from core.engine.self_check import GRADES, failed_stage, self_check


def sky(d: torch.Tensor, gain: torch.Tensor | float = 1.0) -> torch.Tensor:
    """Radiance arriving from direction d: a bright window towards +x, a dim floor, a warm wall."""
    window = 4.0 * torch.exp(-((d[..., 0] - 0.9) ** 2 + d[..., 1] ** 2) / 0.1)
    base = torch.stack((0.3 + 0.2 * d[..., 1], 0.25 + 0.1 * d[..., 2], 0.2 - 0.1 * d[..., 1]), -1)
    return (base + window[..., None] * torch.tensor([1.0, 0.9, 0.8])) * gain


def yaw(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    p = torch.eye(4, dtype=torch.float64)
    p[0, 0], p[0, 2], p[2, 0], p[2, 2] = math.cos(a), math.sin(a), -math.sin(a), math.cos(a)
    return p


def turning_capture(evs=None):
    """A camera turning on the spot over 8 frames (a pan through the window), frames in the
    engine's convention with their exposures stated."""
    k = Intrinsics.from_hfov(48, 32, 70.0)
    poses = torch.stack([yaw(-20.0 * i) for i in range(8)])
    frames = []
    evs = torch.zeros(8) if evs is None else evs
    for i in range(8):
        _, d = Camera(k, poses[i]).pixel_rays()
        frames.append(tonemap(sky(d) * 0.15, float(evs[i])))
    return capture_from_arrays(torch.stack(frames), torch.full((8, 32, 48), 3.0), intrinsics=k, poses=poses,
                               frame_ev=evs)


def field_of(fn):
    return lambda x, t, d: fn(d)


def test_a_field_that_holds_the_light_explains_the_frames():
    q = self_check(field_of(lambda d: sky(d) * 0.15), turning_capture(), uses_time=False)
    assert q["grade"] == GRADES[0], q
    assert q["residual_ratio"] < 0.1 and q["frames_explained"] == q["frames_checked"] == 8


def test_a_field_rotated_by_a_misread_track_is_graded_worse_than_a_constant_map():
    turned = yaw(90.0)[:3, :3].float()
    q = self_check(field_of(lambda d: sky(d @ turned.T) * 0.15), turning_capture(), uses_time=False)
    assert q["grade"] == GRADES[2] and q["residual_ratio"] > 1.0, q


def test_a_wrong_exposure_course_is_caught():
    """The frames were taken at exposures 0..-7 stops, but the field (and the capture, as read)
    have them all at 0: every frame's level is off by its exposure."""
    capture = turning_capture(evs=-torch.arange(8.0))
    wrong = capture_from_arrays(capture.frames, capture.depth, intrinsics=capture.intrinsics, poses=capture.poses)
    q = self_check(field_of(lambda d: sky(d) * 0.15), wrong, uses_time=False)
    assert q["grade"] != GRADES[0] and q["residual_ratio"] > 1.0, q


def test_nothing_usable_is_said_so_not_graded():
    capture = capture_from_arrays(torch.ones(2, 16, 24, 3))  # every pixel clipped
    q = self_check(field_of(lambda d: sky(d)), capture, uses_time=False)
    assert q["grade"] is None and q["frames_checked"] == 0


def test_the_failed_stage_is_named():
    capture = turning_capture()
    assert failed_stage(capture) is None
    capture.metadata["tracking"] = {"method": "failed:static-fallback", "camera_moves": True}
    assert "tracking" in failed_stage(capture)


def test_the_seen_share_is_what_the_frames_cover_of_the_sphere():
    from core.engine.self_check import seen_share

    one = capture_from_arrays(torch.full((1, 32, 48, 3), 0.5), intrinsics=Intrinsics.from_hfov(48, 32, 70.0))
    share = seen_share(one)
    assert 0.05 < share < 0.2, share  # a 70 x 49 deg view: about a tenth of the sphere
    assert seen_share(turning_capture()) > 2 * share  # the pan's 8 views turning 140 deg
