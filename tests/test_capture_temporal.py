"""Temporal detection: static clips (with noise / compression) get no time input, switching
lights and dimming do; overrides and single frames."""
import math

import numpy as np
import pytest
import torch

from core.capture.load import capture_from_arrays
from core.capture.temporal import decide_temporal, detect_temporal
from core.conventions import tonemap

H, W = 72, 96


def _albedo(seed=0):
    g = torch.Generator().manual_seed(seed)
    return 0.2 + 0.6 * torch.rand(H // 8, W // 8, 3, generator=g).repeat_interleave(8, 0).repeat_interleave(8, 1)


def _lamp(center=(20, 25), radius=30.0):
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    r2 = (v - center[0]) ** 2 + (u - center[1]) ** 2
    return 1.5 * torch.exp(-r2 / (2 * radius**2))[..., None]


def _frames(lamp_on, ambient=0.15, noise=0.0, quantise=True, seed=0):
    """LDR frames of a Lambertian wall lit by an ambient term plus a lamp blob."""
    g = torch.Generator().manual_seed(seed)
    alb = _albedo()
    out = []
    for on in lamp_on:
        rad = alb * (ambient + (_lamp() if on else 0.0))
        ldr = tonemap(rad) + noise * torch.randn(H, W, 3, generator=g)
        ldr = ldr.clamp(0, 1)
        if quantise:
            ldr = torch.round(ldr * 255) / 255
        out.append(ldr)
    return torch.stack(out)


def _jpeg_roundtrip(frames, quality=40):
    import cv2

    out = []
    for f in frames.numpy():
        ok, buf = cv2.imencode(".jpg", (f * 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, quality])
        out.append(cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).astype(np.float32) / 255)
    return torch.from_numpy(np.stack(out))


def test_single_frame_has_no_time():
    d = detect_temporal(capture_from_arrays(_frames([True])))
    assert not d.uses_time and "single frame" in d.reason
    # even forced on, one frame cannot carry time
    assert not decide_temporal(capture_from_arrays(_frames([True])), "on").uses_time


@pytest.mark.parametrize("noise", [0.0, 0.02])
def test_static_noisy_video_is_static(noise):
    d = detect_temporal(capture_from_arrays(_frames([True] * 8, noise=noise, seed=1)))
    assert not d.uses_time, d.reason
    assert d.statistic < d.threshold


def test_static_compressed_video_is_static():
    frames = _jpeg_roundtrip(_frames([True] * 6, noise=0.01))
    d = detect_temporal(capture_from_arrays(frames))
    assert not d.uses_time, d.reason


def test_lamp_switching_off_is_temporal():
    d = detect_temporal(capture_from_arrays(_frames([True] * 4 + [False] * 4, noise=0.02)))
    assert d.uses_time, d.reason
    assert d.statistic > 2 * d.threshold


def test_a_moving_camera_that_could_not_be_tracked_is_never_read_as_a_change_of_light():
    """The same frames that read as a switch from a still camera read as static light when tracking
    found the camera moving and registered no track (the frames stand at a pose not theirs)."""
    capture = capture_from_arrays(_frames([True] * 4 + [False] * 4, noise=0.02))
    assert detect_temporal(capture).uses_time
    capture.metadata["tracking"] = {"method": "failed:static-fallback", "camera_moves": True}
    d = detect_temporal(capture)
    assert not d.uses_time and "could not be tracked" in d.reason
    capture.metadata["tracking"] = {"method": "static", "camera_moves": False}  # a still camera: a switch again
    assert detect_temporal(capture).uses_time


def test_global_dimming_is_temporal_and_compression_does_not_hide_it():
    frames = torch.stack([tonemap(_albedo() * 0.5 * s) for s in (1.0, 1.0, 0.6, 0.6)])
    d = detect_temporal(capture_from_arrays(_jpeg_roundtrip(frames)))
    assert d.uses_time, d.reason


