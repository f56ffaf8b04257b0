"""Auto-exposure pans of real panoramas: what an unrecorded exposure does to a job, and what
`frame_ev="estimate"` recovers (docs/captures.md, "Exposure").

    python -m bench.auto_exposure_pans --split dev [--limit N] [--iterations 200] [--curve drawn|NAME|all] [-o out.json]

Per panorama of MANIFEST.tsv (`--split`; tune on dev, report test once): a phone-style pan
from one spot (PAN_DEG of yaw with a pitch wobble, 60 deg FOV, FRAMES frames) of the panorama
pasted on the assumed box room (core.sim.panorama_room), scaled so the clip's mean luminance is
mid-grey, exposed per frame by a phone-style auto-exposure (core.sim.sensor.metered_evs),
encoded by the phone's camera curve (core.sim.camera_curves, `--curve`: by default drawn per
panorama from srgb, rec709, filmic and hlg10; 8 or 10 bits), H.264 at 10 fps declaring the
curve's transfer: a plain video with no poses, no intrinsics, no exposures, as a user uploads
it (each row's `curve`; summaries per curve in `summary_per_curve`). Then:
* `decision`: the temporal decision of the capture as loaded and tracked with `frame_ev`
  unset (`auto`: the product's default, which looks for a moving camera's auto-exposure),
  `"locked"` (no exposure handling) and `"estimate"` (static light is the truth);
  `auto_detected`: whether the default applied an estimated exposure (it does for a moving
  camera whose course spans more than the temporal floor; `tracked`: the camera was followed);
* `estimate_error_stops`: the largest |estimated - true| exposure over the frames tracking
  kept, both relative to the first kept frame;
* `auto` / `locked` / `estimate` / `stated` (the true exposures given): run_job (draft at `--iterations`
  steps, work height 72), the env map at the camera (the origin) at t = 0 and at the last
  frame's time; `drift_stops` = |log2| of the ratio of their mean luminances (static light:
  0 is right), and the t = 0 map's diffuse rel si-RMSE against the panorama rotated into the
  first camera, with a constant map of frame 0's mean colour beside it (linearised with the
  clip's own camera curve);
  `map_change_stops` = the RMS over the sphere of log2 of the two maps' luminance ratio: how
  much the answer at the camera changed over the clip (static light: 0 is right; an
  auto-exposure keeps each frame's mean near mid-grey, so the level alone barely moves while
  what was seen brighter or darker does);
* `locked_dimming`, the control: the same pan under ONE exposure with the light halved from
  the middle frame on (a real change of the whole view): the default takes it for exposure
  (`auto_detected`: the frames alone cannot tell it from one), `frame_ev="locked"` must read
  it as changing light (`read_as_changing_light`).
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
PAN_DEG = 90.0
SIZE = (160, 120)
FPS = 10.0
WORK_HEIGHT = 72
GT_HEIGHT = 64
DIMMING = 0.5  # the locked-exposure control: the light halved from the middle frame on


def pan_curve(filename: str, curve: str = "drawn"):
    """The camera curve of the panorama's pans (`curve` "drawn": drawn by the capture's name,
    this bench and the file, among every realistic curve of a video; a name forces it)."""
    from core.sim.camera_curves import VIDEO, resolve

    return resolve(curve, f"auto_exposure_pans:{filename}", VIDEO)


def ae_clip(pano: torch.Tensor, yaw: float, pitch: float, dimming: float | None = None, *, speed: float = 0.5,
            delay: int = 0, light=None, curve=None):
    """(frames [T, H, W, 3] at each frame's exposure, the exposures, poses) of one pan, exposed by
    an auto-exposure moving `speed` of the way to the metered ev per frame, metering the frame
    `delay` frames before. With `dimming`: the light times `dimming` from the middle frame on,
    under ONE exposure (the clip's mean at mid-grey): a locked exposure and a real change of
    light; `light(i, FRAMES)`: the light's factor per frame, under one exposure too. The frames
    are the camera `curve`'s codes (core.sim.camera_curves), or (None) 8-bit frames in the
    engine's convention (a capture built in memory)."""
    from bench.tracking import HFOV_DEG, PITCH_WOBBLE_DEG
    from core.camera import Camera, Intrinsics
    from core.conventions import expose, tonemap
    from core.exposure import luminance
    from core.sim.panorama_room import PanoramaRoom
    from core.sim.sensor import metered_evs
    from core.sim.state import pose_from_yaw_pitch
    from core.tracking.room import assumed_room

    poses = [
        pose_from_yaw_pitch((0, 0, 0), yaw + PAN_DEG * i / (FRAMES - 1), pitch + PITCH_WOBBLE_DEG * math.sin(i / 3))
        for i in range(FRAMES)
    ]
    intr = Intrinsics.from_hfov(SIZE[0], SIZE[1], HFOV_DEG)
    room = PanoramaRoom(pano, assumed_room(), torch.zeros(3))
    hdr = torch.stack([room.render(Camera(intr, p), 2)[0] for p in poses])
    if dimming is not None:
        light = lambda i, n: 1.0 if i < n // 2 else dimming  # noqa: E731
    if light is not None:
        hdr = hdr * torch.tensor([float(light(i, FRAMES)) for i in range(FRAMES)])[:, None, None, None]
    hdr = hdr * (0.18 / float(luminance(hdr).mean().clamp_min(1e-12)))
    if light is not None:
        evs = [0.0] * FRAMES
    else:
        metered = metered_evs(list(hdr), speed=speed)
        evs = [metered[max(i - delay, 0)] for i in range(FRAMES)]
    if curve is None:
        ldr = torch.stack([torch.round(tonemap(h, ev) * 255) / 255 for h, ev in zip(hdr, evs)])
    else:
        ldr = torch.stack([curve.encode(expose(h, ev)) for h, ev in zip(hdr, evs)])
    return ldr, evs, poses


def map_change_stops(first: torch.Tensor, last: torch.Tensor) -> float:
    """Root-mean-square over the sphere (solid-angle weighted) of log2 of one map's luminance
    over another's: how much the answer at one point changed, in stops (static light: 0)."""
    from core.envmap import solid_angles
    from core.exposure import luminance

    w = solid_angles(first.shape[0], dtype=first.dtype)
    r = torch.log2(luminance(last).clamp_min(1e-8) / luminance(first).clamp_min(1e-8))
    return float(((r**2 * w).sum() / w.sum()).sqrt())


def evaluate(path: Path, iterations: int, workdir: Path, curve: str = "drawn") -> dict:
    from bench.suite.evaluation import envmap_brightness
    from bench.tracking import _view
    from core.capture.params import CaptureParams
    from core.capture.prepare import load_prepared_capture
    from core.capture.temporal import decide_temporal
    from core.engine.job import run_job
    from core.engine.params import JobParams
    from core.engine.presets import preset
    from core.envmap import resize_envmap, rotate_envmap
    from core.sim.camera_curves import VIDEO, write_video
    from core.sim.panorama_room import load_panorama

    pano = load_panorama(path, 256)
    yaw, pitch = _view(path.name)
    cam = pan_curve(path.name, curve)
    extra_params = cam.job_params(VIDEO)  # {} but for the reference, whose video cannot state its curve
    ldr, evs, poses = ae_clip(pano, yaw, pitch, curve=cam)
    stem = path.stem + ("" if curve == "drawn" else f"-{cam.name}")
    video = write_video(workdir / f"{stem}.mp4", ldr, FPS, cam)
    true = [e - evs[0] for e in evs]
    out = {"file": path.name, "curve": cam.name, "true_frame_ev": [round(e, 3) for e in true],
           "ae_range_stops": round(max(true) - min(true), 3)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loaded = {mode: load_prepared_capture(video, params=CaptureParams(fps=FPS, frame_ev=mode, **extra_params))
                  for mode in (None, "locked", "estimate")}
    est = loaded["estimate"]
    out["decision"] = {"auto" if mode is None else mode: decide_temporal(c).uses_time for mode, c in loaded.items()}
    out["auto_detected"] = bool(loaded[None].metadata.get("exposure_estimate", {}).get("applied"))
    out["tracked"] = not loaded[None].static_camera
    out["frames_tracked"] = est.num_frames
    kept = (est.times.double() * FPS).round().long()  # the source frames tracking kept
    truth = torch.tensor(true)[kept]
    out["estimate_error_stops"] = round(float((est.frame_ev - (truth - truth[0])).abs().max()), 3)
    dim_ldr, _, _ = ae_clip(pano, yaw, pitch, dimming=DIMMING, curve=cam)
    dim_video = write_video(workdir / f"{stem}-dimming.mp4", dim_ldr, FPS, cam)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dim = load_prepared_capture(dim_video, params=CaptureParams(fps=FPS, **extra_params))
        dim_locked = load_prepared_capture(dim_video, params=CaptureParams(fps=FPS, frame_ev="locked", **extra_params))
    out["locked_dimming"] = {"auto_detected": bool(dim.metadata.get("exposure_estimate", {}).get("applied")),
                             "read_as_changing_light": decide_temporal(dim_locked).uses_time}
    gt = rotate_envmap(resize_envmap(pano, GT_HEIGHT), poses[0][:3, :3].T)
    cfg = preset("draft").with_overrides({"distill.iterations": iterations, "distill.work_height": WORK_HEIGHT})
    preds, runs = {}, {}
    for name, extra in (("auto", {}), ("locked", {"frame_ev": "locked"}), ("estimate", {"frame_ev": "estimate"}),
                        ("stated", {"frame_ev": true})):
        t0 = time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = run_job(video, None,
                             JobParams.model_validate({"preset": "draft", "fps": FPS, **extra_params, **extra}),
                             workdir / f"{stem}-{name}", config=cfg)
        art = result.artefact
        t_end = float(art.meta["capture"]["duration_s"])
        first, _ = art.envmap(torch.zeros(3), 0.0, GT_HEIGHT)
        last, _ = art.envmap(torch.zeros(3), t_end, GT_HEIGHT)
        level = envmap_brightness(torch.stack((first, last))).clamp_min(1e-12)
        preds[name] = first
        runs[name] = {"uses_time": art.meta["temporal"]["uses_time"],
                      "drift_stops": round(abs(math.log2(float(level[1] / level[0]))), 3),
                      "map_change_stops": round(map_change_stops(first, last), 3),
                      "cpu_s": round(time.process_time() - t0, 1)}
    score_runs(runs, preds, gt, ldr[0], out, cam)
    return out


def score_runs(runs: dict, preds: dict, gt: torch.Tensor, frame_ldr: torch.Tensor, out: dict, curve) -> None:
    """Each run's map (`preds`) scored on the diffuse sphere against `gt` (rel si-RMSE, into
    `runs`), beside a constant map of the frame's mean colour, linearised with the camera
    `curve` it was encoded with; both land in `out`."""
    from bench.suite.evaluation import score_probe
    from core.conventions import equirect_width

    mean = curve.decode(frame_ldr).reshape(-1, 3).mean(0)
    preds = {**preds, "mean-colour": mean.expand(gt.shape[0], equirect_width(gt.shape[0]), 3).clone()}
    scores = score_probe(preds, gt, 64)
    for name in runs:
        runs[name]["diffuse_si_rmse_rel"] = round(scores[name]["diffuse"]["si_rmse_rel"], 4)
    out["runs"] = runs
    out["mean_colour_diffuse_si_rmse_rel"] = round(scores["mean-colour"]["diffuse"]["si_rmse_rel"], 4)


def summarise(rows: list[dict]) -> dict:
    """Counts over every panorama; the means over the pans tracking followed (a pan it did not
    follow is taken for a static camera, and then nothing about exposure is meaningful), with
    the others listed."""
    n = len(rows)
    failed = [r["file"] for r in rows if not r.get("tracked")]
    out = {"tracking_failed": failed}
    rows = [r for r in rows if r.get("tracked")]
    runs = ("auto", "locked", "estimate", "stated")
    errs = [r["estimate_error_stops"] for r in rows if "estimate_error_stops" in r]
    mean = lambda xs: round(sum(xs) / len(xs), 4) if xs else None  # noqa: E731
    return {
        "panoramas": n,
        **out,
        "panoramas_tracked": len(rows),
        "ae_range_stops_mean": mean([r["ae_range_stops"] for r in rows]),
        "auto_exposure_detected": sum(r["auto_detected"] for r in rows),
        "locked_dimming": {"auto_detected": sum(r["locked_dimming"]["auto_detected"] for r in rows),
                           "read_as_changing_light": sum(r["locked_dimming"]["read_as_changing_light"] for r in rows)},
        "read_as_changing_light": {k: sum(r["decision"][k] for r in rows) for k in ("auto", "locked", "estimate")},
        "estimate_error_stops": {"panoramas": len(errs), "mean": mean(errs), "max": max(errs) if errs else None},
        "drift_stops_mean": {k: mean([r["runs"][k]["drift_stops"] for r in rows]) for k in runs},
        "map_change_stops_mean": {k: mean([r["runs"][k]["map_change_stops"] for r in rows]) for k in runs},
        "diffuse_si_rmse_rel_mean": {**{k: mean([r["runs"][k]["diffuse_si_rmse_rel"] for r in rows]) for k in runs},
                                     "mean-colour": mean([r["mean_colour_diffuse_si_rmse_rel"] for r in rows])},
    }


def main(argv: list[str] | None = None) -> int:
    from bench.real_panoramas import add_split_arguments

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_split_arguments(p, iterations=200)
    p.add_argument("--rescore", default=None, metavar="REPORT_JSON",
                   help="recompute a saved report's summary from its per-panorama rows (no estimation) and exit")
    args = p.parse_args(argv)
    from bench.real_panoramas import curve_summaries

    if args.rescore:
        report = json.loads(Path(args.rescore).read_text())
        rows = report["panoramas"]
        report.update(curve_summaries(rows, summarise))
        Path(args.rescore).write_text(json.dumps(report, indent=1))
        print(json.dumps(report["summary"], indent=1))
        return 0

    from bench.panoramas import split_files
    from bench.real_panoramas import rows_over
    from core.sim.camera_curves import VIDEO, run_choices

    rows = rows_over(split_files(args.hdri_dir, args.split, args.limit),
                     lambda f, work, curve: evaluate(f, args.iterations, work, curve), args.workdir,
                     run_choices(args.curve, VIDEO))
    report = {"split": args.split, "frames": FRAMES, "pan_deg": PAN_DEG, "size": list(SIZE),
              "iterations": args.iterations, "curve": args.curve, **curve_summaries(rows, summarise),
              "panoramas": rows}
    from bench.report import show_and_write

    show_and_write(report["summary"], report, args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
