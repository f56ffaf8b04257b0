"""The rooms of the physically based AR-session benchmark, as plain JSON-able dicts.

World frame = the product's (core/conventions.py): right-handed, +y up, metres; a room spans
x in [-W/2, W/2], y in [0, H], z in [-D/2, D/2]. A scene dict holds:

* `room`: size [W, H, D] and the materials of floor, ceiling and the four walls (-x, +x, -z, +z);
* `materials`: name -> {"type": "diffuse" | "plastic" | "conductor" | "twosided", ...}; a diffuse
  reflectance may be a procedural texture {"texture": "checker" | "planks" | "stripes" | "noise", ...}
  (made in numpy, seeded: bench.pbr.render.texture);
* `objects`: boxes (centre, size, yaw), cylinders (p0, p1, radius, caps), spheres, disks and
  quads (centre, normal, width, height), each with a material;
* `lights`: name -> a source (`bulb`: an emitting sphere, optionally under a shade; `quad`:
  an emitting rectangle: a window, a ceiling panel, a screen), its linear RGB radiance and its
  `schedule` [[t, scale], ...] (piecewise linear in time; before the first key the first scale,
  after the last the last);
* `events`: the light events scored (a lamp switching on or off, a dimmer, daylight fading):
  {"light", "kind", "t0", "t1"};
* `camera`: the path ("walk", "look-around", "orbit") and its parameters, `hfov_deg`, `fps`,
  `frames`, `size` [W, H];
* `probes`: ground-truth points [x, y, z] (kept out of furniture) with a label.

Only `room`, `materials`, `objects` and `lights` (without schedules) enter a render's cache key
(bench.pbr.render.geometry_key), with the lights' scales at the render's time.
"""
from __future__ import annotations

import copy
import math

import numpy as np

HFOV_DEG = 64.0
FPS = 10.0
FRAMES = 40
SIZE = (160, 120)

WARM = (1.0, 0.74, 0.48)  # a tungsten-ish lamp's colour (scaled by its radiance)
DAYLIGHT = (0.82, 0.92, 1.0)
PANEL = (1.0, 0.96, 0.9)


def _rgb(colour, scale: float) -> list[float]:
    return [round(float(c) * scale, 5) for c in colour]


def schedule_value(schedule, t: float) -> float:
    """The scale of a light at time t: piecewise linear between the keys [[t, scale], ...]."""
    keys = sorted((float(a), float(b)) for a, b in schedule)
    if t <= keys[0][0]:
        return keys[0][1]
    for (t0, s0), (t1, s1) in zip(keys, keys[1:]):
        if t <= t1:
            return s0 if t1 <= t0 else s0 + (s1 - s0) * (t - t0) / (t1 - t0)
    return keys[-1][1]


def scales_at(scene: dict, t: float) -> dict[str, float]:
    return {name: round(schedule_value(light["schedule"], t), 6) for name, light in scene["lights"].items()}


def frame_times(scene: dict) -> np.ndarray:
    cam = scene["camera"]
    return np.arange(cam["frames"]) / cam["fps"]


# ---------------------------------------------------------------------------------------
# Camera paths (c2w 4x4 in the product's convention: x right, y up, looking along -z)
# ---------------------------------------------------------------------------------------
def rotation(yaw_deg: float, pitch_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """c2w rotation: roll about the camera's z, then pitch about x, then yaw about +y (yaw > 0
    turns left, from -z towards -x; pitch > 0 looks up)."""
    y, p, r = (math.radians(v) for v in (yaw_deg, pitch_deg, roll_deg))
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    rx = np.array([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]])
    rz = np.array([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]])
    return ry @ rx @ rz


