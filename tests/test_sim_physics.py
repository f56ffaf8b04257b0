"""Physics of the simulator: furnace, inverse square, shadows, emitter directions, schedules, cost."""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings, strategies as st

from core.conventions import direction_to_equirect_pixel, equirect_directions
from core.sim.render import radiance, render_envmap, render_frame
from core.sim.shading import SURFACE_OFFSET
from core.sim.spec import (
    AreaEmitter,
    Box,
    CameraSpec,
    Furniture,
    Keyframe,
    Lamp,
    RenderQuality,
    Room,
    RoomAlbedo,
    SceneSpec,
    Schedule,
)
from core.sim.state import light_state, schedule_value

ROOM = Box(lo=(0.0, 0.0, 0.0), hi=(5.0, 3.0, 4.0))
FAST = RenderQuality(area_samples=4, indirect_samples=4, indirect_area_samples=1)


def scene(**kw) -> SceneSpec:
    base = dict(
        room=Room(boxes=[ROOM]),
        camera=CameraSpec(position=(2.5, 1.5, 3.5)),
        resolution=(24, 18),
        quality=FAST,
    )
    base.update(kw)
    return SceneSpec(**base)


def uniform_albedo(a: float) -> RoomAlbedo:
    return RoomAlbedo(floor=(a,) * 3, ceiling=(a,) * 3, walls=(a,) * 3)


@settings(max_examples=12, deadline=None)
@given(a=st.floats(0.0, 0.95), le=st.floats(1e-3, 1e3), with_box=st.booleans())
def test_furnace_one_bounce_is_exact(a, le, with_box):
    """Closed room, every surface emits Le with albedo a: one bounce gives exactly Le (1 + a)."""
    furniture = [Furniture(box=Box(lo=(1.0, 0.0, 1.0), hi=(2.0, 0.8, 2.0)), albedo=(a,) * 3)] if with_box else []
    s = scene(
        room=Room(boxes=[ROOM], albedo=uniform_albedo(a), surface_emission=(le,) * 3),
        furniture=furniture,
        effects=frozenset({"emission", "indirect"}),
    )
    env = render_envmap(s, (3.0, 1.5, 3.0), 0.0, height=8)
    torch.testing.assert_close(env, torch.full_like(env, le * (1.0 + a)), rtol=1e-5, atol=0.0)
    no_bounce = render_envmap(s.with_effects({"emission"}), (3.0, 1.5, 3.0), 0.0, height=8)
    torch.testing.assert_close(no_bounce, torch.full_like(env, le), rtol=1e-6, atol=0.0)


def floor_radiance_below(s: SceneSpec, xz, probe_height=0.2) -> torch.Tensor:
    """Radiance leaving the floor at (x, 0, z), seen from a probe just above it."""
    x = torch.tensor([[xz[0], probe_height, xz[1]]])
    return radiance(s, x, torch.zeros(1), torch.tensor([[0.0, -1.0, 0.0]]))[0]


@pytest.mark.parametrize("h1,h2", [(0.5, 1.0), (0.8, 2.4)])
def test_inverse_square_falloff_from_small_lamp(h1, h2):
    a, le, r = 0.5, 1000.0, 0.01
    values = []
    for h in (h1, h2):
        s = scene(
            room=Room(boxes=[ROOM], albedo=uniform_albedo(a)),
            emitters=[Lamp(center=(2.5, h, 2.0), radius=r, radiance=(le, le, le))],
            effects=frozenset({"direct", "shadows"}),
        )
        values.append(floor_radiance_below(s, (2.5, 2.0), probe_height=0.1))
    # L = a / pi * E,  E = pi r^2 Le / D^2 for an unoccluded sphere straight above; the
    # shading point sits SURFACE_OFFSET above the floor
    dist = [h - SURFACE_OFFSET for h in (h1, h2)]
    for d, v in zip(dist, values):
        torch.testing.assert_close(v, torch.full((3,), a * r * r * le / d**2), rtol=1e-4, atol=0.0)
    ratio = values[0] / values[1]
    torch.testing.assert_close(ratio, torch.full((3,), (dist[1] / dist[0]) ** 2), rtol=1e-4, atol=0.0)


