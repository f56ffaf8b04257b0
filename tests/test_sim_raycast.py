"""Ray casting: analytic distances, L-shaped rooms, axis-parallel rays, occlusion, spheres."""
from __future__ import annotations

import math

import torch
from hypothesis import given, settings, strategies as st

from core.sim.raycast import FURNITURE, MISS, ROOM, SceneGeometry, cast, filler_boxes, occluded, sphere_hits
from core.sim.spec import Box, CameraSpec, Furniture, Room, SceneSpec
from core.sim.state import light_state

L_ROOM = Room(boxes=[Box(lo=(0, 0, 0), hi=(5, 3, 4)), Box(lo=(3, 0, -3), hi=(5, 3, 0.5))])


def geom_and_lights(room: Room, furniture=()):
    s = SceneSpec(room=room, furniture=list(furniture), camera=CameraSpec(position=(1, 1, 1)), resolution=(4, 4))
    return SceneGeometry.from_spec(s), light_state(s, 0.0)


def wall_distance(o, d, lo, hi):
    """Reference exit distance from inside a box, one ray at a time in float64."""
    best = math.inf
    for a in range(3):
        if d[a] > 0:
            best = min(best, (hi[a] - o[a]) / d[a])
        elif d[a] < 0:
            best = min(best, (lo[a] - o[a]) / d[a])
    return best


@settings(max_examples=60, deadline=None)
@given(
    o=st.tuples(st.floats(0.05, 4.95), st.floats(0.05, 2.95), st.floats(0.05, 3.95)),
    d=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(lambda v: sum(x * x for x in v) > 1e-3),
)
def test_ray_from_inside_a_box_room_hits_the_analytic_wall(o, d):
    geom, lights = geom_and_lights(Room(boxes=[Box(lo=(0, 0, 0), hi=(5, 3, 4))]))
    d = torch.tensor(d, dtype=torch.float64)
    d = d / d.norm()
    hit = cast(geom, lights, torch.tensor([o], dtype=torch.float32), d[None].float())
    expected = wall_distance(o, d.tolist(), (0, 0, 0), (5, 3, 4))
    assert int(hit.kind[0]) == ROOM
    assert abs(float(hit.t[0]) - expected) <= 1e-4 * max(1.0, expected)
    # the normal faces back into the room, along the axis of the wall that was hit
    n = hit.normal[0]
    assert float(n.abs().sum()) == 1.0 and float(n @ d.float()) < 0


def test_axis_parallel_rays_are_finite_and_exact():
    geom, lights = geom_and_lights(
        Room(boxes=[Box(lo=(0, 0, 0), hi=(5, 3, 4))]), [Furniture(box=Box(lo=(2, 0, 1), hi=(3, 1, 2)))]
    )
    o = torch.tensor([[2.5, 2.0, 1.5]] * 6)
    d = torch.tensor([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    hit = cast(geom, lights, o, d)
    torch.testing.assert_close(hit.t, torch.tensor([2.5, 2.5, 1.0, 1.0, 2.5, 1.5]))
    assert hit.kind.tolist() == [ROOM, ROOM, ROOM, FURNITURE, ROOM, ROOM]
    assert hit.index[2] == 3 and hit.index[0] == 1  # ceiling (+y face), +x wall


def test_l_shaped_room_has_one_wall_block_and_rays_turn_the_corner():
    lo, hi = filler_boxes(torch.tensor([[0.0, 0, 0], [3, 0, -3]]), torch.tensor([[5.0, 3, 4], [5, 3, 0.5]]))
    torch.testing.assert_close(lo, torch.tensor([[0.0, 0, -3]]))
    torch.testing.assert_close(hi, torch.tensor([[3.0, 3, 0]]))
    geom, lights = geom_and_lights(L_ROOM)
    # from the main part, straight into the wing: reaches the wing's far wall z = -3
    o = torch.tensor([[4.0, 1.5, 3.0], [1.0, 1.5, 3.0], [4.0, 1.5, -2.0]])
    d = torch.tensor([[0.0, 0, -1], [0.0, 0, -1], [-1.0, 0, 0]])
    hit = cast(geom, lights, o, d)
    torch.testing.assert_close(hit.t, torch.tensor([6.0, 3.0, 1.0]))
    assert hit.kind.tolist() == [ROOM, ROOM, ROOM]
    # the concave wall faces +x (into the wing) where the third ray hits it
    torch.testing.assert_close(hit.normal[2], torch.tensor([1.0, 0, 0]))
    # a segment around the concave corner is blocked; one inside the main part is not
    a = torch.tensor([[1.0, 1.5, 1.0], [1.0, 1.5, 1.0]])
    b = torch.tensor([[4.0, 1.5, -2.0], [4.0, 1.5, 3.0]])
    v = b - a
    assert occluded(geom, a, v / v.norm(dim=-1, keepdim=True), v.norm(dim=-1)).tolist() == [True, False]
    assert geom.inside_room(torch.tensor([[4.0, 1.0, -2.0], [1.0, 1.0, -2.0]])).tolist() == [True, False]


def test_ray_outside_the_room_misses():
    geom, lights = geom_and_lights(Room(boxes=[Box(lo=(0, 0, 0), hi=(5, 3, 4))]))
    hit = cast(geom, lights, torch.tensor([[9.0, 1.0, 1.0]]), torch.tensor([[1.0, 0.0, 0.0]]))
    assert int(hit.kind[0]) == MISS and math.isinf(float(hit.t[0]))


@settings(max_examples=40, deadline=None)
@given(dist=st.floats(0.5, 1e4), r=st.floats(1e-3, 0.4), off=st.floats(0.0, 0.99))
def test_sphere_hits_are_accurate_far_away(dist, r, off):
    """The perpendicular-offset form keeps far, small spheres hittable without cancellation."""
    c = torch.tensor([[0.0, off * r, -dist]])
    t, i = sphere_hits(c, torch.tensor([r]), torch.zeros(1, 3), torch.tensor([[0.0, 0.0, -1.0]]))
    expected = dist - math.sqrt(r * r - (off * r) ** 2)
    assert abs(float(t[0]) - expected) <= 1e-6 * dist + 1e-5
