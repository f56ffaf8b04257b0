"""Photometric rotation tracking (core.tracking.direct) on room scans with known answers.

Scans are rendered from the bundled CC0 panorama (core.sim.room_scan: rings at pitch +10,
+55 and -40 degrees with tilts between, hand jitter, a lagging auto-exposure, 8-bit frames),
so every frame's true rotation and exposure are known.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.sim.panorama_room import load_panorama
from core.sim.room_scan import render_scan
from core.tracking.direct import align_pair, exposure_from_offsets, frame_luma, track_rotation_direct
from core.tracking.geometry import rotation_angle_deg

PANORAMA = Path(__file__).resolve().parents[1] / "assets" / "sample_panorama.hdr"


@pytest.fixture(scope="module")
def scan():
    return render_scan(load_panorama(PANORAMA, 256), yaw0=30.0, seed=3)


def _rotation_errors(track, clip) -> list[float]:
    """Per kept frame, the angle between its tracked rotation and the truth, both relative to
    the first kept frame."""
    true = [p[:3, :3].double().numpy() for p in clip.poses]
    base = true[track.kept[0]]
    est0 = track.rotations[0]
    return [rotation_angle_deg((base.T @ true[f]).T @ (est0.T @ track.rotations[n])) for n, f in enumerate(track.kept)]


def test_one_pair_recovers_its_turn_and_exposure_step(scan):
    """Two consecutive scan frames: the rotation within a fraction of a degree and the exposure
    step (stops) within a tenth, from the identity as the only guess."""
    l, v = frame_luma(scan.ldr[3:5])
    pair = align_pair(l[0], v[0], l[1], v[1], scan.intrinsics, [np.eye(3)], 3, 4)
    true = (scan.poses[4][:3, :3].T @ scan.poses[3][:3, :3]).double().numpy()  # bearing 3 -> bearing 4
    assert pair.trusted
    assert rotation_angle_deg(pair.R.T @ true) < 0.5
    assert abs(pair.log_gain / np.log(2.0) - (scan.evs[4] - scan.evs[3])) < 0.1


@pytest.mark.slow  # 46 frames, ~40 s of CPU
def test_a_room_scan_is_tracked_through_its_tilts_and_exposure_changes(scan):
    """Every frame of a three-ring scan placed within 1.5 degrees (no features, no poses), and its
    exposure course from the overlaps within 0.15 stops of the truth, over a span of stops."""
    track = track_rotation_direct(scan.ldr, scan.intrinsics)
    assert track.kept == list(range(len(scan.poses))) and not track.dropped
    errors = _rotation_errors(track, scan)
    assert max(errors) < 1.5, errors
    ev = exposure_from_offsets(track.pairs, track.kept)
    true = np.array(scan.evs) - scan.evs[0]
    assert scan.span_stops > 1.5
    assert np.abs(ev - true).max() < 0.15


def test_a_first_frame_nothing_registers_is_dropped_not_trusted():
    """A first frame no pair can fix (a lens cap, a blank frame) must not set the world's axes:
    the track starts at the first frame of the largest connected set, and the frames before it
    are dropped, the rest still right."""
    clip = render_scan(load_panorama(PANORAMA, 256), yaw0=30.0, seed=3)
    frames = clip.ldr[:8].clone()
    frames[0] = 0.5  # blank grey
    track = track_rotation_direct(frames, clip.intrinsics)
    assert track.dropped == [0] and track.kept[0] == 1
    assert max(_rotation_errors(track, clip)) < 1.0


def test_a_pair_with_nothing_in_common_near_its_guess_is_unmatched_not_an_error(scan):
    """Guessing the camera turned half-way round: no rotation the search tries keeps the
    frames overlapping, and the pair comes back unmatched (cost inf), as a blank frame does."""
    l, v = frame_luma(scan.ldr[3:5])
    half_turn = np.diag([-1.0, 1.0, -1.0])  # 180 deg about y
    pair = align_pair(l[0], v[0], l[1], v[1], scan.intrinsics, [half_turn], 3, 4, span=10.0, candidates=4)
    assert not pair.matched and not pair.trusted and pair.cost == float("inf")
