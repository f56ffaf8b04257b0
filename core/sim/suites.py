"""Benchmark/test suites: fixed-seed scene specs, each with held-out probe points and times.

Small by default (192x144, <= 24 frames) so tests and benchmarks stay fast. Every suite
declares only the effects it needs. `suite(name)` returns a fresh spec; `SUITES` lists them.
"""
from __future__ import annotations

from typing import Callable

from core.sim.spec import (
    AreaEmitter,
    Box,
    CameraSpec,
    DollyPath,
    Furniture,
    Keyframe,
    Lamp,
    PanPath,
    ProbePoint,
    Room,
    RoomAlbedo,
    SceneSpec,
    SceneSpecError,
    Schedule,
    SensorSpec,
)

RESOLUTION = (192, 144)
ROOM = Box(lo=(0.0, 0.0, 0.0), hi=(5.0, 2.8, 4.0))


def table(
    x: float,
    z: float,
    width: float = 1.4,
    depth: float = 0.8,
    height: float = 0.75,
    name: str = "table",
    albedo=(0.45, 0.3, 0.2),
) -> list[Furniture]:
    """A table top slab plus four legs, centred at (x, z); a probe fits under it."""
    top = Furniture(
        name=f"{name}-top",
        box=Box(lo=(x - width / 2, height - 0.04, z - depth / 2), hi=(x + width / 2, height, z + depth / 2)),
        albedo=albedo,
    )
    legs = []
    for sx in (-1, 1):
        for sz in (-1, 1):
            cx, cz = x + sx * (width / 2 - 0.05), z + sz * (depth / 2 - 0.05)
            legs.append(
                Furniture(
                    name=f"{name}-leg",
                    box=Box(lo=(cx - 0.03, 0.0, cz - 0.03), hi=(cx + 0.03, height - 0.04, cz + 0.03)),
                    albedo=(0.3, 0.2, 0.15),
                )
            )
    return [top, *legs]


def _camera(**kw) -> CameraSpec:
    base = dict(position=(2.5, 1.5, 3.7), yaw_deg=0.0, pitch_deg=-8.0, hfov_deg=75.0)
    base.update(kw)
    return CameraSpec(**base)


def static() -> SceneSpec:
    """One room, a table, a ceiling panel and a window; direct light, shadows, one bounce."""
    return SceneSpec(
        name="static",
        seed=101,
        room=Room(boxes=[ROOM]),
        furniture=[
            *table(2.3, 1.6),
            Furniture(name="cabinet", box=Box(lo=(4.2, 0.0, 0.2), hi=(4.9, 1.2, 0.8)), albedo=(0.7, 0.7, 0.75)),
        ],
        emitters=[
            AreaEmitter(
                kind="ceiling_panel",
                name="panel",
                center=(2.5, 2.8, 2.0),
                facing="-y",
                size=(1.2, 0.6),
                radiance=(6.0, 6.0, 5.6),
            ),
            AreaEmitter(
                kind="window",
                name="window",
                center=(0.0, 1.5, 1.8),
                facing="+x",
                size=(1.2, 1.0),
                radiance=(8.0, 9.0, 11.0),
            ),
        ],
        camera=_camera(),
        frames=1,
        fps=10.0,
        resolution=RESOLUTION,
        effects=frozenset({"emission", "direct", "shadows", "indirect"}),
        probes=[
            ProbePoint(x=(1.2, 1.2, 1.0), t=0.0),
            ProbePoint(x=(2.3, 0.35, 1.6), t=0.0),
            ProbePoint(x=(3.8, 1.6, 2.6), t=0.0),
        ],
    )