def test_overrides_keep_the_evidence():
    cap = capture_from_arrays(_frames([True] * 4))
    auto = detect_temporal(cap)
    on, off = decide_temporal(cap, "on"), decide_temporal(cap, "off")
    assert on.uses_time and not off.uses_time
    assert on.statistic == auto.statistic and "forced on" in on.reason and on.mode == "on"
    with pytest.raises(ValueError, match="temporal"):
        decide_temporal(cap, "sometimes")


def test_fully_saturated_video_does_not_crash():
    d = detect_temporal(capture_from_arrays(torch.ones(4, H, W, 3)))
    assert not d.uses_time and "usable" in d.reason


def test_moving_camera_static_lighting_is_static_after_reprojection():
    """A textured back wall seen by a panning-sideways camera: raw frames differ a lot, the
    reprojected ones do not."""
    from core.camera import Camera, Intrinsics

    k = Intrinsics.from_hfov(W, H, 60.0)
    z_wall = 3.0
    frames, depths, poses = [], [], []
    for i in range(4):
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[0, 3] = 0.15 * i
        cam = Camera(k, c2w)
        origin, dirs = cam.pixel_rays(dtype=torch.float64)
        s = z_wall / -dirs[..., 2]
        p = origin + s[..., None] * dirs  # points on the wall z = -3
        tex = 0.3 + 0.25 * (torch.sin(7 * p[..., 0]) * torch.cos(5 * p[..., 1]))[..., None].expand(H, W, 3)
        frames.append(tonemap(tex.float()))
        depths.append(torch.full((H, W), z_wall))
        poses.append(c2w)
    cap = capture_from_arrays(torch.stack(frames), torch.stack(depths), intrinsics=k, poses=torch.stack(poses))
    assert not cap.static_camera
    d = detect_temporal(cap)
    assert not d.uses_time, d.reason
    assert "motion compensated" in d.reason
    # and the same pan with the light halved in the second half is temporal
    frames2 = torch.stack([f if i < 2 else tonemap(torch.pow(f, 2.4) * 0.5) for i, f in enumerate(frames)])
    cap2 = capture_from_arrays(frames2, torch.stack(depths), intrinsics=k, poses=torch.stack(poses))
    assert detect_temporal(cap2).uses_time


def test_a_pan_that_leaves_its_first_view_compares_neighbours():
    """A 60 deg pan with a 60 deg FOV: the last frame shares nothing with the first. Static
    light is static; a lamp switching on half-way (a 1.6x step) is temporal."""
    from pathlib import Path

    from core.camera import Camera, Intrinsics
    from core.sim.panorama_room import PanoramaRoom, load_panorama, render_clip
    from core.sim.state import pose_from_yaw_pitch
    from core.tracking.room import assumed_room

    pano = load_panorama(Path(__file__).resolve().parents[1] / "assets" / "sample_panorama.hdr", 128)
    k = Intrinsics.from_hfov(96, 72, 60.0)
    poses = [pose_from_yaw_pitch((0, 0, 0), 60 * i / 19, 0) for i in range(20)]
    room = PanoramaRoom(pano, assumed_room(), torch.zeros(3))
    _, depth, hdr = render_clip(room, [Camera(k, p) for p in poses], supersample=1)
    from core.sim.panorama_room import ldr_clip

    for gain, temporal in ((1.0, False), (1.6, True)):
        g = torch.tensor([1.0] * 10 + [gain] * 10)[:, None, None, None]
        cap = capture_from_arrays(ldr_clip(hdr * g), depth, intrinsics=k, poses=torch.stack(poses), fps=10)
        d = detect_temporal(cap)
        assert d.uses_time == temporal, d.reason
        assert "motion compensated" in d.reason
    assert d.statistic == pytest.approx(math.log(1.6), rel=0.1)