def look_at_rotation(eye, target) -> np.ndarray:
    f = np.asarray(target, float) - np.asarray(eye, float)
    f /= np.linalg.norm(f)
    right = np.cross(f, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    return np.stack([right, up, -f], axis=1)


def _jitter(seed: int, n: int, amplitude: float) -> np.ndarray:
    """A hand's smooth wobble: [n] samples of a few seeded low-frequency sinusoids."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / max(n - 1, 1)
    out = np.zeros(n)
    for k in (1.3, 2.7, 4.1):
        out += rng.normal() * np.sin(2 * np.pi * (k * t + rng.random())) / k
    return amplitude * out


def camera_poses(scene: dict) -> np.ndarray:
    """[T, 4, 4] float64 c2w poses of the scene's camera path (seeded hand jitter included)."""
    cam = scene["camera"]
    n = int(cam["frames"])
    s = np.linspace(0.0, 1.0, n)
    seed = int(cam.get("seed", 0))
    jit = [_jitter(seed * 7 + k, n, a) for k, a in enumerate((0.6, 0.6, 0.4, 0.008, 0.008, 0.008))]
    poses = np.zeros((n, 4, 4))
    for i in range(n):
        if cam["path"] == "walk":
            # from p0 to p1 (eased), turning yaw0 +- yaw_amp (a full left-right-left swing)
            u = 0.5 - 0.5 * math.cos(math.pi * s[i])
            pos = (1 - u) * np.asarray(cam["p0"]) + u * np.asarray(cam["p1"])
            pos[1] += 0.015 * math.sin(2 * math.pi * 3.0 * s[i])  # the gait
            yaw = cam["yaw0"] + cam["yaw_amp"] * math.sin(2 * math.pi * cam.get("turns", 1.0) * s[i])
            rot = rotation(yaw + jit[0][i], cam.get("pitch", -8.0) + jit[1][i], jit[2][i])
        elif cam["path"] == "look-around":
            pos = np.asarray(cam["p0"], float).copy()
            keys = np.asarray(cam["yaws"], float)  # yaw keyframes visited in order
            yaw = float(np.interp(s[i], np.linspace(0, 1, len(keys)), keys))
            pitch = cam.get("pitch", -10.0) + cam.get("pitch_amp", 8.0) * math.sin(2 * math.pi * s[i])
            rot = rotation(yaw + jit[0][i], pitch + jit[1][i], jit[2][i])
        elif cam["path"] == "orbit":
            a = math.radians(cam["a0"] + (cam["a1"] - cam["a0"]) * s[i])
            c = np.asarray(cam["centre"], float)
            pos = np.array([c[0] + cam["radius"] * math.sin(a), cam["height"], c[2] + cam["radius"] * math.cos(a)])
            rot = look_at_rotation(pos, c) @ rotation(jit[0][i], jit[1][i], jit[2][i])
        else:
            raise ValueError(f"unknown camera path {cam['path']!r}")
        poses[i, :3, :3] = rot
        poses[i, :3, 3] = pos + np.array([jit[3][i], jit[4][i], jit[5][i]])
        poses[i, 3, 3] = 1.0
    return poses


def intrinsics(scene: dict) -> dict:
    """{fx, fy, cx, cy, width, height} of the scene's pinhole (square pixels, centred)."""
    w, h = scene["camera"]["size"]
    f = 0.5 * w / math.tan(math.radians(scene["camera"]["hfov_deg"]) / 2.0)
    return {"fx": f, "fy": f, "cx": w / 2.0, "cy": h / 2.0, "width": int(w), "height": int(h)}


# ---------------------------------------------------------------------------------------
# Probe times
# ---------------------------------------------------------------------------------------
def probe_times(scene: dict) -> list[dict]:
    """The scored times: before and after each event (for a fade also its middle), at frame
    times 3 frames off the event (the field's step needs a frame or two), and the static
    stretch's two ends for drift. [{"t", "role", "event"}], sorted by time, unique in t."""
    times = frame_times(scene)
    t_last = float(times[-1])
    gap = 3.0 / scene["camera"]["fps"]

    def snap(t):
        return float(times[np.argmin(np.abs(times - min(max(t, 0.0), t_last)))])

    out: list[dict] = []
    for k, ev in enumerate(scene["events"]):
        out.append({"t": snap(ev["t0"] - gap), "role": "before", "event": k})
        if ev["kind"] in ("dimmer", "fade"):
            out.append({"t": snap(0.5 * (ev["t0"] + ev["t1"])), "role": "middle", "event": k})
        out.append({"t": snap(ev["t1"] + gap), "role": "after", "event": k})
    a, b = static_stretch(scene)
    if a is not None:
        out += [{"t": a, "role": "static-start", "event": None}, {"t": b, "role": "static-end", "event": None}]
    merged: dict[float, dict] = {}
    for row in out:
        merged.setdefault(row["t"], {"t": row["t"], "roles": []})["roles"].append(
            {"role": row["role"], "event": row["event"]})
    return [merged[t] for t in sorted(merged)]


def static_stretch(scene: dict) -> tuple[float | None, float | None]:
    """The longest run of frame times (>= 1 s) over which no light's scale changes: its first and
    last frame times (drift is measured between them), or (None, None)."""
    times = frame_times(scene)
    states = [tuple(scales_at(scene, float(t)).values()) for t in times]
    best, start = (None, None), 0
    for i in range(1, len(times) + 1):
        if i == len(times) or states[i] != states[start]:
            a, b = float(times[start]), float(times[i - 1])
            if b - a >= 1.0 and (best[0] is None or b - a > best[1] - best[0]):
                best = (a, b)
            start = i
    return best


# ---------------------------------------------------------------------------------------
# Building blocks
# ---------------------------------------------------------------------------------------
def box(centre, size, mat, yaw=0.0):
    return {"type": "box", "centre": list(centre), "size": list(size), "mat": mat, "yaw": yaw}


def table(x, z, w, d, h, mat, leg_mat=None, top=0.04):
    """A table: top slab + 4 legs (a list of boxes)."""
    leg_mat = leg_mat or mat
    parts = [box((x, h - top / 2, z), (w, top, d), mat)]
    for sx in (-1, 1):
        for sz in (-1, 1):
            parts.append(box((x + sx * (w / 2 - 0.05), (h - top) / 2, z + sz * (d / 2 - 0.05)),
                             (0.05, h - top, 0.05), leg_mat))
    return parts


def round_table(x, z, r, h, mat):
    return [
        {"type": "cylinder", "p0": [x, h - 0.04, z], "p1": [x, h, z], "radius": r, "mat": mat, "caps": True},
        {"type": "cylinder", "p0": [x, 0.0, z], "p1": [x, h - 0.04, z], "radius": 0.06, "mat": mat, "caps": False},
        {"type": "cylinder", "p0": [x, 0.0, z], "p1": [x, 0.03, z], "radius": 0.3, "mat": mat, "caps": True},
    ]


def chair(x, z, mat, yaw=0.0):
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    back = (x - 0.2 * s, 0.7, z - 0.2 * c)
    return [box((x, 0.45, z), (0.44, 0.05, 0.44), mat, yaw), box(back, (0.44, 0.5, 0.04), mat, yaw),
            box((x, 0.21, z), (0.36, 0.42, 0.36), mat, yaw)]


def sofa(x, z, length, mat, facing="+x"):
    """A sofa along a wall, facing `facing` (+x, -x, +z, -z): seat, back, two arms."""
    ax = 0 if facing in ("+z", "-z") else 2  # the axis the sofa runs along
    sign = 1.0 if facing[0] == "+" else -1.0

    def at(along, across, y, sa, sc, sy):
        if ax == 2:
            return box((x + sign * across, y, z + along), (sc, sy, sa), mat)
        return box((x + along, y, z + sign * across), (sa, sy, sc), mat)

    return [at(0.0, 0.0, 0.22, length, 0.85, 0.44), at(0.0, -0.35, 0.6, length, 0.16, 0.8),
            at(-length / 2 + 0.08, 0.0, 0.55, 0.16, 0.85, 0.22), at(length / 2 - 0.08, 0.0, 0.55, 0.16, 0.85, 0.22)]


def bulb(centre, radius, colour, level, schedule, shade=None, pole=None, pole_mat="metal"):
    """A lamp: an emitting sphere (radiance colour x level), optionally a shade {"kind": "drum" |
    "cap", "radius", "height", "mat"} (drum: an open cylinder around the bulb, light leaves up and
    down; cap: a cylinder above the bulb's centre with a closed top, light leaves downwards and
    sideways below it) and a pole from the floor (floor lamps) or the ceiling (pendants)."""
    light = {"kind": "bulb", "centre": list(centre), "radius": radius, "radiance": _rgb(colour, level),
             "schedule": schedule}
    if shade:
        light["shade"] = shade
    if pole:
        light["pole"] = {"to": pole, "mat": pole_mat}
    return light


def quad_light(centre, normal, width, height, colour, level, schedule, frame_mat=None):
    light = {"kind": "quad", "centre": list(centre), "normal": list(normal), "width": width, "height": height,
             "radiance": _rgb(colour, level), "schedule": schedule}
    if frame_mat:
        light["frame_mat"] = frame_mat
    return light


def step(t: float, before: float, after: float, width: float = 0.05):
    return [[0.0, before], [t, before], [t + width, after]]


# ---------------------------------------------------------------------------------------
# The rooms
# ---------------------------------------------------------------------------------------
def _base_materials() -> dict:
    return {
        "white": {"type": "diffuse", "rgb": [0.8, 0.8, 0.78]},
        "metal": {"type": "conductor", "material": "Al", "alpha": 0.25},
        "chrome": {"type": "conductor", "material": "Cr", "alpha": 0.0},
        # dark-lined: a light inside would be a tiny, very bright second source that only BSDF
        # sampling finds (fireflies over every wall at 36-144 spp)
        "shade": {"type": "shade", "rgb": [0.85, 0.8, 0.7], "inside": [0.04, 0.04, 0.04]},
        "bulb": {"type": "diffuse", "rgb": [0.9, 0.9, 0.9]},  # a bulb switched off
        "window": {"type": "diffuse", "rgb": [0.05, 0.06, 0.07]},  # glass at night, roughly
        "screen": {"type": "plastic", "rgb": [0.02, 0.02, 0.02], "alpha": 0.05},
        "panel": {"type": "diffuse", "rgb": [0.85, 0.85, 0.85]},
    }


def issue61_living() -> dict:
    """The issue's own case: a furnished living room, a window, a ceiling panel and a floor lamp
    that switches ON halfway; the camera walks ~1.3 m turning +-38 deg."""
    mats = _base_materials() | {
        "walls": {"type": "diffuse", "rgb": [0.72, 0.68, 0.6]},
        "ceiling": {"type": "diffuse", "rgb": [0.85, 0.85, 0.83]},
        "floor": {"type": "diffuse", "texture": "planks", "c0": [0.32, 0.2, 0.11], "c1": [0.45, 0.3, 0.17],
                  "n": [1, 10], "res": 256, "seed": 1},
        "rug": {"type": "diffuse", "texture": "checker", "c0": [0.5, 0.12, 0.1], "c1": [0.75, 0.65, 0.45],
                "n": [6, 4], "res": 192, "seed": 0},
        "sofa": {"type": "diffuse", "rgb": [0.18, 0.25, 0.4]},
        "wood": {"type": "diffuse", "rgb": [0.35, 0.22, 0.12]},
        "books": {"type": "diffuse", "texture": "stripes", "c0": [0.6, 0.15, 0.1], "c1": [0.15, 0.3, 0.5],
                  "n": [14, 1], "res": 128, "seed": 3},
        "vase": {"type": "plastic", "rgb": [0.6, 0.08, 0.05], "alpha": 0.08},
    }
    objects = [
        *table(0.0, -0.6, 1.2, 0.75, 0.74, "wood"),
        {"type": "sphere", "centre": [0.25, 0.86, -0.5], "radius": 0.12, "mat": "chrome"},
        {"type": "cylinder", "p0": [-0.3, 0.74, -0.7], "p1": [-0.3, 1.0, -0.7], "radius": 0.06, "mat": "vase",
         "caps": True},
        *sofa(2.05, 0.2, 1.8, "sofa", facing="-x"),
        box((-1.0, 0.9, -1.92), (1.4, 1.8, 0.34), "wood"),
        {"type": "quad", "centre": [-1.0, 0.9, -1.749], "normal": [0, 0, 1], "width": 1.3, "height": 1.7,
         "mat": "books"},
        {"type": "quad", "centre": [0.3, 0.005, 0.3], "normal": [0, 1, 0], "width": 2.4, "height": 1.7, "mat": "rug"},
    ]
    lights = {
        "window": quad_light((-2.498, 1.5, -0.5), (1, 0, 0), 1.4, 1.3, DAYLIGHT, 3.5, [[0.0, 1.0]]),
        "ceiling_panel": quad_light((0.3, 2.698, 0.2), (0, -1, 0), 1.0, 0.5, PANEL, 6.0, [[0.0, 1.0]]),
        "floor_lamp": bulb((1.6, 1.55, -1.4), 0.1, WARM, 60.0, step(1.95, 0.0, 1.0), pole=[1.6, 0.0, -1.4]),
    }
    return {
        "name": "issue61-living",
        "room": {"size": [5.0, 2.7, 4.2], "floor": "floor", "ceiling": "ceiling", "walls": ["walls"] * 4},
        "materials": mats, "objects": objects, "lights": lights,
        "events": [{"light": "floor_lamp", "kind": "on", "t0": 1.95, "t1": 2.0}],
        "camera": {"path": "walk", "p0": [-0.55, 1.45, 1.45], "p1": [0.65, 1.45, 0.95], "yaw0": -12.0,
                   "yaw_amp": 38.0, "turns": 1.0, "pitch": -10.0, "seed": 61,
                   "hfov_deg": HFOV_DEG, "fps": FPS, "frames": FRAMES, "size": list(SIZE)},
        "probes": [
            {"x": [1.15, 1.2, -0.95], "label": "near lamp"},
            {"x": [0.0, 1.05, -0.6], "label": "above table"},
            {"x": [-1.9, 1.3, -0.4], "label": "by window"},
            {"x": [-1.9, 0.9, 1.5], "label": "far corner"},
            {"x": [0.4, 1.5, 0.5], "label": "room middle"},
            {"x": [1.5, 0.9, 0.9], "label": "by sofa"},
        ],
    }


def office_desk_lamp_off() -> dict:
    """An office: a desk lamp under a cap shade switches OFF; a monitor and two ceiling panels stay
    on; the camera looks around from one spot."""
    mats = _base_materials() | {
        "walls": {"type": "diffuse", "rgb": [0.55, 0.6, 0.64]},
        "accent": {"type": "diffuse", "texture": "checker", "c0": [0.62, 0.6, 0.55], "c1": [0.42, 0.45, 0.5],
                   "n": [9, 6], "res": 180, "seed": 2},
        "ceiling": {"type": "diffuse", "rgb": [0.82, 0.82, 0.82]},
        "floor": {"type": "diffuse", "texture": "noise", "c0": [0.2, 0.2, 0.22], "c1": [0.35, 0.34, 0.33],
                  "n": [24, 24], "res": 192, "seed": 4},
        "desk": {"type": "plastic", "rgb": [0.55, 0.42, 0.3], "alpha": 0.15},
        "cabinet": {"type": "diffuse", "rgb": [0.25, 0.27, 0.3]},
        "mug": {"type": "plastic", "rgb": [0.1, 0.35, 0.6], "alpha": 0.05},
        "chair": {"type": "diffuse", "rgb": [0.1, 0.1, 0.1]},
    }
    objects = [
        *table(0.3, -1.6, 1.5, 0.75, 0.75, "desk", "metal"),
        box((0.15, 0.83, -1.85), (0.2, 0.16, 0.12), "cabinet"),  # the monitor's stand
        box((0.15, 1.06, -1.88), (0.62, 0.38, 0.04), "cabinet"),  # the monitor's body behind its screen
        {"type": "cylinder", "p0": [0.55, 0.75, -1.35], "p1": [0.55, 0.85, -1.35], "radius": 0.04, "mat": "mug",
         "caps": True},
        {"type": "sphere", "centre": [-0.25, 0.81, -1.4], "radius": 0.06, "mat": "chrome"},
        box((-1.45, 0.55, -1.3), (0.5, 1.1, 0.9), "cabinet"),
        *chair(0.3, -0.9, "chair", yaw=180.0),
        box((1.45, 1.0, 1.2), (0.5, 2.0, 1.0), "cabinet"),
    ]
    lights = {
        "desk_lamp": bulb((0.85, 1.2, -1.45), 0.045, WARM, 320.0, step(2.45, 1.0, 0.0),
                          shade={"kind": "cap", "radius": 0.1, "height": 0.1, "mat": "shade"},
                          pole=[0.85, 0.75, -1.45]),
        "monitor": quad_light((0.15, 1.06, -1.859), (0, 0, 1), 0.58, 0.34, (0.75, 0.85, 1.0), 1.6, [[0.0, 1.0]]),
        "panels": {"kind": "quads", "radiance": _rgb(PANEL, 4.0), "schedule": [[0.0, 1.0]],
                   "quads": [{"centre": [-0.8, 2.598, -0.6], "normal": [0, -1, 0], "width": 0.6, "height": 0.6},
                             {"centre": [0.8, 2.598, 0.8], "normal": [0, -1, 0], "width": 0.6, "height": 0.6}]},
    }
    return {
        "name": "office-desk-lamp-off",
        "room": {"size": [3.6, 2.6, 4.0], "floor": "floor", "ceiling": "ceiling",
                 "walls": ["walls", "walls", "accent", "walls"]},
        "materials": mats, "objects": objects, "lights": lights,
        "events": [{"light": "desk_lamp", "kind": "off", "t0": 2.45, "t1": 2.5}],
        "camera": {"path": "look-around", "p0": [-0.1, 1.5, 1.05], "yaws": [25.0, -35.0, 5.0], "pitch": -14.0,
                   "pitch_amp": 7.0, "seed": 2, "spp": 100, "hfov_deg": HFOV_DEG, "fps": FPS, "frames": FRAMES,
                   "size": list(SIZE)},
        "probes": [
            {"x": [0.6, 0.95, -1.15], "label": "on desk, by the lamp"},
            {"x": [-0.45, 0.95, -1.45], "label": "on desk, left"},
            {"x": [0.0, 1.3, 0.0], "label": "room middle"},
            {"x": [0.9, 1.0, -0.2], "label": "in front of the desk"},
            {"x": [-0.8, 1.9, -0.2], "label": "under a panel"},
            {"x": [-1.3, 0.45, 0.6], "label": "low, far from the lamp"},
        ],
    }


def dining_dimmer() -> dict:
    """A dining room: a pendant lamp over a round table is dimmed to a fifth; a window; the camera
    orbits the table slowly."""
    mats = _base_materials() | {
        "walls": {"type": "diffuse", "rgb": [0.45, 0.53, 0.4]},
        "paper": {"type": "diffuse", "texture": "stripes", "c0": [0.7, 0.66, 0.55], "c1": [0.5, 0.56, 0.42],
                  "n": [16, 1], "res": 256, "seed": 5},
        "ceiling": {"type": "diffuse", "rgb": [0.86, 0.85, 0.82]},
        "floor": {"type": "diffuse", "texture": "checker", "c0": [0.75, 0.74, 0.7], "c1": [0.25, 0.25, 0.26],
                  "n": [10, 10], "res": 200, "seed": 6},
        "table": {"type": "plastic", "rgb": [0.3, 0.17, 0.08], "alpha": 0.2},
        "chairs": {"type": "diffuse", "rgb": [0.55, 0.35, 0.2]},
        "sideboard": {"type": "diffuse", "rgb": [0.15, 0.12, 0.1]},
        "bowl": {"type": "plastic", "rgb": [0.8, 0.75, 0.2], "alpha": 0.03},
        "gold": {"type": "conductor", "material": "Au", "alpha": 0.1},
    }
    objects = [
        *round_table(0.0, 0.0, 0.6, 0.76, "table"),
        *chair(0.0, 0.85, "chairs", yaw=0.0), *chair(0.0, -0.85, "chairs", yaw=180.0),
        *chair(0.85, 0.0, "chairs", yaw=90.0), *chair(-0.85, 0.0, "chairs", yaw=-90.0),
        {"type": "sphere", "centre": [0.15, 0.86, 0.1], "radius": 0.1, "mat": "gold"},
        box((-1.6, 0.45, 1.9), (1.4, 0.9, 0.45), "sideboard"),
        {"type": "sphere", "centre": [-1.7, 1.0, 1.9], "radius": 0.1, "mat": "bowl"},
    ]
    lights = {
        "pendant": bulb((0.0, 1.6, 0.0), 0.07, WARM, 220.0, [[0.0, 1.0], [1.5, 1.0], [3.0, 0.2]],
                        shade={"kind": "cap", "radius": 0.2, "height": 0.16, "mat": "shade"}, pole=[0.0, 2.8, 0.0]),
        "window": quad_light((2.198, 1.5, 0.6), (-1, 0, 0), 1.6, 1.4, DAYLIGHT, 2.6, [[0.0, 1.0]]),
    }
    return {
        "name": "dining-dimmer",
        "room": {"size": [4.4, 2.8, 4.6], "floor": "floor", "ceiling": "ceiling",
                 "walls": ["paper", "walls", "walls", "walls"]},
        "materials": mats, "objects": objects, "lights": lights,
        "events": [{"light": "pendant", "kind": "dimmer", "t0": 1.5, "t1": 3.0}],
        "camera": {"path": "orbit", "centre": [0.0, 0.85, 0.0], "radius": 1.75, "height": 1.5, "a0": 20.0,
                   "a1": 120.0, "seed": 3, "hfov_deg": HFOV_DEG, "fps": FPS, "frames": FRAMES, "size": list(SIZE)},
        "probes": [
            {"x": [0.3, 1.1, 0.25], "label": "over the table, under the pendant"},
            {"x": [-0.5, 0.95, -0.45], "label": "table edge"},
            {"x": [1.6, 1.3, 0.6], "label": "by window"},
            {"x": [-1.7, 1.3, -1.8], "label": "far corner"},
            {"x": [-1.4, 1.3, 1.3], "label": "by the sideboard"},
            {"x": [0.9, 2.1, -1.2], "label": "high, off the table"},
        ],
    }


def studio_dusk() -> dict:
    """A large studio: a wide window whose daylight fades to a sixth at dusk, a floor lamp under a
    drum shade and a TV stay on; the camera walks with turns."""
    mats = _base_materials() | {
        "walls": {"type": "diffuse", "rgb": [0.82, 0.8, 0.76]},
        "ceiling": {"type": "diffuse", "rgb": [0.85, 0.85, 0.85]},
        "floor": {"type": "diffuse", "texture": "noise", "c0": [0.3, 0.3, 0.29], "c1": [0.5, 0.49, 0.47],
                  "n": [32, 32], "res": 256, "seed": 7},
        "sofa": {"type": "diffuse", "rgb": [0.55, 0.3, 0.12]},
        "coffee": {"type": "plastic", "rgb": [0.05, 0.05, 0.05], "alpha": 0.02},
        "shelf": {"type": "diffuse", "texture": "stripes", "c0": [0.7, 0.6, 0.4], "c1": [0.2, 0.35, 0.25],
                  "n": [10, 1], "res": 128, "seed": 8},
        "copper": {"type": "conductor", "material": "Cu", "alpha": 0.15},
    }
    objects = [
        *sofa(0.0, 1.6, 2.4, "sofa", facing="-z"),
        box((0.0, 0.2, 0.5), (1.2, 0.04, 0.6), "coffee"),
        box((0.0, 0.1, 0.5), (1.1, 0.2, 0.5), "coffee"),
        {"type": "sphere", "centre": [0.3, 0.33, 0.5], "radius": 0.09, "mat": "copper"},
        {"type": "cylinder", "p0": [-0.3, 0.22, 0.45], "p1": [-0.3, 0.5, 0.45], "radius": 0.05, "mat": "copper",
         "caps": True},
        box((-2.7, 1.0, 0.0), (0.4, 2.0, 1.6), "shelf"),
        box((2.75, 0.3, -0.8), (0.4, 0.6, 1.6), "coffee"),
    ]
    lights = {
        "window": quad_light((0.0, 1.6, -2.498), (0, 0, 1), 3.0, 1.8, DAYLIGHT, 4.0,
                             [[0.0, 1.0], [0.6, 1.0], [3.4, 0.16]]),
        "floor_lamp": bulb((2.2, 1.6, 1.2), 0.08, WARM, 110.0, [[0.0, 1.0]],
                           shade={"kind": "drum", "radius": 0.2, "height": 0.3, "mat": "shade"},
                           pole=[2.2, 0.0, 1.2]),
        "tv": quad_light((2.948, 1.25, -0.8), (-1, 0, 0), 1.2, 0.68, (0.7, 0.8, 1.0), 1.2, [[0.0, 1.0]]),
    }
    return {
        "name": "studio-dusk",
        "room": {"size": [6.0, 3.0, 5.0], "floor": "floor", "ceiling": "ceiling", "walls": ["walls"] * 4},
        "materials": mats, "objects": objects, "lights": lights,
        "events": [{"light": "window", "kind": "fade", "t0": 0.6, "t1": 3.4}],
        "camera": {"path": "walk", "p0": [-2.2, 1.55, 2.1], "p1": [-0.8, 1.5, 2.2], "yaw0": -45.0,
                   "yaw_amp": 32.0, "turns": 1.0, "pitch": -12.0, "seed": 4, "hfov_deg": HFOV_DEG, "fps": FPS,
                   "frames": FRAMES, "size": list(SIZE)},
        "probes": [
            {"x": [0.4, 1.2, -1.9], "label": "by window"},
            {"x": [2.0, 0.75, 0.95], "label": "under the floor lamp"},
            {"x": [0.0, 0.9, 0.5], "label": "over the coffee table"},
            {"x": [-2.2, 1.4, -1.6], "label": "window corner"},
            {"x": [1.0, 1.6, -0.4], "label": "room middle"},
            {"x": [-1.6, 1.0, 1.9], "label": "behind the sofa's end"},
        ],
    }


def bedroom_reading() -> dict:
    """A small bedroom with checked wallpaper: a bedside reading lamp switches ON; a dim evening
    window and a laptop screen stay on; the camera looks around from the door."""
    mats = _base_materials() | {
        "paper": {"type": "diffuse", "texture": "checker", "c0": [0.78, 0.62, 0.6], "c1": [0.86, 0.8, 0.7],
                  "n": [12, 8], "res": 192, "seed": 9},
        "walls": {"type": "diffuse", "rgb": [0.78, 0.7, 0.62]},
        "ceiling": {"type": "diffuse", "rgb": [0.85, 0.84, 0.8]},
        "carpet": {"type": "diffuse", "texture": "noise", "c0": [0.3, 0.34, 0.42], "c1": [0.4, 0.45, 0.52],
                   "n": [40, 40], "res": 160, "seed": 10},
        "bed": {"type": "diffuse", "rgb": [0.82, 0.82, 0.85]},
        "blanket": {"type": "diffuse", "texture": "stripes", "c0": [0.6, 0.2, 0.25], "c1": [0.85, 0.75, 0.6],
                    "n": [8, 1], "res": 128, "seed": 11},
        "wood": {"type": "diffuse", "rgb": [0.42, 0.28, 0.16]},
        "glossy": {"type": "plastic", "rgb": [0.05, 0.25, 0.1], "alpha": 0.04},
    }
    objects = [
        box((0.7, 0.25, -1.0), (1.5, 0.5, 2.0), "bed"),
        {"type": "quad", "centre": [0.7, 0.501, -0.6], "normal": [0, 1, 0], "width": 1.5, "height": 1.1,
         "mat": "blanket"},
        box((0.7, 0.6, -1.98), (1.6, 1.2, 0.06), "wood"),
        box((-0.35, 0.3, -1.65), (0.45, 0.6, 0.5), "wood"),  # nightstand
        box((1.45, 0.38, 1.45), (0.4, 0.76, 0.8), "wood"),  # desk (a block)
        box((1.4, 0.77, 1.45), (0.26, 0.02, 0.34), "wood"),
        {"type": "sphere", "centre": [-0.48, 0.68, -1.75], "radius": 0.08, "mat": "glossy"},
    ]
    lights = {
        "reading_lamp": bulb((-0.3, 1.0, -1.55), 0.05, WARM, 240.0, step(1.55, 0.0, 1.0),
                             shade={"kind": "cap", "radius": 0.12, "height": 0.14, "mat": "shade"},
                             pole=[-0.3, 0.6, -1.55]),
        "window": quad_light((-1.698, 1.45, 0.4), (1, 0, 0), 1.0, 1.1, (0.6, 0.65, 0.95), 1.0, [[0.0, 1.0]]),
        "laptop": quad_light((1.45, 0.93, 1.42), (-0.94, 0.34, 0.0), 0.3, 0.2, (0.8, 0.85, 1.0), 2.0,
                             [[0.0, 1.0]]),
    }
    return {
        "name": "bedroom-reading",
        "room": {"size": [3.4, 2.5, 4.0], "floor": "carpet", "ceiling": "ceiling",
                 "walls": ["walls", "walls", "paper", "paper"]},
        "materials": mats, "objects": objects, "lights": lights,
        "events": [{"light": "reading_lamp", "kind": "on", "t0": 1.55, "t1": 1.6}],
        "camera": {"path": "look-around", "p0": [-0.9, 1.55, 1.3], "yaws": [-40.0, 10.0, 35.0, -10.0],
                   "pitch": -15.0, "pitch_amp": 6.0, "seed": 5, "spp": 100, "hfov_deg": HFOV_DEG, "fps": FPS,
                   "frames": FRAMES, "size": list(SIZE)},
        "probes": [
            {"x": [-0.05, 0.85, -1.2], "label": "by the reading lamp"},
            {"x": [0.7, 0.85, -1.0], "label": "over the bed"},
            {"x": [-1.25, 1.2, 0.4], "label": "by window"},
            {"x": [1.2, 1.2, 1.2], "label": "by the desk"},
            {"x": [0.2, 1.6, 0.3], "label": "room middle"},
            {"x": [-1.2, 0.5, -0.6], "label": "low, window side"},
        ],
    }


def gallery_glossy() -> dict:
    """A dark gallery with glossy objects on plinths and a polished floor: three ceiling strips stay
    on, a bare floor lamp switches OFF; the camera orbits the central plinth."""
    mats = _base_materials() | {
        "walls": {"type": "diffuse", "rgb": [0.3, 0.3, 0.32]},
        "ceiling": {"type": "diffuse", "rgb": [0.6, 0.6, 0.6]},
        "floor": {"type": "plastic", "rgb": [0.12, 0.1, 0.09], "alpha": 0.08},
        "plinth": {"type": "diffuse", "rgb": [0.85, 0.85, 0.82]},
        "gold": {"type": "conductor", "material": "Au", "alpha": 0.05},
        "red": {"type": "plastic", "rgb": [0.6, 0.05, 0.04], "alpha": 0.02},
        "painting": {"type": "diffuse", "texture": "checker", "c0": [0.8, 0.6, 0.1], "c1": [0.1, 0.2, 0.5],
                     "n": [5, 4], "res": 100, "seed": 12},
    }
    objects = [
        box((0.0, 0.45, 0.0), (0.6, 0.9, 0.6), "plinth"),
        {"type": "sphere", "centre": [0.0, 1.1, 0.0], "radius": 0.2, "mat": "chrome"},
        box((-1.5, 0.5, -1.8), (0.5, 1.0, 0.5), "plinth"),
        {"type": "cylinder", "p0": [-1.5, 1.0, -1.8], "p1": [-1.5, 1.45, -1.8], "radius": 0.12, "mat": "red",
         "caps": True},
        box((1.5, 0.4, 1.6), (0.5, 0.8, 0.5), "plinth"),
        {"type": "sphere", "centre": [1.5, 0.95, 1.6], "radius": 0.15, "mat": "gold"},
        {"type": "quad", "centre": [2.499, 1.6, -0.5], "normal": [-1, 0, 0], "width": 1.6, "height": 1.1,
         "mat": "painting"},
    ]
    lights = {
        "strips": {"kind": "quads", "radiance": _rgb(PANEL, 6.0), "schedule": [[0.0, 1.0]],
                   "quads": [{"centre": [x, 3.198, 0.0], "normal": [0, -1, 0], "width": 0.25, "height": 4.0}
                             for x in (-1.5, 0.0, 1.5)]},
        "floor_lamp": bulb((1.2, 1.5, -1.2), 0.09, WARM, 90.0, step(2.05, 1.0, 0.0), pole=[1.2, 0.0, -1.2]),
    }
    return {
        "name": "gallery-glossy",
        "room": {"size": [5.0, 3.2, 6.0], "floor": "floor", "ceiling": "ceiling", "walls": ["walls"] * 4},
        "materials": mats, "objects": objects, "lights": lights,
        "events": [{"light": "floor_lamp", "kind": "off", "t0": 2.05, "t1": 2.1}],
        "camera": {"path": "orbit", "centre": [0.0, 1.0, 0.0], "radius": 2.0, "height": 1.6, "a0": -20.0,
                   "a1": 90.0, "seed": 6, "hfov_deg": HFOV_DEG, "fps": FPS, "frames": FRAMES, "size": list(SIZE)},
        "probes": [
            {"x": [0.8, 1.2, -0.8], "label": "by the lamp"},
            {"x": [0.0, 1.5, 0.0], "label": "over the chrome sphere"},
            {"x": [-1.5, 1.7, -1.8], "label": "over the red vase"},
            {"x": [1.5, 1.3, 1.6], "label": "over the gold sphere"},
            {"x": [-1.8, 1.2, 2.2], "label": "far corner"},
            {"x": [-0.6, 0.5, 0.9], "label": "low, in the lamp's shadow side"},
        ],
    }


SCENES = {
    "issue61-living": issue61_living,
    "office-desk-lamp-off": office_desk_lamp_off,
    "dining-dimmer": dining_dimmer,
    "studio-dusk": studio_dusk,
    "bedroom-reading": bedroom_reading,
    "gallery-glossy": gallery_glossy,
}
QUICK_SCENES = ("issue61-living",)


def tiny_scene() -> dict:
    """The tests' scene: a small room, a window and a bare lamp that switches on at frame 4 of 8
    (64x48, a static look-around)."""
    mats = _base_materials() | {
        "walls": {"type": "diffuse", "rgb": [0.7, 0.7, 0.68]},
        "floor": {"type": "diffuse", "texture": "checker", "c0": [0.3, 0.3, 0.3], "c1": [0.6, 0.6, 0.6],
                  "n": [4, 4], "res": 32, "seed": 0},
    }
    lights = {
        "window": quad_light((-1.498, 1.4, -0.3), (1, 0, 0), 1.0, 1.0, DAYLIGHT, 3.0, [[0.0, 1.0]]),
        "lamp": bulb((0.8, 1.3, -1.2), 0.1, WARM, 60.0, step(0.35, 0.0, 1.0)),
    }
    return {
        "name": "tiny",
        "room": {"size": [3.0, 2.5, 3.0], "floor": "floor", "ceiling": "white", "walls": ["walls"] * 4},
        "materials": mats, "objects": [box((0.0, 0.35, -0.6), (0.8, 0.7, 0.6), "walls")], "lights": lights,
        "events": [{"light": "lamp", "kind": "on", "t0": 0.35, "t1": 0.4}],
        "camera": {"path": "look-around", "p0": [0.0, 1.4, 1.0], "yaws": [10.0, -25.0], "pitch": -8.0,
                   "pitch_amp": 2.0, "seed": 1, "hfov_deg": HFOV_DEG, "fps": 10.0, "frames": 8, "size": [64, 48]},
        "probes": [{"x": [0.45, 1.1, -0.8], "label": "near lamp"}, {"x": [-0.9, 1.2, 0.5], "label": "far"}],
    }


def get_scene(name: str) -> dict:
    if name == "tiny":
        return tiny_scene()
    return copy.deepcopy(SCENES[name]())