def spatial() -> SceneSpec:
    """An L-shaped room with strong near lamps and hard shadows: lighting varies over space."""
    return SceneSpec(
        name="spatial",
        seed=202,
        room=Room(
            boxes=[ROOM, Box(lo=(3.0, 0.0, -3.0), hi=(5.0, 2.8, 0.5))],
            albedo=RoomAlbedo(floor=(0.5, 0.45, 0.4), walls=(0.7, 0.68, 0.65)),
        ),
        furniture=[
            *table(1.6, 2.0),
            Furniture(name="shelf", box=Box(lo=(3.4, 0.0, 1.0), hi=(4.0, 1.6, 1.3)), albedo=(0.6, 0.5, 0.4)),
        ],
        emitters=[
            Lamp(name="warm-lamp", center=(0.5, 1.3, 0.6), radius=0.06, radiance=(900.0, 650.0, 350.0)),
            Lamp(name="cool-lamp", center=(4.3, 1.8, -2.2), radius=0.06, radiance=(300.0, 420.0, 600.0)),
            AreaEmitter(
                kind="ceiling_panel",
                name="dim-panel",
                center=(1.5, 2.8, 2.5),
                facing="-y",
                size=(0.6, 0.6),
                radiance=(2.0, 2.0, 2.0),
            ),
        ],
        camera=_camera(position=(2.0, 1.5, 3.7), yaw_deg=-15.0),
        frames=1,
        resolution=RESOLUTION,
        effects=frozenset({"emission", "direct", "shadows"}),
        probes=[
            ProbePoint(x=(0.8, 1.0, 0.9), t=0.0),
            ProbePoint(x=(1.6, 0.3, 2.0), t=0.0),
            ProbePoint(x=(4.0, 1.5, -1.5), t=0.0),
            ProbePoint(x=(3.7, 0.8, 1.6), t=0.0),
        ],
    )


PANEL_OFF_FRAME = 8


def temporal() -> SceneSpec:
    """The ceiling panel switches off at frame 8; a lamp dims linearly and turns warmer."""
    return SceneSpec(
        name="temporal",
        seed=303,
        room=Room(boxes=[ROOM]),
        furniture=table(2.5, 1.8),
        emitters=[
            AreaEmitter(
                kind="ceiling_panel",
                name="panel",
                center=(2.5, 2.8, 2.0),
                facing="-y",
                size=(1.0, 1.0),
                radiance=(8.0, 8.0, 8.0),
                schedule=Schedule(keyframes=[Keyframe(frame=PANEL_OFF_FRAME, on=False)]),
            ),
            Lamp(
                name="lamp",
                center=(4.2, 1.2, 0.8),
                radius=0.05,
                radiance=(500.0, 500.0, 500.0),
                schedule=Schedule(
                    interpolation="linear",
                    keyframes=[Keyframe(frame=0), Keyframe(frame=15, intensity=0.3, color=(1.0, 0.7, 0.4))],
                ),
            ),
        ],
        camera=_camera(),
        frames=16,
        fps=8.0,
        resolution=RESOLUTION,
        effects=frozenset({"emission", "direct", "shadows", "schedules"}),
        probes=[
            ProbePoint(x=(1.5, 1.2, 1.5), t=0.5),
            ProbePoint(x=(1.5, 1.2, 1.5), t=1.5),
            ProbePoint(x=(3.5, 1.0, 2.5), t=0.875),
            ProbePoint(x=(3.5, 1.0, 2.5), t=1.875),
        ],
    )


