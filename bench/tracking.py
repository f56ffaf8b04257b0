"""`lightfield bench` section "tracking": what camera tracking costs and what it is worth.

Speed: `track_camera` on 20-frame 320x240 clips rendered from the bundled CC0 panorama (a
`dev` panorama, assets/): a pan from one spot and a walk with parallax; CPU seconds of this
process (time.process_time, all threads) and wall seconds. Target (issue 13): <= 15 s CPU.

Accuracy (the product, the way a user runs it): per panorama of MANIFEST.tsv, a phone-style
pan (PAN_FRAMES frames, PAN_DEG of yaw with a pitch wobble, 60 deg FOV, one locked exposure,
encoded by the phone's camera curve (core.sim.camera_curves: drawn per file name from srgb,
rec709, filmic and hlg10 unless `curve` forces one; each image's `curve`), H.264 at 10 fps
declaring it) from a view drawn per file name, written as an mp4 and estimated with
`run_job` (no intrinsics given, as a user would); the env map at the camera at t = 0 (the
world origin: world = first camera) is compared with the panorama rotated into that camera:
* `tracked`: no poses given (the product tracks the camera);
* `true-poses`: the true poses given in `params.poses`;
* `static`: tracking off (`params.tracking = "off"`: what the product did before it tracked);
* `mean-colour`: a constant map of frame 0's mean colour, linearised with its camera curve.
Target: tracked within 5 % of true-poses on diffuse rel si-RMSE, and better than mean-colour.
`test` panoramas are evaluated once for the report, never tuned on.
"""
from __future__ import annotations

import math
import random
import time
from pathlib import Path

import torch

SPEED_FRAMES = 20
SPEED_SIZE = (320, 240)
SPEED_TARGET_CPU_S = 15.0
PAN_DEG = 45.0
PITCH_WOBBLE_DEG = 4.0
HFOV_DEG = 60.0
FPS = 10.0
GT_HEIGHT = 64
PANO_HEIGHT = 256
SEED = 13
BUNDLED = Path(__file__).resolve().parents[1] / "assets" / "sample_panorama.hdr"


def pan_poses(n: int, yaw0: float, pitch0: float) -> list[torch.Tensor]:
    from core.sim.state import pose_from_yaw_pitch

    return [pose_from_yaw_pitch((0, 0, 0), yaw0 + PAN_DEG * i / max(n - 1, 1),
                                pitch0 + PITCH_WOBBLE_DEG * math.sin(i / 3)) for i in range(n)]


def walk_poses(n: int, scale: float = 1.0) -> list[torch.Tensor]:
    """A 1.3 m walk (1.2 m across, 0.5 m forward) turning 40 deg; `scale` scales its translation."""
    from core.sim.state import pose_from_yaw_pitch

    return [
        pose_from_yaw_pitch(
            (scale * (-0.6 + 1.2 * i / (n - 1)), scale * 0.1 * math.sin(i / 4), scale * -0.5 * i / (n - 1)),
            20 - 40 * i / (n - 1),
            0,
        )
        for i in range(n)
    ]


def _clip(pano: torch.Tensor, poses, size, centre=(0.0, 0.0, 0.0), curve=None):
    """(frames, depth, intrinsics) of the clip: the camera `curve`'s codes, or (None) the
    engine's convention (the speed clips, tracked in memory)."""
    from core.camera import Camera, Intrinsics
    from core.sim.panorama_room import PanoramaRoom, render_clip
    from core.tracking.room import assumed_room

    intr = Intrinsics.from_hfov(size[0], size[1], HFOV_DEG)
    room = PanoramaRoom(pano, assumed_room(), torch.tensor(centre))
    ldr, depth, _ = render_clip(room, [Camera(intr, p) for p in poses], curve=curve)
    return ldr, depth, intr


