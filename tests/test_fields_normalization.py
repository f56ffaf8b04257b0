"""SceneBounds: robust, never degenerate, JSON round-trip."""
import json
import math

import pytest
import torch
from hypothesis import given, settings, strategies as st

from core.fields.components.normalization import (
    FALLBACK_HALF_EXTENT_M,
    MIN_EXTENT_M,
    BoundsError,
    SceneBounds,
)


def _finite_box(b: SceneBounds):
    assert all(math.isfinite(v) for v in b.lo + b.hi)
    assert all(h - l >= MIN_EXTENT_M for l, h in zip(b.lo, b.hi))


def test_normalize_maps_box_corners_to_unit_cube_and_midtime_to_zero():
    b = SceneBounds((-1.0, 0.0, -4.0), (3.0, 2.0, 0.0), t0=1.0, t1=3.0)
    x = torch.tensor([b.lo, b.hi, [1.0, 1.0, -2.0]])
    assert torch.allclose(b.normalize_x(x), torch.tensor([[-1.0] * 3, [1.0] * 3, [0.0] * 3]))
    assert torch.allclose(b.normalize_t(torch.tensor([1.0, 2.0, 3.0])), torch.tensor([-1.0, 0.0, 1.0]))


def test_zero_duration_maps_time_to_zero():
    b = SceneBounds((0, 0, 0), (1, 1, 1), t0=2.0, t1=2.0)
    assert torch.equal(b.normalize_t(torch.tensor([-5.0, 2.0, 7.0])), torch.zeros(3))
    assert b.contains_t(torch.tensor([2.0])).item() and not b.contains_t(torch.tensor([2.1])).item()


def test_flat_wall_gets_minimum_depth_extent():
    xy = torch.rand(1000, 2) * 4 - 2
    wall = torch.cat([xy, torch.full((1000, 1), -3.0)], dim=1)  # every point at z = -3
    b = SceneBounds.from_points(wall)
    _finite_box(b)
    assert b.lo[2] < -3.0 < b.hi[2]
    assert torch.isfinite(b.normalize_x(wall)).all()


def test_single_valid_point_and_holes():
    pts = torch.full((50, 3), float("nan"))
    pts[7] = torch.tensor([1.0, 2.0, -3.0])
    pts[8, 0] = float("inf")
    b = SceneBounds.from_points(pts)
    _finite_box(b)
    assert not b.fallback
    assert b.contains(pts[7]).item()


def test_all_invalid_depth_falls_back_to_box_around_camera():
    cam = torch.tensor([[5.0, 1.0, 2.0]])
    b = SceneBounds.from_points(torch.full((10, 10, 3), float("nan")), camera_positions=cam)
    assert b.fallback
    assert b.lo == pytest.approx((5 - FALLBACK_HALF_EXTENT_M, 1 - FALLBACK_HALF_EXTENT_M, 2 - FALLBACK_HALF_EXTENT_M))
    assert b.contains(cam[0]).item()


def test_outliers_do_not_inflate_box():
    pts = torch.rand(10_000, 3) * 2 - 1  # room in [-1, 1]^3
    pts[:50] = 1e6  # 0.5% depth spikes
    b = SceneBounds.from_points(pts)
    assert max(b.hi) < 2.0


def test_camera_positions_are_inside():
    pts = torch.rand(500, 3) - torch.tensor([0.5, 0.5, 5.0])  # points far in front
    cam = torch.zeros(1, 3)
    b = SceneBounds.from_points(pts, camera_positions=cam)
    assert b.contains(cam[0]).item()


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(*[st.one_of(st.floats(-1e4, 1e4), st.just(float("nan")), st.just(float("inf")))] * 3),
        min_size=0,
        max_size=40,
    )
)
def test_any_points_give_finite_nondegenerate_bounds(rows):
    pts = torch.tensor(rows, dtype=torch.float64).reshape(-1, 3)
    b = SceneBounds.from_points(pts, times=torch.tensor([0.0, 0.5]))
    _finite_box(b)
    n = b.normalize_x(torch.tensor([b.lo, b.hi], dtype=torch.float64))
    assert torch.isfinite(n).all()


def test_json_round_trip_and_validation():
    b = SceneBounds((-1, -2, -3), (1, 2, 3), 0.0, 4.5, fallback=True)
    assert SceneBounds.from_dict(json.loads(json.dumps(b.to_dict()))) == b
    with pytest.raises(BoundsError, match="hi"):
        SceneBounds.from_dict({"lo": [0, 0, 0], "hi": [1, 0, 1], "t0": 0, "t1": 0})
    with pytest.raises(BoundsError, match="missing"):
        SceneBounds.from_dict({"lo": [0, 0, 0]})
    with pytest.raises(BoundsError, match="finite"):
        SceneBounds.from_dict({"lo": [0, 0, float("nan")], "hi": [1, 1, 1], "t0": 0, "t1": 0})
    with pytest.raises(BoundsError, match="t1"):
        SceneBounds((0, 0, 0), (1, 1, 1), 2.0, 1.0)
