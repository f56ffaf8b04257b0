"""Write a simulated capture directory (format: docs/simulator.md, "lightfield-capture" v1).

The engine's capture loader reads it unchanged: LDR PNG frames + mp4, HDR EXR frames,
planar depth (.npz), intrinsics, c2w poses, the scene spec and ground-truth env maps. The
frames are the scene's camera's codes (core.sim.camera_curves, `sensor.curve`): the PNGs and
the mp4 declare what that camera's files declare, and capture.json states the transfer as a
capture app does (`transfer`) and, for the benches, the curve itself (`camera_curve`).
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from core.sim.cost import CostReport
from core.sim.render import check_probe, render_envmap, render_frame
from core.sim.sensor import exposure_ev, frame_evs, scene_curve, sensor_sequence
from core.sim.spec import ProbePoint, SceneSpec, SceneSpecError

CAPTURE_FORMAT = "lightfield-capture"
CAPTURE_VERSION = 1


def parse_probes(text: str) -> list[ProbePoint]:
    """'x,y,z@t;x,y,z@t' -> probe points (t in seconds; '@t' optional, default 0)."""
    probes = []
    for item in filter(None, (s.strip() for s in text.split(";"))):
        pos, _, t = item.partition("@")
        try:
            xyz = [float(v) for v in pos.split(",")]
            tv = float(t) if t else 0.0
        except ValueError:
            raise SceneSpecError(f"probes: cannot parse {item!r}; expected 'x,y,z@t'") from None
        if len(xyz) != 3:
            raise SceneSpecError(f"probes: {item!r} needs three coordinates x,y,z")
        probes.append(ProbePoint(x=tuple(xyz), t=tv))
    return probes


def _check_probes(scene: SceneSpec, probes: Sequence[ProbePoint]) -> None:
    for i, p in enumerate(probes):
        if p.t > scene.duration + 1e-9:
            raise SceneSpecError(f"probes[{i}].t={p.t} is after the last frame time {scene.duration}")
        check_probe(scene, p.x)


def write_capture(
    scene: SceneSpec,
    out_dir: str | os.PathLike,
    probes: Sequence[ProbePoint] | None = None,
    envmap_height: int = 64,
    video: bool = True,
) -> dict:
    """Render every frame and the probes' ground truth, write the capture directory and
    return the capture.json document plus a "cost" entry (per-effect seconds and rays).

    `probes=None` uses the scene's own held-out probes."""
    from core.io.depth import write_depth_npz  # noqa: PLC0415 — core.io.depth pulls in av, cv2, OpenEXR, PIL: imported when used
    from core.io.exr import atomic_write, write_exr  # noqa: PLC0415 — core.io.exr pulls in av, cv2, OpenEXR, PIL: imported when used
    from core.sim.camera_curves import write_png, write_video  # noqa: PLC0415 — core.io pulls in av, cv2, OpenEXR, PIL: imported when used

    probes = list(scene.probes if probes is None else probes)
    _check_probes(scene, probes)
    out = Path(out_dir)
    for sub in ("frames", "hdr", "gt"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    cost = CostReport()
    curve = scene_curve(scene)
    renders = []
    for i in range(scene.frames):
        r = render_frame(scene, i)
        cost.merge(r.cost)
        renders.append(r)
    ldr = sensor_sequence(scene, [r.hdr for r in renders], cost)
    frame_paths, hdr_paths = [], []
    for i, (r, image) in enumerate(zip(renders, ldr)):
        frame_paths.append(f"frames/{i:05d}.png")
        hdr_paths.append(f"hdr/{i:05d}.exr")
        write_png(out / frame_paths[-1], image, curve)
        write_exr(out / hdr_paths[-1], r.hdr.numpy())
    write_depth_npz(out / "depth.npz", np.stack([r.depth.numpy() for r in renders]))
    video_path = None
    if video:
        video_path = "video.mp4"
        write_video(out / video_path, ldr, scene.fps, curve)
    probe_docs = []
    for i, p in enumerate(probes):
        env = render_envmap(scene, p.x, p.t, envmap_height, cost)
        rel = f"gt/probe_{i:02d}_t{int(round(p.t * scene.fps)):03d}.exr"
        write_exr(out / rel, env.numpy())
        probe_docs.append({"x": list(p.x), "t": p.t, "envmap": rel})
    (out / "scene.json").write_text(scene.model_dump_json(indent=2))
    k = renders[0].camera.intrinsics
    doc = {
        "format": CAPTURE_FORMAT,
        "version": CAPTURE_VERSION,
        "fps": scene.fps,
        "frame_count": scene.frames,
        "intrinsics": k.as_dict(),
        "poses": [r.camera.c2w.reshape(-1).tolist() for r in renders],
        "frames": frame_paths,
        "video": video_path,
        "depth": "depth.npz",
        "hdr_frames": hdr_paths,
        "scene": "scene.json",
        "exposure_ev": exposure_ev(scene),
        # what the capture app states of its camera's transfer (core.capture.load reads it), and the
        # curve itself (informational: the ground truth a bench linearises with; the tone curve of
        # `filmic` is not stated, as phones do not state theirs)
        "transfer": curve.oetf,
        "camera_curve": curve.name,
        "probes": probe_docs,
    }
    if scene.has("sensor") and scene.sensor.auto_exposure:
        evs = [round(e, 6) for e in frame_evs(scene, [r.hdr for r in renders])]
        doc["sensor_frame_ev"] = evs  # informational: what the sensor did, stated or not
        if scene.sensor.record_exposure:
            doc["frame_ev"] = evs  # the capture's per-frame exposure metadata (core.capture.load reads it)
    # written last and atomically: a capture.json means a complete capture
    atomic_write(out / "capture.json", json.dumps(doc, indent=2).encode())
    return {**doc, "cost": cost.as_dict()}