def test_dark_noisy_static_room_is_static():
    """Most pixels hover around the near-black cut-off; noise moves them across it from frame
    to frame, which must not read as a lighting change (same pixel set in every frame)."""
    g = torch.Generator().manual_seed(3)
    rad = _albedo() * 0.0004  # LDR ~ 0.02-0.04
    frames = torch.stack([(tonemap(rad) + 0.01 * torch.randn(H, W, 3, generator=g)).clamp(0, 1) for _ in range(8)])
    d = detect_temporal(capture_from_arrays(torch.round(frames * 255) / 255))
    assert not d.uses_time, d.reason


def test_a_pan_sees_a_pool_of_light_switch_off_in_part_of_the_view():
    """A lamp's pool (2x at its centre, 20 deg wide) on part of the room goes off half-way
    through a pan: no whole-view change (the median block moves little), a local one."""
    from bench.pan_light_changes import pan_capture, pool

    d = detect_temporal(pan_capture(pool(gain=2.0, width=20.0, centre=0.0)))
    assert d.uses_time, d.reason
    assert "local" in d.reason


def test_something_dark_walking_along_the_wall_of_a_pan_is_not_light(monkeypatch):
    """A dark figure (a fifth of the room's mean, 12 deg wide, soft-edged) walking 3 deg per
    frame along the wall while the camera pans: its edges carry light between neighbouring
    blocks, which the 3 x 3 neighbourhood's means keep; block by block it reads as a change."""
    import core.capture.temporal as temporal
    from bench.pan_light_changes import drift, pan_capture

    cap = pan_capture(drift(brightness=0.2, speed=3.0))
    d = detect_temporal(cap)
    assert not d.uses_time, d.reason
    monkeypatch.setattr(temporal, "NEIGHBOURHOOD", 1)
    assert detect_temporal(cap).uses_time  # what the statistic read before it looked at neighbourhoods


@pytest.mark.slow
def test_simulator_suites_hard_is_static_temporal_is_not(tmp_path):
    """The `hard` suite (static lights; dolly camera, noise, compression, saturated windows)
    read as temporal before linear-space resampling; the `temporal` suite switches a panel."""
    import warnings

    from core.capture.prepare import load_prepared_capture
    from core.sim.capture import write_capture
    from core.sim.suites import hard, temporal

    decisions = {}
    for name, spec in (("hard", hard()), ("temporal", temporal())):
        frames = 4 if name == "hard" else spec.frames
        small = spec.model_copy(update={"frames": frames, "resolution": (96, 72), "probes": []})
        write_capture(small, tmp_path / name, envmap_height=8, video=False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            decisions[name] = detect_temporal(load_prepared_capture(tmp_path / name))
    assert not decisions["hard"].uses_time, decisions["hard"].reason
    assert decisions["hard"].statistic < 0.75 * decisions["hard"].threshold
    assert decisions["temporal"].uses_time, decisions["temporal"].reason


def _window_with_a_ringing_edge(ring_gain: float) -> torch.Tensor:
    """8 frames [T, 36, 48, 3] of a still room with a clipped window, the 2-pixel band round the
    window brightened by `ring_gain` in every other frame (what a codec's ringing at a saturated
    edge does as the frames are encoded apart)."""
    frames = []
    for i in range(8):
        f = torch.full((36, 48, 3), 0.35)
        f[10:26, 14:34] = 1.0  # the window, clipped
        band = torch.zeros(36, 48, dtype=torch.bool)
        band[8:28, 12:36] = True
        band[10:26, 14:34] = False
        f[band] = 0.35 * (ring_gain if i % 2 else 1.0)
        frames.append(torch.round(f * 255) / 255)
    return torch.stack(frames)


def test_what_rings_round_a_clipped_source_is_not_light(monkeypatch):
    """Pixels within CLIP_MARGIN of a clipped one are left out: the band round the window is
    not read as the light changing; without the margin it is."""
    import core.capture.temporal as temporal

    cap = capture_from_arrays(_window_with_a_ringing_edge(1.6))
    assert not detect_temporal(cap).uses_time
    monkeypatch.setattr(temporal, "CLIP_MARGIN", 0)
    assert detect_temporal(cap).uses_time