def test_small_area_emitter_matches_point_limit_and_cosines():
    """A small panel at height h straight above: E ~ Le A / h^2; tilted receivers follow cos."""
    a, le, side, h = 0.5, 10.0, 0.05, 3.0
    s = scene(
        room=Room(boxes=[ROOM], albedo=uniform_albedo(a)),
        emitters=[
            AreaEmitter(
                kind="ceiling_panel", center=(2.5, 3.0, 2.0), facing="-y", size=(side, side), radiance=(le,) * 3
            )
        ],
        effects=frozenset({"direct"}),
    )
    v = floor_radiance_below(s, (2.5, 2.0))
    expected = a / math.pi * le * side * side / (h - 1e-3 - SURFACE_OFFSET) ** 2  # panel sits 1 mm off the ceiling
    torch.testing.assert_close(v, torch.full((3,), expected), rtol=2e-3, atol=0.0)
    # off-axis floor point: both cosines equal cos(theta) = h / D, so E ~ Le A h^2 / D^4
    dx, hh = 2.0, h - 1e-3 - SURFACE_OFFSET
    off = floor_radiance_below(s, (2.5 + dx, 2.0))
    d2 = hh * hh + dx * dx
    torch.testing.assert_close(
        off, torch.full((3,), a / math.pi * le * side * side * hh * hh / d2**2), rtol=5e-3, atol=0.0
    )


def test_shadowed_point_gets_no_direct_light_from_occluded_lamp():
    table_top = Furniture(box=Box(lo=(2.0, 0.7, 1.5), hi=(3.0, 0.75, 2.5)))
    s = scene(
        room=Room(boxes=[ROOM], albedo=uniform_albedo(0.6)),
        furniture=[table_top],
        emitters=[Lamp(center=(2.5, 2.5, 2.0), radius=0.02, radiance=(500.0,) * 3)],
        effects=frozenset({"direct", "shadows"}),
    )
    under = floor_radiance_below(s, (2.5, 2.0))
    assert torch.equal(under, torch.zeros(3))
    lit_without_shadows = floor_radiance_below(s.with_effects({"direct"}), (2.5, 2.0))
    assert bool((lit_without_shadows > 0).all())
    outside = floor_radiance_below(s, (4.0, 2.0))  # not under the table: lit
    assert bool((outside > 0).all())


def _angle_between(a: torch.Tensor, b: torch.Tensor) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, float((a / a.norm()) @ (b / b.norm()))))))


@pytest.mark.parametrize(
    "lamp",
    [
        (3.5, 1.5, 1.0),  # generic
        (2.0, 1.5, 3.9),  # behind the probe: on the phi = +-pi seam
        (2.0, 2.9, 2.0),  # straight up: the pole
        (0.2, 0.3, 0.5),  # low, far corner
    ],
)
def test_envmap_sees_lamp_where_geometry_says(lamp):
    probe = torch.tensor([2.0, 1.5, 2.0])
    height = 64
    s = scene(
        emitters=[Lamp(center=lamp, radius=0.02, radiance=(1e4, 1e4, 1e4))], effects=frozenset({"emission", "direct"})
    )
    env = render_envmap(s, probe.tolist(), 0.0, height=height)
    lum = env.sum(-1)
    i, j = divmod(int(lum.argmax()), 2 * height)
    true_d = torch.tensor(lamp) - probe
    got_d = equirect_directions(height)[i, j]
    pixel_deg = 180.0 / height
    assert _angle_between(got_d, true_d) <= pixel_deg * math.sqrt(2) * 0.75
    row, col = direction_to_equirect_pixel(true_d, height)
    assert abs(i - float(row)) <= 1.0
    if 1 < i < height - 2:  # the column is meaningless at the pole rows
        dc = abs(j - float(col)) % (2 * height)
        assert min(dc, 2 * height - dc) <= 1.0


