"""HDR recovery across the frames of a moving camera (core.capture.hdr_merge): a lamp clipped in a
bright frame gets its radiance from a darker one; what no frame saw unclipped keeps the brightest
estimate; a reading from another surface (occlusion) is not merged."""
from __future__ import annotations

import math

import torch

from core.camera import Camera, Intrinsics
from core.capture.hdr_merge import capture_reading_weights, merge_frames, reading_weight
from core.capture.load import capture_from_arrays
from core.conventions import inverse_tonemap, tonemap
from core.sim.state import pose_from_yaw_pitch
from core.tracking.room import assumed_room, box_depth


def _panorama(h: int = 64) -> torch.Tensor:
    """A grey room with one small lamp 80x brighter straight ahead (-z) and a dim band below."""
    from core.conventions import equirect_directions

    d = equirect_directions(h)
    pano = torch.full((h, 2 * h, 3), 0.2)
    lamp = (d[..., 2] < -0.995)
    pano[lamp] = 16.0
    pano[d[..., 1] < -0.5] = 0.05
    return pano


def _frames(yaws, evs, size=(48, 36), hfov=60.0):
    from core.envmap import sample_envmap

    pano = _panorama()
    k = Intrinsics.from_hfov(size[0], size[1], hfov)
    poses = [pose_from_yaw_pitch((0.0, 0.0, 0.0), y, 0.0) for y in yaws]
    hdr = torch.stack(
        [sample_envmap(pano.double(), Camera(k, p).pixel_rays(dtype=torch.float64)[1]).float() for p in poses]
    )
    ldr = torch.stack([torch.round(tonemap(h, ev) * 255) / 255 for h, ev in zip(hdr, evs)])
    depth = box_depth(assumed_room(), [Camera(k, p) for p in poses])
    return hdr, ldr, depth, k, torch.stack(poses)


def _linear(ldr, evs):
    return torch.stack([inverse_tonemap(f) * 2.0 ** (-ev) for f, ev in zip(ldr, evs)])


def test_clipped_lamp_takes_its_radiance_from_the_darker_frame():
    evs = [0.0, -7.0]  # frame 0 clips the lamp (16 > 1), frame 1 (1/128) does not
    hdr, ldr, depth, k, poses = _frames([0.0, 8.0], evs)
    cap = capture_from_arrays(ldr, depth, intrinsics=k, poses=poses, frame_ev=evs)
    lin = _linear(ldr, evs)
    lamp = hdr[0].amax(-1) > 4.0
    assert bool(lamp.any()) and float(lin[0][lamp].mean()) < 1.5  # clipped: at most white
    merged = merge_frames(cap, lin, capture_reading_weights(cap))
    ratio = float(merged[0][lamp].mean() / hdr[0][lamp].mean())
    assert 0.7 < ratio < 1.3, ratio
    wall = hdr[0].amax(-1) < 0.3  # right in both frames: the merge keeps them (8-bit steps, edges aside)
    rel = (merged[0][wall] / hdr[0][wall] - 1.0).abs()
    assert float(rel.median()) < 0.03 and float(rel.quantile(0.95)) < 0.25


def test_clipped_everywhere_keeps_the_brightest_estimate():
    evs = [0.0, -1.0]  # the lamp clips in both: merging cannot know it, the darker frame bounds it higher
    hdr, ldr, depth, k, poses = _frames([0.0, 8.0], evs)
    cap = capture_from_arrays(ldr, depth, intrinsics=k, poses=poses, frame_ev=evs)
    lin = _linear(ldr, evs)
    merged = merge_frames(cap, lin, capture_reading_weights(cap))
    lamp = hdr[0].amax(-1) > 4.0
    assert float(merged[0][lamp].mean()) >= 0.95 * 2.0 ** 1.0 * float(ldr[0][lamp].mean() ** 2.4)


def test_no_overlap_no_change_and_weights():
    evs = [0.0, 0.0]
    hdr, ldr, depth, k, poses = _frames([0.0, 180.0], evs)  # back to back: nothing in common
    cap = capture_from_arrays(ldr, depth, intrinsics=k, poses=poses, frame_ev=evs)
    lin = _linear(ldr, evs)
    assert torch.equal(merge_frames(cap, lin, capture_reading_weights(cap)), lin)
    w = reading_weight(torch.tensor([0.0, 0.05, 0.5, 0.5]), torch.tensor([0.0, 0.0, 0.0, 1.0]))
    assert w.tolist() == [0.0, 0.5, 1.0, 0.0]


def test_other_surface_is_not_merged():
    """A reading whose depth disagrees (an occluder in front in the other frame) is left out."""
    evs = [0.0, -7.0]
    hdr, ldr, depth, k, poses = _frames([0.0, 8.0], evs)
    depth = depth.clone()
    depth[1] = depth[1] * 0.5  # frame 1 sees something else, nearer, everywhere
    cap = capture_from_arrays(ldr, depth, intrinsics=k, poses=poses, frame_ev=evs)
    lin = _linear(ldr, evs)
    merged = merge_frames(cap, lin, capture_reading_weights(cap))
    assert torch.allclose(merged[0], lin[0])
    assert math.isfinite(float(merged.sum()))
