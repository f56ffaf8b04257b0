"""Camera tracking on handheld-style pans: motion blur, a rolling shutter and sensor noise.

    python -m bench.handheld --split dev [--limit N] [--variants a,b] [--global-shutter] [--curve drawn|NAME|all]
        [-o out.json]

bench/tracking.py renders each frame at one instant (a global shutter, no blur). A phone
pans by hand: each frame integrates the scene over its exposure (motion blur) and its rows
are read out one after another (a rolling shutter: the top row earlier than the bottom). Per
panorama of MANIFEST.tsv (`--split`; tune on dev, report test once), a pan from the view
bench.tracking draws for the file: PAN_DEG of yaw in FRAMES frames at FPS with a pitch
wobble, SIZE at 60 deg FOV, from one spot of the panorama pasted on the assumed box room,
rendered at SUB_SAMPLES instants per frame. Variants (VARIANTS): `sharp` (global shutter),
`blur` (EXPOSURE_S of exposure), `rolling` (READOUT_S from the top row to the bottom),
`handheld` (both, with NOISE_SIGMA Gaussian noise in code units), `dim` (the same, exposed
DIM_EV stops, with DIM_NOISE_SIGMA of noise), and `portrait-rolling` /
`portrait-handheld` (the phone held upright: SIZE turned, the sensor's rows vertical, so the
readout runs along the pan and stretches the frame rather than shearing it). Each is encoded at one
exposure by the phone's camera curve (core.sim.camera_curves, `--curve`: by default drawn per
panorama from srgb, rec709, filmic and hlg10; the noise in its code units, then its bit depth),
decoded as the loader decodes the declared file (`CameraCurve.loaded`), and run through camera
tracking as loading runs it (`core.tracking.track.track_camera`,
no intrinsics given: the assumed 60 deg, refined by the pan as the product does). Reported per
clip: the method, frames kept, the largest rotation error against the true poses (degrees,
the kept frames, world = the first kept frame), the refined horizontal FOV, the rotation
model's evidence and whether it was taken only as the fallback after structure from motion
failed (core.tracking.track.rotation_fallback_ok: without that fallback those clips were a
static camera); per variant the clips tracked within MAX_ROTATION_ERROR_DEG, and how many of
them the fallback took. Walks (WALKS, `--variants walk-noisy,walk-short-noisy,walk-dim`)
count the clips with a translation the tracker took for a pan, and how far off their turn then
was. `--global-shutter` tracks without the rotation model's rolling shutter (an ablation: what
modelling the readout buys).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from pathlib import Path

import torch

FRAMES = 20
FPS = 10.0
PAN_DEG = 90.0  # 45 deg/s: a brisk handheld pan
SIZE = (320, 240)
SUB_SAMPLES = 12  # instants rendered per frame (blur and the rolling shutter are built from them)
EXPOSURE_S = 1.0 / 30.0  # a phone's video exposure indoors is often as long as the frame rate allows
READOUT_S = 1.0 / 30.0  # top row to bottom row: phone sensors read out in ~10-33 ms
NOISE_SIGMA = 0.02
# A dim room: the phone exposes 2 stops under the bench's level (the frames' mean luminance at
# 0.18) and its sensor gain raises the noise. Such frames matched 10-60 features a pair in a
# one-off count on dev clips, where the others match hundreds.
DIM_EV = -2.0
DIM_NOISE_SIGMA = 0.03
MAX_ROTATION_ERROR_DEG = 1.0
VARIANTS = {  # name: (exposure seconds, readout seconds, noise sigma, portrait)
    "sharp": (0.0, 0.0, 0.0, False),
    "blur": (EXPOSURE_S, 0.0, 0.0, False),
    "rolling": (0.0, READOUT_S, 0.0, False),
    "handheld": (EXPOSURE_S, READOUT_S, NOISE_SIGMA, False),
    "portrait-rolling": (0.0, READOUT_S, 0.0, True),
    "portrait-handheld": (EXPOSURE_S, READOUT_S, NOISE_SIGMA, True),
    "dim": (EXPOSURE_S, READOUT_S, DIM_NOISE_SIGMA, False),
}
VARIANT_EV = {"dim": DIM_EV}  # the tone map's exposure where not 0
# Walks, which a rotation explains only in part: how many the tracker takes for a pan anyway
# (`--variants walk-noisy,...`, not run by default): bench.tracking's walk (1.2 m across the
# box room, 0.5 m forward, turning 40 deg), scaled, rendered at the frame instants, with noise. name: (scale, noise
# sigma, exposure ev)
WALKS = {
    "walk-noisy": (1.0, NOISE_SIGMA, 0.0),
    "walk-short-noisy": (0.3, NOISE_SIGMA, 0.0),
    "walk-dim": (1.0, DIM_NOISE_SIGMA, DIM_EV),
}


def pose_at(t: float, yaw0: float, pitch0: float) -> torch.Tensor:
    """The camera at time t seconds: the pan's yaw linear in time, its pitch wobbling (as
    bench.tracking.pan_poses at the frame instants)."""
    from bench.tracking import PITCH_WOBBLE_DEG
    from core.sim.state import pose_from_yaw_pitch

    i = t * FPS
    return pose_from_yaw_pitch(
        (0, 0, 0), yaw0 + PAN_DEG * i / (FRAMES - 1), pitch0 + PITCH_WOBBLE_DEG * math.sin(i / 3)
    )


def render_frame(room, intr, index: int, yaw0: float, pitch0: float, exposure: float, readout: float,
                 portrait: bool = False) -> torch.Tensor:
    """HDR [H, W, 3] of frame `index`: row r integrates [t_r, t_r + exposure], t_r = t_frame +
    readout r / H, from SUB_SAMPLES instants over [t_frame, t_frame + readout + exposure]. A
    `portrait` frame is a landscape sensor turned by 90 deg: its columns are read, left first."""
    from core.camera import Camera

    t0, span = index / FPS, readout + exposure
    if span <= 0:
        return room.render(Camera(intr, pose_at(t0, yaw0, pitch0)), 1)[0]
    times = [t0 + span * (k + 0.5) / SUB_SAMPLES for k in range(SUB_SAMPLES)]
    renders = torch.stack([room.render(Camera(intr, pose_at(t, yaw0, pitch0)), 1)[0] for t in times])  # [K, H, W, 3]
    if portrait:
        renders = renders.transpose(1, 2)  # columns as rows
    h = renders.shape[1]
    out = torch.empty_like(renders[0])
    for r in range(h):
        start = t0 + readout * (r + 0.5) / h
        inside = [k for k, t in enumerate(times) if start <= t <= start + exposure]
        if not inside:  # no exposure: the nearest instant
            inside = [min(range(SUB_SAMPLES), key=lambda k: abs(times[k] - start))]
        out[r] = renders[inside, r].mean(0)
    return out.transpose(0, 1) if portrait else out


def clip_curve(filename: str, curve: str = "drawn"):
    """The camera curve of the panorama's clips (`curve` "drawn": drawn by the capture's name,
    this bench and the file, among every realistic curve of a video; a name forces it)."""
    from core.sim.camera_curves import VIDEO, resolve

    return resolve(curve, f"handheld:{filename}", VIDEO)


def clips(path: Path, variants: dict = VARIANTS, curve: str = "drawn"):
    """Yield (name, frames [T, H, W, 3] as loading hands them to tracking (the camera curve's
    codes, quantised, decoded as the file declares), intrinsics, true c2w poses [T, 4, 4]
    relative to the first frame) per variant of `variants` (VARIANTS or WALKS) for the panorama;
    the camera: `clip_curve(path.name, curve)`."""
    from bench.tracking import HFOV_DEG, _view, walk_poses
    from core.camera import Camera, Intrinsics
    from core.conventions import expose
    from core.exposure import luminance
    from core.sim.camera_curves import VIDEO
    from core.sim.panorama_room import PanoramaRoom, load_panorama
    from core.tracking.geometry import relative_to_first
    from core.tracking.room import assumed_room

    pano = load_panorama(path, 512)
    yaw, pitch = _view(path.name)
    cam = clip_curve(path.name, curve)
    room = PanoramaRoom(pano, assumed_room(), torch.zeros(3))
    pan_truth, _ = relative_to_first(torch.stack([pose_at(i / FPS, yaw, pitch) for i in range(FRAMES)]).numpy())
    for name, spec in variants.items():
        if name in WALKS:
            scale, sigma, ev = spec
            intr = Intrinsics.from_hfov(SIZE[0], SIZE[1], HFOV_DEG)
            poses = walk_poses(FRAMES, scale)
            true, _ = relative_to_first(torch.stack(poses).numpy())
            hdr = torch.stack([room.render(Camera(intr, p), 1)[0] for p in poses])
        else:
            (exposure, readout, sigma, portrait), ev, true = spec, VARIANT_EV.get(name, 0.0), pan_truth
            size = SIZE[::-1] if portrait else SIZE
            intr = Intrinsics.from_hfov(size[0], size[1], HFOV_DEG)
            hdr = torch.stack(
                [render_frame(room, intr, i, yaw, pitch, exposure, readout, portrait) for i in range(FRAMES)]
            )
        hdr = hdr * (0.18 / float(luminance(hdr).mean().clamp_min(1e-12)))
        codes = cam.apply(expose(hdr, ev))
        if sigma > 0:
            codes = (codes + sigma * torch.randn(codes.shape, generator=torch.Generator().manual_seed(7))).clamp(0, 1)
        yield name, cam.loaded(cam.quantise(codes), VIDEO), intr, true


def evaluate(path: Path, variants: dict = VARIANTS, curve: str = "drawn") -> dict:
    from core.tracking.capture_geometry import pose_errors
    from core.tracking.geometry import relative_to_first
    from core.tracking.track import track_camera

    out = {"file": path.name, "curve": clip_curve(path.name, curve).name, "clips": {}}
    for name, ldr, intr, true in clips(path, variants, curve):
        size = (intr.width, intr.height)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = track_camera(ldr, intr, refine_focal=True)
        model = r.stats.get("rotation_model", {})
        clip = {"method": r.method, "frames_kept": len(r.kept), "cpu_s": round(r.cpu_seconds, 2),
                "rotation_fallback": bool(r.stats.get("rotation_fallback")),
                "keypoint_noise_px": r.motion.evidence.get("keypoint_noise_px"),
                **{k: model.get(k) for k in ("median_px", "inlier_share", "parallax_px", "epipolar_px", "fits",
                                             "readout_frames")}}
        if "models" in r.stats:  # structure from motion's starts (core.tracking.sfm.choose_model)
            clip["sfm_start_deg"] = r.stats.get("init_min_tri_angle_deg")
            clip["sfm_models"] = r.stats["models"]
        if r.method not in ("static", "failed:static-fallback") and len(r.kept) > 1:
            # world = the first kept frame
            rot, _ = pose_errors(r.poses, torch.from_numpy(relative_to_first(true[r.kept])[0]))
            clip["max_rotation_error_deg"] = round(rot, 3)
            clip["reprojection_error_px"] = r.reprojection_error_px
            focal = r.summary().get("refined_focal_px")
            if focal:
                clip["refined_hfov_deg"] = round(math.degrees(2 * math.atan(size[0] / 2 / float(focal))), 2)
        out["clips"][name] = clip
    return out


def summarise(rows: list[dict], variants: dict = VARIANTS) -> dict:
    out = {}
    for name in variants:
        clips = [r["clips"][name] for r in rows]
        if name in WALKS:  # how each walk was read, and how far off its turn was
            errs = [c["max_rotation_error_deg"] for c in clips if "max_rotation_error_deg" in c]
            methods = [c["method"] for c in clips]
            out[name] = {"clips": len(clips), "methods": {m: methods.count(m) for m in sorted(set(methods))},
                         "taken_as_a_pan": methods.count("rotation"),
                         "max_rotation_error_deg_median": round(sorted(errs)[len(errs) // 2], 3) if errs else None,
                         "max_rotation_error_deg_worst": max(errs) if errs else None}
            continue
        errs = [c["max_rotation_error_deg"] for c in clips if "max_rotation_error_deg" in c]
        good = [e for e in errs if e <= MAX_ROTATION_ERROR_DEG]
        fallback = [c for c in clips if c.get("rotation_fallback")]
        out[name] = {"clips": len(clips), "tracked": len(errs), "within_1_deg": len(good),
                     "by_the_rotation_fallback": len(fallback),
                     "within_1_deg_by_the_fallback": sum(c.get("max_rotation_error_deg", 99) <= MAX_ROTATION_ERROR_DEG
                                                        for c in fallback),
                     "frames_kept_mean": round(sum(c["frames_kept"] for c in clips) / len(clips), 2),
                     "max_rotation_error_deg_median": round(sorted(errs)[len(errs) // 2], 3) if errs else None}
    return out


def main(argv: list[str] | None = None) -> int:
    from core.sim.camera_curves import VIDEO, add_curve_argument, run_choices

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--split", default="dev", choices=("dev", "test"))
    p.add_argument("--hdri-dir", default=str(Path(__file__).resolve().parents[2] / "shared" / "hdri"))
    p.add_argument("--limit", type=int, default=None)
    p.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated names of VARIANTS")
    p.add_argument("--global-shutter", action="store_true", help="track without the rolling-shutter model")
    p.add_argument("-o", "--output", default=None)
    add_curve_argument(p)
    args = p.parse_args(argv)
    from bench.panoramas import split_files
    from bench.real_panoramas import curve_summaries

    files = split_files(args.hdri_dir, args.split, args.limit)
    known = {**VARIANTS, **WALKS}
    unknown = set(args.variants.split(",")) - set(known)
    if unknown:
        p.error(f"unknown variants {sorted(unknown)}; known: {', '.join(known)}")
    variants = {k: v for k, v in known.items() if k in args.variants.split(",")}
    if args.global_shutter:
        import functools

        import core.tracking.track as track_module

        track_module.estimate_rotations = functools.partial(track_module.estimate_rotations, rolling_shutter=False)
    rows = []
    for f in files:
        for curve in run_choices(args.curve, VIDEO):
            rows.append(evaluate(f, variants, curve))
            print(json.dumps(rows[-1]), flush=True)
    report = {"split": args.split, "frames": FRAMES, "fps": FPS, "pan_deg": PAN_DEG, "size": list(SIZE),
              "exposure_s": EXPOSURE_S, "readout_s": READOUT_S, "noise_sigma": NOISE_SIGMA,
              "dim": {"ev": DIM_EV, "noise_sigma": DIM_NOISE_SIGMA}, "curve": args.curve,
              "rolling_shutter_model": not args.global_shutter,
              **curve_summaries(rows, lambda rs: summarise(rs, variants)), "panoramas": rows}
    from bench.report import show_and_write

    show_and_write(report["summary"], report, args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
