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
from core.tracking.config import tracking_config
from core.tracking.direct import (
    DirectPair,
    _better_of,
    align_pair,
    exposure_from_offsets,
    frame_luma,
    track_rotation_direct,
)
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


def test_the_grid_search_ranks_in_single_precision_to_the_same_answer_as_in_double(scan, monkeypatch):
    """The full grid (two starts, the camera coasting and standing still: about 4,400 candidates)
    ranked in single precision picks the same turn as in double: the pair's rotation within
    0.01 degrees and its cost within 1e-4 of itself, within a ring, where a ring starts to tilt
    up, and on the tilt down between two rings (a 40 degree turn)."""
    import torch

    import core.tracking.direct as direct

    l, v = frame_luma(scan.ldr)
    R = [p[:3, :3].double().numpy() for p in scan.poses]
    for i, j in ((3, 4), (15, 16), (30, 31)):
        coast = R[i].T @ R[i - 1]  # the previous pair's true turn, repeated
        answers = {}
        for dtype in (torch.float32, torch.float64):
            monkeypatch.setattr(direct, "GRID_DTYPE", dtype)
            answers[dtype] = align_pair(l[i], v[i], l[j], v[j], scan.intrinsics, [coast, np.eye(3)], i, j)
        single, double = answers[torch.float32], answers[torch.float64]
        assert double.trusted and single.trusted
        assert rotation_angle_deg(double.R.T @ (R[j].T @ R[i])) < 0.5  # the right turn
        assert rotation_angle_deg(single.R.T @ double.R) < 0.01
        assert single.cost == pytest.approx(double.cost, rel=1e-4)


def test_the_full_grid_replaces_a_near_answer_only_where_it_fits_as_well_as_usual_or_explains_as_much(scan):
    """A consecutive pair's near answer (its guesses) against the full grid's: a wrong basin that
    keeps a sliver of blank overlap can be cheaper than the right turn and explain less of frame
    i's texture (the score); a right turn between rings overlaps little and can explain less
    than a wrong one over a smooth wall, but fits at the clip's usual cost. The full grid's
    answer replaces the near one when it is cheaper and either fits as well as the usual pair or
    explains at least as much, or when the near one is not trusted."""
    l, v = frame_luma(scan.ldr[3:5])
    near = align_pair(l[0], v[0], l[1], v[1], scan.intrinsics, [np.eye(3)], 3, 4)
    assert near.trusted and near.score < 0  # explains more of the texture than it leaves
    wrong = np.diag([-1.0, 1.0, -1.0])
    sliver = tracking_config().direct.min_overlap
    cheaper_blank = DirectPair(3, 4, wrong, 0.0, near.cost / 2, sliver, near.info, score=near.score / 10)
    cheaper_explains_more = DirectPair(3, 4, wrong, 0.0, near.cost / 2, sliver, near.info, score=near.score * 1.1)
    costlier = DirectPair(3, 4, wrong, 0.0, near.cost * 2, near.overlap, near.info, score=near.score * 1.1)
    assert cheaper_blank.trusted and cheaper_explains_more.trusted
    above_usual, usual = near.cost / 4, near.cost
    assert _better_of(near, cheaper_blank, above_usual) is near
    assert _better_of(near, cheaper_blank, usual) is cheaper_blank
    assert _better_of(near, cheaper_explains_more, above_usual) is cheaper_explains_more
    assert _better_of(near, costlier, usual) is near
    untrusted_near = DirectPair(3, 4, near.R, 0.0, near.cost, near.overlap)  # no information: fixes nothing
    assert _better_of(untrusted_near, cheaper_blank, above_usual) is cheaper_blank


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