@settings(max_examples=25, deadline=None)
@given(switch=st.integers(1, 40), fps=st.sampled_from([1.0, 3.0, 7.0, 10.0, 24.0, 29.97, 30.0, 60.0]))
def test_schedule_switches_exactly_at_declared_frame(switch, fps):
    sched = Schedule(keyframes=[Keyframe(frame=switch, on=False)])
    t_before, t_at = (switch - 1) / fps, switch / fps
    assert schedule_value(sched, t_before * fps, (0, 0, 0)).on
    assert not schedule_value(sched, t_at * fps, (0, 0, 0)).on


def test_schedule_switch_in_rendered_envmap_and_linear_dimming():
    fps, k = 10.0, 5
    panel = AreaEmitter(
        kind="ceiling_panel", center=(2.5, 3.0, 2.0), facing="-y", size=(1.0, 1.0), radiance=(4.0,) * 3,
        schedule=Schedule(keyframes=[Keyframe(frame=k, on=False)]),
    )
    lamp = Lamp(
        center=(4.0, 1.0, 1.0),
        radius=0.05,
        radiance=(100.0,) * 3,
        schedule=Schedule(interpolation="linear", keyframes=[Keyframe(frame=0), Keyframe(frame=8, intensity=0.0)]),
    )
    s = scene(emitters=[panel, lamp], frames=10, fps=fps, effects=frozenset({"emission", "schedules"}))

    def up(t):  # top row looks at the panel
        return render_envmap(s, (2.5, 1.5, 2.0), t, height=8)[0].max()

    assert float(up((k - 1) / fps)) == pytest.approx(4.0)
    assert float(up(k / fps)) == 0.0
    torch.testing.assert_close(light_state(s, 4.0).lamp_radiance, torch.full((1, 3), 50.0))
    # without the 'schedules' effect, schedules are ignored
    assert float(
        render_envmap(s.with_effects({"emission"}), (2.5, 1.5, 2.0), k / fps, height=8)[0].max()
    ) == pytest.approx(4.0)


def test_fewer_effects_cast_fewer_rays():
    s = scene(
        room=Room(boxes=[ROOM]),
        furniture=[Furniture(box=Box(lo=(2.0, 0.7, 1.5), hi=(3.0, 0.75, 2.5)))],
        emitters=[
            AreaEmitter(kind="ceiling_panel", center=(2.5, 3.0, 2.0), facing="-y", size=(1.0, 1.0), radiance=(4.0,) * 3)
        ],
        effects=frozenset({"emission", "direct", "shadows", "indirect"}),
    )
    full = render_frame(s, 0).cost.rays
    no_indirect = render_frame(s.with_effects({"emission", "direct", "shadows"}), 0).cost.rays
    no_shadows = render_frame(s.with_effects({"emission", "direct"}), 0).cost.rays
    emission_only = render_frame(s.with_effects({"emission"}), 0).cost.rays
    assert full["indirect"] > 0 and no_indirect.get("indirect", 0) == 0
    assert sum(full.values()) > sum(no_indirect.values()) > sum(no_shadows.values())
    assert no_shadows.get("shadows", 0) == 0
    assert sum(emission_only.values()) == 24 * 18  # primary rays only


@pytest.mark.parametrize("le", [1e-6, 1.0, 1e6])
def test_extreme_radiance_stays_finite_and_linear(le):
    s = scene(
        emitters=[Lamp(center=(2.5, 2.0, 2.0), radius=0.05, radiance=(le,) * 3)],
        effects=frozenset({"emission", "direct", "shadows"}),
    )
    env = render_envmap(s, (2.0, 1.0, 2.0), 0.0, height=8)
    ref = render_envmap(
        s.model_copy(update={"emitters": [Lamp(center=(2.5, 2.0, 2.0), radius=0.05, radiance=(1.0,) * 3)]}),
        (2.0, 1.0, 2.0),
        0.0,
        height=8,
    )
    assert bool(torch.isfinite(env).all())
    torch.testing.assert_close(env, ref * le, rtol=1e-5, atol=0.0)