def pan_curve(filename: str, curve: str = "drawn"):
    """The camera curve of the panorama's pan (`curve` "drawn": drawn by the capture's name,
    this bench and the file, among every realistic curve of a video; a name forces it)."""
    from core.sim.camera_curves import VIDEO, resolve

    return resolve(curve, f"tracking:{filename}", VIDEO)


def run_speed() -> dict:
    """Tracking CPU and wall seconds on the two 20-frame 320x240 clips."""
    from core.sim.panorama_room import load_panorama
    from core.tracking.capture_geometry import pose_errors
    from core.tracking.geometry import relative_to_first
    from core.tracking.track import track_camera

    pano = load_panorama(BUNDLED)
    out = {"frames": SPEED_FRAMES, "size": list(SPEED_SIZE), "target_cpu_s": SPEED_TARGET_CPU_S, "clips": {}}
    for name, poses, centre in (("pan", pan_poses(SPEED_FRAMES, 10.0, 0.0), (0.0, 0.0, 0.0)),
                                ("walk", walk_poses(SPEED_FRAMES), (0.0, 0.0, -1.0))):
        ldr, _, intr = _clip(pano, poses, SPEED_SIZE, centre)
        wall = time.perf_counter()
        r = track_camera(ldr, intr)
        wall = time.perf_counter() - wall
        true, _ = relative_to_first(torch.stack(poses).numpy())
        rot, pos = pose_errors(r.poses, torch.from_numpy(relative_to_first(true[r.kept])[0]))
        out["clips"][name] = {
            "method": r.method,
            "cpu_s": round(r.cpu_seconds, 3),
            "wall_s": round(wall, 3),
            "frames_kept": len(r.kept),
            "reprojection_error_px": r.reprojection_error_px,
            "max_rotation_error_deg": round(rot, 4),
            "max_position_error_m": round(pos, 4) if r.scale is None or r.scale.source == "depth" else None,
            "scale_source": r.summary()["scale_source"],
            "within_target": r.cpu_seconds <= SPEED_TARGET_CPU_S,
        }
    return out


def _view(filename: str) -> tuple[float, float]:
    rng = random.Random(f"{SEED}:{filename}")
    return rng.uniform(-180.0, 180.0), rng.uniform(-10.0, 10.0)


def _estimate(video: Path, params: dict, workdir: Path, iterations: int, work_height: int) -> torch.Tensor:
    """The product: run_job on the uploaded video, then the env map at the origin at t = 0."""
    from core.engine.job import run_job
    from core.engine.params import JobParams
    from core.engine.presets import preset

    cfg = preset("draft").with_overrides({"distill.iterations": iterations, "distill.work_height": work_height})
    result = run_job(
        video, None, JobParams.model_validate({"preset": "draft", "fps": FPS, **params}), workdir, config=cfg
    )
    env, _ = result.artefact.envmap(torch.zeros(3), 0.0, GT_HEIGHT)
    return env


def evaluate_panorama(path: Path, frames: int, size, iterations: int, work_height: int, sphere_size: int,
                      workdir: Path, curve: str = "drawn") -> dict:
    from bench.suite.evaluation import score_probe
    from core.conventions import equirect_width
    from core.envmap import resize_envmap, rotate_envmap
    from core.sim.camera_curves import VIDEO, write_video
    from core.sim.panorama_room import load_panorama

    pano = load_panorama(path, PANO_HEIGHT)
    yaw, pitch = _view(path.name)
    poses = pan_poses(frames, yaw, pitch)
    cam = pan_curve(path.name, curve)
    ldr, _, _ = _clip(pano, poses, size, curve=cam)
    video = write_video(workdir / f"{path.stem}-{cam.name}.mp4", ldr, FPS, cam)
    R0 = poses[0][:3, :3]
    gt = rotate_envmap(resize_envmap(pano, GT_HEIGHT), R0.T)  # world = the first camera's frame
    rel = [torch.linalg.inv(poses[0]) @ p for p in poses]
    extra = cam.job_params(VIDEO)  # {} but for the reference, whose video cannot state its curve
    runs = {
        "tracked": {**extra},
        "true-poses": {"poses": [p.reshape(-1).tolist() for p in rel], **extra},
        "static": {"tracking": "off", **extra},
    }
    preds, seconds, meta = {}, {}, {}
    for name, params in runs.items():
        t0 = time.perf_counter()
        preds[name] = _estimate(video, params, workdir / f"{path.stem}-{cam.name}-{name}", iterations, work_height)
        seconds[name] = round(time.perf_counter() - t0, 2)
    mean = cam.decode(ldr[0]).reshape(-1, 3).mean(0)  # linearised with the clip's own curve
    preds["mean-colour"] = mean.expand(GT_HEIGHT, equirect_width(GT_HEIGHT), 3).clone()
    return {"file": path.name, "curve": cam.name, "yaw_deg": round(yaw, 2), "pitch_deg": round(pitch, 2),
            "seconds": seconds, "scores": score_probe(preds, gt, sphere_size), **meta}