@pytest.mark.slow  # 46 frames, ~40 s of CPU
def test_a_scan_tracked_with_a_wrong_focal_length_fits_it_from_its_loop_closures(scan):
    """The intrinsics assumed 3.5 % off (a 58 deg guess for a 60 deg lens): registered with that
    focal length every ring comes round a few degrees short or long; with `refine_focal` the loop
    closures fit the focal length within 0.5 % and every frame falls within a degree."""
    from core.camera import Intrinsics

    k = scan.intrinsics
    wrong = Intrinsics.from_hfov(k.width, k.height, k.hfov_deg - 2.0)
    plain = track_rotation_direct(scan.ldr, wrong)
    fitted = track_rotation_direct(scan.ldr, wrong, refine_focal=True)
    assert max(_rotation_errors(plain, scan)) > 2.0  # what the wrong focal length costs
    assert fitted.stats["focal_scale_applied"]
    assert abs(wrong.fx / fitted.focal_scale / k.fx - 1.0) < 0.005
    assert max(_rotation_errors(fitted, scan)) < 1.0


def test_a_short_turn_without_loop_closures_keeps_its_focal_length(scan):
    """Six frames of one ring never come round: any focal length explains their consecutive
    pairs, so the fit must not move it (the chi-square test keeps s = 1)."""
    from core.camera import Intrinsics

    k = scan.intrinsics
    wrong = Intrinsics.from_hfov(k.width, k.height, k.hfov_deg - 2.0)
    track = track_rotation_direct(scan.ldr[:6], wrong, refine_focal=True)
    assert track.stats["loop_pairs"] == 0
    assert not track.stats["focal_scale_applied"] and track.focal_scale == 1.0


def test_the_finer_levels_keep_distinct_candidates_not_copies_of_one_basin():
    """Survivors are picked by score but each more than a grid step from the others: the many
    near-copies of one basin the local grid puts at the top must not crowd out a second basin
    (the right turn, when a wrong one scores a little better on a coarse level), and the
    cheapest candidate is kept besides."""
    import torch

    from core.tracking.direct import _survivors
    from core.tracking.geometry import rotvec_to_matrix

    angles = np.radians([0.0, 0.5, 1.0, 1.5, 20.0, 40.0])  # yaw: a basin of four copies, two others
    R = torch.from_numpy(rotvec_to_matrix(np.stack([np.zeros(6), angles, np.zeros(6)], -1)))
    texture = torch.ones(4, dtype=torch.float64)
    # residuals: the copies explain every pixel, the 20 deg one three of four, the 40 deg none
    r = torch.tensor([[0.0] * 4] * 4 + [[0.0, 0.0, 0.0, 1.0], [1.0] * 4], dtype=torch.float64)
    w = torch.ones_like(r)
    picked = _survivors(r, w, texture, 2, R).tolist()
    assert picked[:2] == [0, 4]
    for a in picked:
        for b in picked:
            if a < b:
                assert abs(np.degrees(angles[a] - angles[b])) > tracking_config().direct.search_step_deg


def test_a_candidate_whose_gauss_newton_system_is_singular_stays_put_instead_of_failing_the_job():
    """In single precision (the grid's ranking) the 1e-9 damping is lost in rounding: a
    candidate whose residuals move the same way under two turns (a sliver of overlap, one
    textured edge) has an exactly singular system. It keeps its rotation and gain (the demo's
    room scan stopped on this with a LinAlgError on one machine's CPU kernels)."""
    import torch

    from core.tracking.direct import _refine

    class OneEdge:  # a level whose residual sees only the sum of the turns about y and z
        li = torch.zeros(100)

        def residuals(self, R, g):
            r = (R[:, 0, 1] - R[:, 0, 2] - 0.01)[:, None].expand(-1, 100)
            return r.float(), torch.ones_like(r, dtype=torch.float32)

    R0 = torch.eye(3).expand(2, 3, 3).clone()
    R, g = _refine(OneEdge(), R0, torch.zeros(2), iterations=2)
    assert torch.isfinite(R).all() and torch.isfinite(g).all()
    assert torch.equal(R, R0) and torch.equal(g, torch.zeros(2))


