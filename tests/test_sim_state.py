"""Time-dependent state: camera paths, emitter movement and colour schedules."""
from __future__ import annotations

import math

import torch
from hypothesis import given, settings, strategies as st

from core.sim.spec import AreaEmitter, Box, CameraSpec, DollyPath, Keyframe, Lamp, PanPath, Room, SceneSpec, Schedule
from core.sim.state import camera_at, light_state, pose_from_yaw_pitch

ROOM = Room(boxes=[Box(lo=(0, 0, 0), hi=(5, 3, 4))])


@settings(max_examples=30, deadline=None)
@given(yaw=st.floats(-360, 360), pitch=st.floats(-89, 89))
def test_pose_is_a_rotation_whose_forward_follows_yaw_and_pitch(yaw, pitch):
    c2w = pose_from_yaw_pitch((1.0, 2.0, 3.0), yaw, pitch)
    r = c2w[:3, :3]
    torch.testing.assert_close(r @ r.T, torch.eye(3, dtype=torch.float64))
    assert abs(float(torch.linalg.det(r)) - 1.0) < 1e-9
    forward = -r[:, 2]
    y, p = math.radians(yaw), math.radians(pitch)
    expected = torch.tensor([-math.sin(y) * math.cos(p), math.sin(p), -math.cos(y) * math.cos(p)], dtype=torch.float64)
    torch.testing.assert_close(forward, expected)


def test_pan_and_dolly_paths_and_camera_motion_switch():
    pan = SceneSpec(
        room=ROOM,
        camera=CameraSpec(position=(2, 1.5, 3), yaw_deg=20, path=PanPath(yaw_end_deg=-40)),
        frames=7,
        effects=frozenset({"camera_motion"}),
    )
    last = camera_at(pan, 6).c2w
    torch.testing.assert_close(last, pose_from_yaw_pitch((2, 1.5, 3), -40, 0))
    torch.testing.assert_close(camera_at(pan, 3).c2w, pose_from_yaw_pitch((2, 1.5, 3), -10, 0))
    torch.testing.assert_close(camera_at(pan.with_effects(set()), 6).c2w, pose_from_yaw_pitch((2, 1.5, 3), 20, 0))
    dolly = pan.model_copy(
        update={"camera": CameraSpec(position=(2, 1.5, 3), path=DollyPath(position_end=(2, 1.0, 1)))}
    )
    torch.testing.assert_close(camera_at(dolly, 3).position, torch.tensor([2.0, 1.25, 2.0], dtype=torch.float64))


def test_lamp_moves_and_changes_colour_linearly():
    lamp = Lamp(
        center=(1, 1, 1),
        radius=0.05,
        radiance=(10.0, 10.0, 10.0),
        schedule=Schedule(
            interpolation="linear",
            keyframes=[
                Keyframe(frame=2, position=(1, 1, 1)),
                Keyframe(frame=6, position=(3, 2, 1), color=(1.0, 0.5, 0.0), intensity=2.0),
            ],
        ),
    )
    s = SceneSpec(
        room=ROOM, camera=CameraSpec(position=(2, 1.5, 3)), emitters=[lamp], frames=10, effects=frozenset({"schedules"})
    )
    st4 = light_state(s, 4.0)
    torch.testing.assert_close(st4.lamp_center, torch.tensor([[2.0, 1.5, 1.0]]))
    # halfway from scale 1 to 2 * (1, .5, 0)
    torch.testing.assert_close(st4.lamp_radiance, torch.tensor([[15.0, 10.0, 5.0]]))
    # held after the last key
    torch.testing.assert_close(light_state(s, 9.0).lamp_center, torch.tensor([[3.0, 2.0, 1.0]]))
    # before the first key
    torch.testing.assert_close(light_state(s, 0.0).lamp_radiance, torch.tensor([[10.0, 10.0, 10.0]]))


def test_area_emitter_sits_just_in_front_of_its_wall_facing_the_room():
    panel = AreaEmitter(kind="window", center=(0.0, 1.5, 2.0), facing="+x", size=(1.0, 2.0), radiance=(1, 1, 1))
    s = SceneSpec(room=ROOM, camera=CameraSpec(position=(2, 1.5, 3)), emitters=[panel])
    st0 = light_state(s, 0.0)
    assert float(st0.rect_center[0, 0]) > 0.0  # inside the room
    torch.testing.assert_close(st0.rect_normal, torch.tensor([[1.0, 0.0, 0.0]]))
    torch.testing.assert_close(st0.rect_half, torch.tensor([[0.0, 0.5, 1.0]]))  # size is (y, z) extent