def moving_camera() -> SceneSpec:
    """A panning camera with a sensor (exposure, noise) over a static scene."""
    return SceneSpec(
        name="moving-camera",
        seed=404,
        room=Room(boxes=[ROOM]),
        furniture=[
            *table(2.0, 1.5),
            Furniture(name="sofa", box=Box(lo=(3.6, 0.0, 2.6), hi=(4.9, 0.5, 3.5)), albedo=(0.3, 0.35, 0.5)),
        ],
        emitters=[
            AreaEmitter(
                kind="window",
                name="window",
                center=(2.5, 1.5, 0.0),
                facing="+z",
                size=(1.6, 1.1),
                radiance=(10.0, 11.0, 13.0),
            ),
            Lamp(name="lamp", center=(0.6, 1.4, 3.2), radius=0.05, radiance=(600.0, 480.0, 300.0)),
        ],
        camera=_camera(position=(2.5, 1.4, 3.6), yaw_deg=25.0, path=PanPath(yaw_end_deg=-25.0)),
        frames=12,
        fps=6.0,
        resolution=RESOLUTION,
        effects=frozenset({"emission", "direct", "shadows", "camera_motion", "sensor"}),
        sensor=SensorSpec(ev=-0.5, noise_sigma=0.01),
        probes=[
            ProbePoint(x=(2.0, 0.3, 1.5), t=0.0),
            ProbePoint(x=(1.0, 1.5, 2.0), t=1.0),
            ProbePoint(x=(4.0, 1.2, 1.0), t=1.8333333333),
        ],
    )


def auto_exposure() -> SceneSpec:
    """`moving-camera`'s room under a wider pan with a phone's auto-exposure: the window comes
    into view and the exposure drops (static light; capture.json states each frame's ev)."""
    base = moving_camera()
    return base.model_copy(update={
        "name": "auto-exposure",
        "seed": 606,
        "camera": _camera(position=(2.5, 1.4, 3.6), yaw_deg=-100.0, path=PanPath(yaw_end_deg=20.0)),
        "sensor": SensorSpec(ev=0.0, noise_sigma=0.01, auto_exposure=True, auto_exposure_speed=0.5),
    })


def hard() -> SceneSpec:
    """Dark room, a tiny lamp >= 1e4x brighter than the lit walls, saturated windows (LDR 1 at
    ev 0), a probe under a table, a dolly camera and a compressed, noisy sensor."""
    return SceneSpec(
        name="hard",
        seed=505,
        room=Room(
            boxes=[ROOM], albedo=RoomAlbedo(floor=(0.06, 0.05, 0.05), ceiling=(0.1, 0.1, 0.1), walls=(0.08, 0.08, 0.09))
        ),
        furniture=table(2.5, 1.5, width=1.6, depth=1.0, albedo=(0.12, 0.08, 0.06)),
        emitters=[
            Lamp(name="tiny-lamp", center=(1.0, 1.6, 2.5), radius=0.015, radiance=(500.0, 450.0, 380.0)),
            AreaEmitter(
                kind="window",
                name="window-left",
                center=(0.0, 1.5, 1.5),
                facing="+x",
                size=(1.0, 1.2),
                radiance=(6.0, 6.0, 6.6),
            ),
            AreaEmitter(
                kind="window",
                name="window-back",
                center=(3.5, 1.5, 0.0),
                facing="+z",
                size=(1.2, 1.2),
                radiance=(6.0, 6.2, 7.0),
            ),
        ],
        camera=_camera(position=(2.5, 1.4, 3.8), path=DollyPath(position_end=(2.5, 1.3, 3.0))),
        frames=10,
        fps=5.0,
        resolution=RESOLUTION,
        effects=frozenset({"emission", "direct", "shadows", "camera_motion", "sensor"}),
        sensor=SensorSpec(ev=0.0, noise_sigma=0.02, video_compression=True, crf=28),
        probes=[
            ProbePoint(x=(2.5, 0.3, 1.5), t=0.0),
            ProbePoint(x=(1.2, 1.6, 2.5), t=1.0),
            ProbePoint(x=(0.5, 1.5, 1.5), t=1.8),
        ],
    )


SUITES: dict[str, Callable[[], SceneSpec]] = {
    "static": static,
    "spatial": spatial,
    "temporal": temporal,
    "moving-camera": moving_camera,
    "auto-exposure": auto_exposure,
    "hard": hard,
}


def suite(name: str) -> SceneSpec:
    try:
        return SUITES[name]()
    except KeyError:
        raise SceneSpecError(f"unknown suite {name!r}; choose one of {sorted(SUITES)}") from None