def _reference_residuals(li, vi, lj, vj, k, height, R, gain):
    """The lookup written out the plain way: project each of frame i's usable pixels through R
    with the level's intrinsics, read frame j's luma with border padding and its mask with zero
    padding in two lookups, and keep the pixels in front of frame j and inside its edges."""
    import torch
    import torch.nn.functional as F

    from core.tracking.direct import _level, _pixel_bearings

    Li, Vi = _level(li, vi, height)
    Lj, Vj = _level(lj, vj, height)
    h, w = Li.shape
    s = k.scaled(w, h)
    b = _pixel_bearings(h, w, k).reshape(-1, 3)[Vi.reshape(-1) > 0.5]
    d = torch.einsum("sij,nj->sni", R, b)
    z = (-d[..., 2]).clamp_min(1e-6)
    u, v = s.fx * d[..., 0] / z + s.cx, -s.fy * d[..., 1] / z + s.cy
    grid = torch.stack([2.0 * u / w - 1.0, 2.0 * v / h - 1.0], -1)[:, None]
    n = R.shape[0]
    lj_ = F.grid_sample(Lj.expand(n, 1, h, w), grid, align_corners=False, padding_mode="border")[:, 0, 0]
    vj_ = F.grid_sample(Vj.expand(n, 1, h, w), grid, align_corners=False, padding_mode="zeros")[:, 0, 0]
    inside = (-d[..., 2] > tracking_config().direct.min_depth) & (u > 0) & (u < w) & (v > 0) & (v < h)
    return lj_ - torch.exp(gain)[:, None] * Li.reshape(-1)[Vi.reshape(-1) > 0.5], inside & (vj_ > 0.999)


def test_the_folded_projection_reads_what_the_plain_projection_reads(scan):
    """The lookup folds rotation, intrinsics and the margined image's coordinates into one 3 x 3
    map per candidate and reads luma and mask in one two-channel lookup (a scan's tracking
    time): for turns up to 40 degrees, with an off-centre principal point, it must give the
    plain projection's residuals and in-view pixels."""
    import torch

    from core.camera import Intrinsics
    from core.tracking.direct import _Level
    from core.tracking.geometry import rotvec_to_matrix

    l, v = frame_luma(scan.ldr[3:5])
    k0 = scan.intrinsics
    k = Intrinsics(k0.fx * 1.1, k0.fy * 1.1, k0.cx + 7.0, k0.cy - 5.0, k0.width, k0.height)
    rng = np.random.default_rng(0)
    R = torch.from_numpy(rotvec_to_matrix(rng.normal(size=(40, 3)) * np.radians(20.0)))
    gain = torch.from_numpy(rng.normal(size=40) * 0.3)
    for height in (18, 36):
        lev = _Level(l[0], v[0], l[1], v[1], k, height)
        r, w = lev.residuals(R, gain)
        r_ref, w_ref = _reference_residuals(l[0], v[0], l[1], v[1], k, height, R, gain)
        # the two differ only by rounding in where a pixel lands: at most a few pixels on the
        # mask's threshold change side
        assert (w != w_ref.double()).double().mean() < 1e-3
        both = (w > 0) & w_ref
        assert both.sum() > 1000
        assert torch.allclose(r[both], r_ref[both], atol=1e-9)


def test_a_pixel_behind_frame_j_is_not_in_its_view():
    """A turn of 180 degrees puts frame i's pixels behind frame j: the perspective divide is
    clamped there, which maps a pixel straight behind to the image's centre; none may count
    as seen (nor any under a turn past the side)."""
    import torch

    from core.camera import Intrinsics
    from core.tracking.direct import _Level
    from core.tracking.geometry import rotvec_to_matrix

    k = Intrinsics(10.0, 10.0, 8.0, 6.0, 16, 12)
    ones = torch.full((12, 16), 0.5)
    lev = _Level(ones, torch.ones(12, 16), ones, torch.ones(12, 16), k, 12)
    turns = np.radians([[0.0, 180.0, 0.0], [180.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 0.0]])
    R = torch.from_numpy(rotvec_to_matrix(turns))
    # the pixel nearest the axis, straight behind after the half turn: make it exactly so
    b = lev.bearings.clone()
    b[0] = torch.tensor([0.0, 0.0, -1.0], dtype=b.dtype)
    lev.bearings = b
    _, w = lev.residuals(R, torch.zeros(4, dtype=torch.float64))
    assert w[:3].sum() == 0
    assert w[3].sum() == lev.bearings.shape[0]