def run_tracking(hdri_dir: Path, limit: int | None, sphere_size: int, quick: bool, workdir: Path,
                 splits: tuple[str, ...] = ("dev", "test"), curve: str = "drawn") -> dict:
    from bench.panoramas import read_manifest
    from core.sim.camera_curves import REFERENCE, VIDEO, group_by_curve, run_choices

    frames, size = (12, (160, 120)) if quick else (20, (320, 240))
    iterations, work_height = (60, 72) if quick else (300, 96)
    out: dict = {
        "speed": run_speed(),
        "protocol": (
            f"pan of {PAN_DEG:g} deg yaw (+-{PITCH_WOBBLE_DEG:g} deg pitch wobble) from one spot, {frames} frames "
            f"{size[0]}x{size[1]}, {HFOV_DEG:g} deg FOV, locked exposure, H.264 at {FPS:g} fps; run_job "
            f"draft preset at {iterations} steps, work height {work_height}; env map at the first camera, t = 0; "
            f"camera curve {curve} (core.sim.camera_curves; each image's `curve`)"
        ),
        "curve": curve,
        "splits": {},
    }
    hdri_dir = Path(hdri_dir)
    if not (hdri_dir / "MANIFEST.tsv").is_file():
        out["skipped"] = f"no MANIFEST.tsv in {hdri_dir}: the accuracy part was not run"
        return out
    rows = read_manifest(hdri_dir)
    for split in splits:
        files = sorted(r["filename"] for r in rows if r.get("split") == split and (hdri_dir / r["filename"]).is_file())
        files = files[:limit] if limit is not None else files
        if not files:
            continue
        images = []
        for f in files:
            d = workdir / "tracking" / split
            d.mkdir(parents=True, exist_ok=True)
            for choice in run_choices(curve, VIDEO):
                images.append(evaluate_panorama(hdri_dir / f, frames, size, iterations, work_height, sphere_size, d,
                                                choice))
        realistic = [im for im in images if im["curve"] != REFERENCE] or images
        out["splits"][split] = {"files": files, **split_summary(realistic), "images": images,
                                "per_curve": group_by_curve(images, split_summary)}
    return out


def split_summary(images: list[dict]) -> dict:
    """Mean scores per method over the images, and the targets: tracked within 5 % of
    true-poses on diffuse rel si-RMSE, and better than the constant map."""
    from bench.suite.evaluation import mean_scores

    methods = {name: mean_scores([im["scores"][name] for im in images])
               for name in ("tracked", "true-poses", "static", "mean-colour")}
    t, p, c = (methods[n]["diffuse"]["si_rmse_rel"] for n in ("tracked", "true-poses", "mean-colour"))
    return {"methods": methods, "tracked_vs_true_poses": round(t / p - 1.0, 4) if p else None,
            "within_5_percent": bool(p and t <= 1.05 * p), "better_than_constant": bool(t < c)}
