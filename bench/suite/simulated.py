"""Simulated suites with ground truth: capture directories (cached), held-out probes, and
the time series used for flicker and switch lag.

Captures are written with the simulator's own `write_capture` (docs/simulator.md) and read
back with the engine's `load_capture`, so every method sees exactly what a user's job sees.
Rendering dominates the first run, so capture directories are cached under a key of the
scene spec (any change to the spec or the resolution re-renders).
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import torch

from core.sim.spec import ProbePoint, SceneSpec

SERIES_HEIGHT = 16  # env-map height of flicker / lag time series (brightness only matters)
SWITCH_SAMPLES_PER_FRAME = 4
SWITCH_WINDOW_FRAMES = 2  # frames either side of a switch
MAX_SERIES_POSITIONS = 2


@dataclass
class Series:
    """Env maps over time at one position: a static-light stretch (flicker) or a switch (lag)."""

    kind: str  # "stretch" | "switch"
    x: tuple[float, float, float]
    times: torch.Tensor  # [K] seconds
    gt: torch.Tensor  # [K, h, 2h, 3]
    switch_frame: int | None = None


@dataclass
class SuiteData:
    name: str
    scene: SceneSpec
    capture_dir: Path
    probes: list[ProbePoint]
    gt: torch.Tensor  # [P, H, 2H, 3] ground truth at the held-out probes
    global_point: tuple[float, float, float]
    global_time: float
    series: list[Series] = field(default_factory=list)
    render_seconds: float = 0.0  # 0 when the capture came from the cache
    # capture/job parameters every job and bound prior of this run uses (e.g. temporal, frame_ev)
    params: dict = field(default_factory=dict)

    @property
    def eval_height(self) -> int:
        return int(self.gt.shape[1])

    def describe(self) -> dict:
        from core.sim.sensor import scene_curve

        return {
            "camera_curve": scene_curve(self.scene).label,  # what the capture's frames were encoded with
            "frames": self.scene.frames,
            "fps": self.scene.fps,
            "resolution": list(self.scene.resolution),
            "effects": sorted(self.scene.effects),
            "held_out_probes": [{"x": list(p.x), "t": p.t} for p in self.probes],
            "global_probe": {"x": list(self.global_point), "t": self.global_time},
            "series": [
                {"kind": s.kind, "x": list(s.x), "samples": len(s.times), "switch_frame": s.switch_frame}
                for s in self.series
            ],
            "gt_height": self.eval_height,
            "render_seconds": round(self.render_seconds, 2),
        }


def scene_key(scene: SceneSpec) -> str:
    return hashlib.sha256(scene.model_dump_json().encode()).hexdigest()[:12]


def prepare_capture(scene: SceneSpec, cache_dir: Path, gt_height: int) -> tuple[Path, float]:
    """The capture directory of `scene` (rendered now unless cached); (path, render seconds)."""
    import time

    from core.sim.capture import write_capture

    w, h = scene.resolution
    out = Path(cache_dir) / f"{scene.name}-{w}x{h}-gt{gt_height}-{scene_key(scene)}"
    if (out / "capture.json").is_file():
        return out, 0.0
    t0 = time.perf_counter()
    write_capture(scene, out, envmap_height=gt_height, video=False)
    return out, time.perf_counter() - t0


def switch_frames(scene: SceneSpec) -> list[int]:
    """Frames at which some emitter turns on or off (Keyframe.on switches exactly there)."""
    frames = set()
    for emitter in scene.emitters:
        schedule = getattr(emitter, "schedule", None)
        state = True
        for kf in (schedule.keyframes if schedule else []):
            if kf.on != state and 0 < kf.frame < scene.frames:
                frames.add(int(kf.frame))
            state = kf.on
    return sorted(frames)


def global_probe_point(scene: SceneSpec, capture) -> tuple[float, float, float]:
    """The DiffusionLight-style single probe: the centre of the visible scene's bounding box
    (from unprojected depth), moved towards the camera until it is in free space."""
    from core.engine.scene import scene_bounds
    from core.sim.render import ProbeError, check_probe

    b = scene_bounds(capture)
    centre = torch.tensor([(lo + hi) / 2 for lo, hi in zip(b.lo, b.hi)], dtype=torch.float64)
    cam = capture.poses[capture.num_frames // 2, :3, 3]
    for k in range(21):
        p = centre + (cam - centre) * (k / 20.0)
        try:
            check_probe(scene, p.tolist())
            return tuple(float(v) for v in p)
        except ProbeError:
            continue
    return tuple(float(v) for v in cam)


def _gt_series(scene: SceneSpec, x, times: torch.Tensor) -> torch.Tensor:
    from core.sim.render import render_envmap

    return torch.stack([render_envmap(scene, x, float(t), SERIES_HEIGHT) for t in times])


def build_series(scene: SceneSpec) -> list[Series]:
    """Flicker stretches between switches (every frame time) and dense windows around switches,
    at up to MAX_SERIES_POSITIONS distinct held-out probe positions."""
    if scene.frames < 2:
        return []
    positions: list[tuple] = []
    for p in scene.probes:
        if tuple(p.x) not in positions:
            positions.append(tuple(p.x))
    positions = positions[:MAX_SERIES_POSITIONS]
    switches = switch_frames(scene)
    bounds = [0, *switches, scene.frames]
    out: list[Series] = []
    for x in positions:
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b - a >= 2:
                times = torch.arange(a, b, dtype=torch.float64) / scene.fps
                out.append(Series("stretch", x, times, _gt_series(scene, x, times)))
        for s in switches:
            lo, hi = max(0, s - SWITCH_WINDOW_FRAMES), min(scene.frames - 1, s + SWITCH_WINDOW_FRAMES)
            k = (hi - lo) * SWITCH_SAMPLES_PER_FRAME + 1
            times = torch.linspace(lo / scene.fps, hi / scene.fps, k, dtype=torch.float64)
            out.append(Series("switch", x, times, _gt_series(scene, x, times), switch_frame=s))
    return out


EXTRA_PROBE_MARGIN_M = 0.3  # extra held-out probes keep this far from walls, floor and ceiling
EXTRA_PROBE_TRIES = 200  # draws per wanted probe before giving up (furniture rejects some)


def free_space_box(scene) -> tuple[torch.Tensor, torch.Tensor]:
    """(lo, hi) float64 [3]: the room's bounding box EXTRA_PROBE_MARGIN_M inside its walls, floor
    and ceiling, where held-out points are drawn (check_probe still rejects furniture)."""
    lo = torch.tensor([min(b.lo[k] for b in scene.room.boxes) for k in range(3)], dtype=torch.float64)
    hi = torch.tensor([max(b.hi[k] for b in scene.room.boxes) for k in range(3)], dtype=torch.float64)
    return lo + EXTRA_PROBE_MARGIN_M, hi - EXTRA_PROBE_MARGIN_M


def capture_linear(capture_dir: Path, capture) -> torch.Tensor:
    """The frames [T, H, W, 3] the job kept of a simulated capture (`capture`, as loaded),
    linearised with the camera curve they were encoded with (capture.json `camera_curve`, the
    truth a bench knows: core.sim.camera_curves.CameraCurve.decode, the filmic tone curve
    included) and each frame's exposure removed as the job removes it (`capture.frame_ev`).
    A capture written before camera curves: `capture.linear()` (the engine's convention)."""
    from core.io.images import read_image
    from core.sim.camera_curves import get_curve

    doc = json.loads((Path(capture_dir) / "capture.json").read_text())
    if doc.get("camera_curve") is None:
        return capture.linear()
    curve = get_curve(doc["camera_curve"])
    index = (capture.times.double() * float(doc["fps"])).round().long().tolist()
    codes = torch.stack([torch.from_numpy(read_image(Path(capture_dir) / doc["frames"][i])[..., :3].copy())
                         for i in index]).float()
    return curve.decode(codes) * torch.pow(2.0, -capture.frame_ev.float())[:, None, None, None]


def with_extra_probes(suite: SuiteData, n: int, seed: int = 0) -> SuiteData:
    """The suite with `n` more held-out probes: positions uniform in the room's free space
    (EXTRA_PROBE_MARGIN_M inside its bounding box; a draw outside the room or in furniture is
    redrawn), times uniform over the capture, drawn from `seed` (not near the scene's probes or
    anywhere the field does well); ground truth rendered by the simulator at the suite's eval
    height. The time series are unchanged. More probes shrink the noise of per-suite ratios."""
    from core.sim.render import ProbeError, check_probe, render_envmap
    from core.sim.spec import ProbePoint

    if n <= 0:
        return suite
    scene = suite.scene
    lo, hi = free_space_box(scene)
    t_end = (scene.frames - 1) / scene.fps
    gen = torch.Generator().manual_seed(seed)
    probes, gts = [], []
    for _ in range(n * EXTRA_PROBE_TRIES):
        if len(probes) == n:
            break
        x = tuple(round(float(v), 3) for v in lo + (hi - lo) * torch.rand(3, generator=gen, dtype=torch.float64))
        t = round(float(torch.rand((), generator=gen, dtype=torch.float64)) * t_end, 4)
        try:
            check_probe(scene, x)  # the rounded point is the one rendered
        except ProbeError:
            continue
        p = ProbePoint(x=x, t=t)
        probes.append(p)
        gts.append(render_envmap(scene, p.x, p.t, suite.eval_height).float())
    if len(probes) < n:
        raise RuntimeError(f"only {len(probes)} of {n} extra probes fit in {scene.name}'s free space")
    return SuiteData(name=suite.name, scene=scene, capture_dir=suite.capture_dir, probes=[*suite.probes, *probes],
                     gt=torch.cat([suite.gt, torch.stack(gts)]), global_point=suite.global_point,
                     global_time=suite.global_time, series=suite.series, render_seconds=suite.render_seconds)


def load_suite(name: str, cache_dir: Path, resolution: tuple[int, int] | None, gt_height: int,
               curve: str | None = None) -> SuiteData:
    """Render (or reuse) a suite's capture and collect its ground truth. `curve`: the camera
    curve of its frames (core.sim.camera_curves; None or "drawn": the scene's own, drawn by
    its name; a name forces it)."""
    from core.capture.prepare import load_prepared_capture
    from core.io.exr import read_exr
    from core.sim.suites import suite

    scene = suite(name)
    if resolution is not None:
        scene = scene.model_copy(update={"resolution": tuple(resolution)})
    if curve is not None and curve != scene.sensor.curve:
        scene = scene.model_copy(update={"sensor": scene.sensor.model_copy(update={"curve": curve})})
    capture_dir, render_seconds = prepare_capture(scene, cache_dir, gt_height)
    doc = json.loads((capture_dir / "capture.json").read_text())
    gt = torch.stack(
        [torch.from_numpy(read_exr(capture_dir / p["envmap"])[..., :3].copy()).float() for p in doc["probes"]]
    )
    capture = load_prepared_capture(capture_dir)
    mid = capture.num_frames // 2
    return SuiteData(
        name=name,
        scene=scene,
        capture_dir=capture_dir,
        probes=list(scene.probes),
        gt=gt,
        global_point=global_probe_point(scene, capture),
        global_time=float(capture.times[mid]),
        series=build_series(scene),
        render_seconds=render_seconds,
    )

