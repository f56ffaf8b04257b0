"""A person walking through a static camera's view of real panorama rooms: read as the light
changing, or painted out (core/capture/transients.py; docs/captures.md).

    python -m bench.transients --split dev [--limit N] [--iterations 200] [--curve drawn|NAME|all] [-o out.json]

Per panorama of MANIFEST.tsv (`--split`; tune on dev, report test once): a static view (the
yaw and pitch of bench.tracking's clips, 60 deg FOV, SIZE) of the panorama pasted on the
assumed box room (core.sim.panorama_room), FRAMES frames at FPS under one exposure (the clip's
mean at mid-grey), encoded by the phone's camera curve (core.sim.camera_curves, `--curve`: by
default drawn per panorama from srgb, rec709, filmic and hlg10), H.264 declaring the curve's
transfer: a plain video with no parameters, as a user uploads it (each row's `curve`; summaries
per curve in `summary_per_curve`). A
simulated figure (a head and a body 3/4 of the frame high, a textured coat whose brightness is
drawn per panorama, 0.1x-2x mid-grey) walks from left to right over frames WALK. Clips:
* `walk`: the figure under steady light;
* `walk-halved`: the figure, and the room's light halved from the middle frame on (a real
  change that must stay one);
* `pool-off`: no figure; a lamp's pool of light (a soft blob adding 2x the room's light at its
  centre) switches off at the middle frame (a local change of light that must not be painted
  out);
* `clean`: no figure, steady light (the reference);
* `pans`: bench.auto_exposure_pans' 90 deg pan under one exposure and steady light, with and
  without the figure, and two without it that must not be painted: under a phone's
  auto-exposure (`pan-ae`) and with the light halved from the middle frame (`pan-halved`);
  per clip: tracked or not, its largest rotation error, read as changing light or not, the
  painted share.
Per clip, as loaded: whether the temporal decision reads changing light with the default
(`transients` unset: "remove") and with "keep"; the painted share; for the figure, the mask's
intersection over union with where it was (at full resolution) and its recall.

Jobs (`walk` with the default and with "keep", and `clean`; the draft at `--iterations` steps,
work height 72): the env map at the camera at t = 0 and at the middle frame's time (the figure
in view); `map_change_stops` = RMS over the sphere of log2 of their luminance ratio (static
light: 0 is right); the middle map's diffuse rel si-RMSE against the panorama rotated into the
camera, with a constant map of the clean frame's mean colour beside it (linearised with the
clip's camera curve). The figure is
simulated: real people cast shadows, reflect, and stop.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path

import torch

FRAMES = 16
FPS = 4.0
SIZE = (160, 120)
WALK = (3, 12)  # the figure's first and last frame
WORK_HEIGHT = 72
GT_HEIGHT = 64


def figure(h: int, w: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A person's silhouette [h, w] bool (a head over a body, 3/4 of the frame high, w/6 wide)
    and a coat [h, w, 3] in linear units (textured; brightness 0.1x-2x mid-grey, drawn)."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    tall, wide = 0.75 * h, w / 6
    top = h - tall
    head = ((yy - (top + 0.08 * tall)) ** 2 + (xx - wide / 2) ** 2) < (0.08 * tall) ** 2
    body = (yy >= top + 0.16 * tall) & (xx >= 0.05 * wide) & (xx < 0.95 * wide)
    shape = head | body
    level = 0.18 * 10 ** (float(torch.rand(1, generator=g)) * math.log10(20.0) - 1.0)
    colour = 0.6 + 0.8 * torch.rand(3, generator=g)
    texture = 0.7 + 0.6 * torch.nn.functional.avg_pool2d(torch.rand(1, 1, h, w, generator=g), 3, 1, 1)[0, 0]
    return shape, level * colour * texture[..., None]


def view_curve(filename: str, curve: str = "drawn"):
    """The camera curve of the panorama's clips (`curve` "drawn": drawn by the capture's name,
    this bench and the file, among every realistic curve of a video; a name forces it)."""
    from core.sim.camera_curves import VIDEO, resolve

    return resolve(curve, f"transients:{filename}", VIDEO)


def clip(
    pano: torch.Tensor, yaw: float, pitch: float, seed: int, *, walker: bool, light, curve
) -> tuple[torch.Tensor, torch.Tensor]:
    """(the camera `curve`'s codes [T, H, W, 3], where the figure is [T, H, W]) of one static
    view; `light(i, hdr)` returns frame i's linear image from the steady one."""
    from bench.tracking import HFOV_DEG
    from core.camera import Camera, Intrinsics
    from core.exposure import luminance
    from core.sim.panorama_room import PanoramaRoom
    from core.sim.state import pose_from_yaw_pitch
    from core.tracking.room import assumed_room

    w, h = SIZE
    room = PanoramaRoom(pano, assumed_room(), torch.zeros(3))
    steady = room.render(Camera(Intrinsics.from_hfov(w, h, HFOV_DEG), pose_from_yaw_pitch((0, 0, 0), yaw, pitch)), 2)[0]
    steady = steady * (0.18 / float(luminance(steady).mean().clamp_min(1e-12)))
    hdr = torch.stack([light(i, steady) for i in range(FRAMES)])
    where = torch.zeros(FRAMES, h, w, dtype=torch.bool)
    if walker:
        shape, coat = figure(h, w, seed)
        pw = w // 6
        first, last = WALK
        for i in range(first, last + 1):
            x0 = round((i - first) / (last - first) * (w - pw))
            s = torch.zeros(h, w, dtype=torch.bool)
            s[:, x0:x0 + pw] = shape[:, :pw]
            hdr[i][s] = coat[:, :pw][shape[:, :pw]]
            where[i] = s
    return curve.encode(hdr), where


def pool(h: int, w: int) -> torch.Tensor:
    """A lamp's pool of light [h, w, 1]: 2 at its centre (a third across, two thirds down)."""
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    return 2.0 * torch.exp(-((xx - 0.35) ** 2 + (yy - 0.65) ** 2) / 0.03)[..., None]


def pans(pano: torch.Tensor, yaw: float, pitch: float, seed: int, stem: Path, curve) -> dict:
    """bench.auto_exposure_pans' pan (90 deg, 16 frames at 10 fps, one exposure, steady light)
    with and without the figure walking across the frame over frames 4-11 (with the room's
    drift in the frame, the camera half following them), under an auto-exposure, and with the
    light halved from the middle frame. Per clip as loaded: tracked or taken for a static
    camera, the tracking method, the largest rotation error (deg, frames kept, world = the
    first kept frame), whether the temporal decision reads changing light, the painted share.
    Every clip is the camera `curve`'s (core.sim.camera_curves)."""
    from bench.auto_exposure_pans import FPS as PAN_FPS, ae_clip
    from core.capture.params import CaptureParams
    from core.capture.prepare import load_prepared_capture
    from core.capture.temporal import decide_temporal
    from core.sim.camera_curves import VIDEO, write_video

    ldr, _, poses = ae_clip(pano, yaw, pitch, light=lambda i, n: 1.0, curve=curve)
    ae, _, _ = ae_clip(pano, yaw, pitch, speed=0.5, curve=curve)
    halved, _, _ = ae_clip(pano, yaw, pitch, light=lambda i, n: 1.0 if i < n // 2 else 0.5, curve=curve)
    T, h, w, _ = ldr.shape
    lin = curve.decode(ldr)
    shape, coat = figure(h, w, seed)
    pw = w // 6
    for i in range(4, 12):
        x0 = round((i - 4) / 7 * (w - pw))
        s = torch.zeros(h, w, dtype=torch.bool)
        s[:, x0:x0 + pw] = shape[:, :pw]
        lin[i][s] = coat[:, :pw][shape[:, :pw]]
    out = {}
    for name, frames in (("pan", ldr), ("pan-walk", curve.encode(lin)), ("pan-ae", ae), ("pan-halved", halved)):
        video = write_video(Path(f"{stem}-{name}.mp4"), frames, PAN_FPS, curve)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cap = load_prepared_capture(video, params=CaptureParams(fps=PAN_FPS, **curve.job_params(VIDEO)))
        kept = (cap.times.double() * PAN_FPS).round().long()
        truth = torch.stack([torch.as_tensor(poses[int(k)], dtype=torch.float64) for k in kept])
        rel_true = truth[0, :3, :3].T @ truth[:, :3, :3]
        rel_est = cap.poses[0, :3, :3].T @ cap.poses[:, :3, :3]
        cos = ((rel_true.transpose(1, 2) @ rel_est).diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2
        out[name] = {"static_camera": cap.static_camera, "method": cap.metadata.get("tracking", {}).get("method"),
                     "frames_kept": cap.num_frames,
                     "max_rotation_error_deg": round(math.degrees(float(cos.clamp(-1, 1).acos().max())), 2),
                     "read_as_changing_light": decide_temporal(cap).uses_time,
                     "exposure_detected": bool(cap.metadata.get("exposure_estimate", {}).get("applied", False)),
                     "painted_share": cap.metadata.get("transients", {}).get("pixel_share", 0.0)}
    return out


def evaluate(path: Path, iterations: int, workdir: Path, pans_only: bool = False, curve: str = "drawn") -> dict:
    from bench.auto_exposure_pans import map_change_stops, score_runs
    from bench.tracking import _view
    from core.capture.params import CaptureParams
    from core.capture.prepare import load_prepared_capture
    from core.capture.temporal import decide_temporal
    from core.capture.transients import transient_mask
    from core.engine.job import run_job
    from core.engine.params import JobParams
    from core.engine.presets import preset
    from core.envmap import resize_envmap, rotate_envmap
    from core.sim.camera_curves import VIDEO, write_video
    from core.sim.panorama_room import load_panorama
    from core.sim.state import pose_from_yaw_pitch

    pano = load_panorama(path, 256)
    yaw, pitch = _view(path.name)
    seed = sum(path.name.encode())
    cam = view_curve(path.name, curve)
    extra_params = cam.job_params(VIDEO)  # {} but for the reference, whose video cannot state its curve
    stem = path.stem + ("" if curve == "drawn" else f"-{cam.name}")
    if pans_only:
        return {"file": path.name, "curve": cam.name, "pans": pans(pano, yaw, pitch, seed, workdir / stem, cam)}
    w, h = SIZE
    mid = FRAMES // 2
    lights = {
        "walk": (True, lambda i, x: x),
        "walk-halved": (True, lambda i, x: x if i < mid else 0.5 * x),
        "pool-off": (False, lambda i, x: x * (1.0 + pool(h, w)) if i < mid else x),
        "clean": (False, lambda i, x: x),
    }
    out = {"file": path.name, "curve": cam.name, "clips": {}}
    videos = {}
    for name, (walker, light) in lights.items():
        ldr, where = clip(pano, yaw, pitch, seed, walker=walker, light=light, curve=cam)
        videos[name] = write_video(workdir / f"{stem}-{name}.mp4", ldr, FPS, cam)
        row = {}
        for mode in ("remove", "keep"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                params = CaptureParams(fps=FPS, transients=mode, **extra_params)
                cap = load_prepared_capture(videos[name], params=params)
            row[f"changing_light_{mode}"] = decide_temporal(cap).uses_time
            if mode == "remove":
                found = cap.metadata.get("transients", {})
                row.update(static_camera=cap.static_camera, painted_share=found.get("pixel_share", 0.0),
                           frames_with_transients=found.get("frames_with_transients", 0), rank=found.get("rank"))
            elif walker:  # the mask of the frames as loaded ("keep" leaves them so)
                mask = transient_mask(cap)[0]
                if mask.shape == where.shape:
                    row["iou"] = round(float((mask & where).sum()) / max(float((mask | where).sum()), 1.0), 3)
                    row["recall"] = round(float((mask & where).sum()) / max(float(where.sum()), 1.0), 3)
        out["clips"][name] = row
    out["pans"] = pans(pano, yaw, pitch, seed, workdir / stem, cam)
    gt = rotate_envmap(resize_envmap(pano, GT_HEIGHT), pose_from_yaw_pitch((0, 0, 0), yaw, pitch)[:3, :3].T)
    cfg = preset("draft").with_overrides({"distill.iterations": iterations, "distill.work_height": WORK_HEIGHT})
    t_mid = mid / FPS
    preds, runs = {}, {}
    for name, clip_name, extra in (("default", "walk", {}), ("keep", "walk", {"transients": "keep"}),
                                   ("clean", "clean", {})):
        t0 = time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = run_job(
                videos[clip_name],
                None,
                JobParams.model_validate({"preset": "draft", "fps": FPS, **extra_params, **extra}),
                workdir / f"{stem}-job-{name}",
                config=cfg,
            )
        art = result.artefact
        first, _ = art.envmap(torch.zeros(3), 0.0, GT_HEIGHT)
        middle, _ = art.envmap(torch.zeros(3), t_mid, GT_HEIGHT)
        preds[name] = middle
        runs[name] = {
            "uses_time": art.meta["temporal"]["uses_time"],
            "map_change_stops": round(map_change_stops(first, middle), 3),
            "cpu_s": round(time.process_time() - t0, 1),
        }
    clean_ldr, _ = clip(pano, yaw, pitch, seed, walker=False, light=lights["clean"][1], curve=cam)
    score_runs(runs, preds, gt, clean_ldr[0], out, cam)
    return out


def summarise(rows: list[dict]) -> dict:
    mean = lambda xs: round(sum(xs) / len(xs), 4) if xs else None  # noqa: E731
    pan = _pans_summary(rows, mean)
    if any("clips" not in r for r in rows):  # --pans-only
        return {"panoramas": len(rows), "pans": pan}
    clips = {}
    for name in ("walk", "walk-halved", "pool-off", "clean"):
        cs = [r["clips"][name] for r in rows]
        clips[name] = {
            "read_as_changing_light": {m: sum(c[f"changing_light_{m}"] for c in cs) for m in ("remove", "keep")},
            "painted": sum(c["frames_with_transients"] > 0 for c in cs),
            "painted_share_mean": mean([c["painted_share"] for c in cs]),
            "static_camera": sum(c["static_camera"] for c in cs),
        }
        scored = [c for c in cs if "iou" in c]  # a clip tracking took for a moving camera has no mask to score
        if scored:
            clips[name].update(iou_mean=mean([c["iou"] for c in scored]), iou_min=min(c["iou"] for c in scored),
                               recall_mean=mean([c["recall"] for c in scored]), scored=len(scored))
    runs = ("default", "keep", "clean")
    return {"panoramas": len(rows), "clips": clips, "pans": pan,
            "map_change_stops_mean": {k: mean([r["runs"][k]["map_change_stops"] for r in rows]) for k in runs},
            "map_change_stops_max": {k: max(r["runs"][k]["map_change_stops"] for r in rows) for k in runs},
            "jobs_with_time_input": {k: sum(r["runs"][k]["uses_time"] for r in rows) for k in runs},
            "diffuse_si_rmse_rel_mean": {**{k: mean([r["runs"][k]["diffuse_si_rmse_rel"] for r in rows]) for k in runs},
                                         "mean-colour": mean([r["mean_colour_diffuse_si_rmse_rel"] for r in rows])},
            "cpu_s_mean": {k: mean([r["runs"][k]["cpu_s"] for r in rows]) for k in runs}}


def _pans_summary(rows: list[dict], mean) -> dict:
    pan = {name: {"taken_for_static": sum(r["pans"][name]["static_camera"] for r in rows),
                  "read_as_changing_light": sum(r["pans"][name]["read_as_changing_light"] for r in rows),
                  "within_1deg": sum(r["pans"][name]["max_rotation_error_deg"] <= 1.0 for r in rows)}
           for name in ("pan", "pan-walk", "pan-ae", "pan-halved")}
    for name in pan:
        shares = [r["pans"][name].get("painted_share", 0.0) for r in rows]
        pan[name].update(painted=sum(x > 0 for x in shares), painted_share_mean=mean(shares))
    return pan


def main(argv: list[str] | None = None) -> int:
    from bench.real_panoramas import add_split_arguments

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_split_arguments(p, iterations=200)
    p.add_argument("--rescore", default=None, metavar="LOG",
                   help="rebuild the report from a run's printed per-panorama lines (JSON, one per line) and exit")
    p.add_argument(
        "--pans-only",
        action="store_true",
        help="only the pans (pan, pan-walk, pan-ae, pan-halved: tracking and the temporal decision; no jobs)",
    )
    args = p.parse_args(argv)
    if args.rescore:
        return _write([json.loads(line) for line in Path(args.rescore).read_text().splitlines()
                       if line.startswith('{"file"')], args)

    from bench.panoramas import split_files
    from bench.real_panoramas import rows_over
    from core.sim.camera_curves import VIDEO, run_choices

    rows = rows_over(
        split_files(args.hdri_dir, args.split, args.limit),
        lambda f, work, curve: evaluate(f, args.iterations, work, args.pans_only, curve),
        args.workdir,
        run_choices(args.curve, VIDEO),
    )
    return _write(rows, args)


def _write(rows: list[dict], args) -> int:
    from bench.real_panoramas import curve_summaries
    from bench.report import show_and_write

    report = {"split": args.split, "frames": FRAMES, "fps": FPS, "size": list(SIZE), "walk": list(WALK),
              "iterations": args.iterations, "curve": args.curve, **curve_summaries(rows, summarise),
              "panoramas": rows}
    show_and_write(report["summary"], report, args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
