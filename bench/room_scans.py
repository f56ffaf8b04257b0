"""Room scans of real panoramas, end to end: what a user gets from a phone turned around a room.

    python -m bench.room_scans [--rooms a,b] [--modes product,true-poses] [--set distill.emitters=0]
        [--curve drawn|NAME|all] [-o out.json]

Per indoor panorama of MANIFEST.tsv (dev, test and extra together; `control` rooms are not
indoor and are reported apart): a room scan as core.sim.room_scan makes it (46 frames at 10 fps,
192x144, rings at pitch +10, +55 and -40 with tilts between, hand jitter, a lagging
auto-exposure spanning 4-9 stops; seeded by the file name), encoded by the phone's camera curve
(core.sim.camera_curves, `--curve`: by default drawn per room from srgb, rec709, filmic and
hlg10; 8 or 10 bits), H.264 declaring the curve's transfer, uploaded as a plain MP4: no poses,
no exposures, no intrinsics. Each room's `curve` is in its row; `summary_per_curve` and the
table's per-curve rows score each curve apart (`--curve all`: every room once per curve, and
the reference gamma2.4, the curve the product used to assume, labelled so). Then `run_job`
(the draft preset, as `lightfield estimate scan.mp4` runs it) and the env map at the first
camera (the origin) at t = 0 and at the last frame's time.

Modes: `product` (THE PRODUCT: the video alone); `product+estimate` (the video and
`"frame_ev": "estimate"`: the user says the exposure moved, as the README advises); `true-poses` (a diagnostic shortcut,
labelled:
the scan's true rotations given as params.poses, exposures still unknown); `true-poses+ev` (the
true exposures given too: what tracking and exposure recovery could reach at best).

Scores, against the panorama rotated into the first camera's frame (world = first camera):
three-sphere metrics (bench.suite.evaluation.score_probe) as ratios to the constant map of the
clip's mean colour linearised with its camera curve (`mean-colour`, as in bench.real_panoramas);
`seen_corr`, the log-luminance correlation of the map re-projected into every frame (true
rotations) with the frame linearised by its camera curve, over the frames (does what was seen
reappear where it was seen); `drift`, the relative L1 between the maps at the first and the
last time (static light: 0); the job's CPU
seconds; and for tracking, the method, frames kept and the largest rotation error.
No setting of the product is fitted here; what the product itself fitted on panoramas (the
indoor fill's elevation profile and source cap, the clip rule's coefficients and spill colour
thresholds) is refitted without the room scored (the default; `--no-cv` uses the shipped
values): the profile, the coefficients and the thresholds on the other indoor rooms, the cap as
the photo cross-validation
(bench.real_panoramas --cv) chose it in that room's fold.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
import zlib
from pathlib import Path

import torch

from bench.overrides import knobs_of
from bench.panoramas import DEFAULT_HDRI_DIR

GT_HEIGHT = 128
MODES = ("product", "product+estimate", "true-poses", "true-poses+ev")
CONSTANT = "mean-colour"
TARGETS = {"diffuse_si_rmse_rel": 0.5, "diffuse_angular_deg": 0.5, "mirror_si_rmse_rel": 0.7, "seen_corr": 0.8,
           "drift": 0.1, "cpu_s": 60.0}


def room_seed(name: str) -> int:
    return zlib.crc32(name.encode()) % 1000


def scan_curve(filename: str, curve: str = "drawn"):
    """The camera curve of the room's scan (`curve` "drawn": drawn by the capture's name, this
    bench and the file, among every realistic curve of a video; a name forces it)."""
    from core.sim.camera_curves import VIDEO, resolve

    return resolve(curve, f"room_scans:{filename}", VIDEO)


def make_scan(pano_path: Path, workdir: Path, path: str = "scan", curve: str = "drawn"):
    """(video path, ScanClip) of the room's scan (or pan: core.sim.room_scan.scan_angles), seeded
    by its file name, encoded by its camera curve (`scan_curve`) and written declaring it."""
    from core.sim.panorama_room import load_panorama
    from core.sim.room_scan import render_scan, write_scan

    seed = room_seed(pano_path.name)
    cam = scan_curve(pano_path.name, curve)
    clip = render_scan(load_panorama(pano_path, 256), yaw0=float(seed % 360), seed=seed, path=path, curve=cam)
    video = write_scan(workdir / f"{pano_path.stem}-{path}-{cam.name}.mp4", clip)
    return video, clip


def relative_poses(clip, first: int = 0) -> list[torch.Tensor]:
    """The scan's c2w poses with camera `first` (the first the track kept) as the world
    (core.conventions)."""
    inv0 = torch.linalg.inv(clip.poses[first])
    return [inv0 @ p for p in clip.poses]


def ground_truth(pano_path: Path, clip, first: int = 0) -> torch.Tensor:
    from core.sim.panorama_room import load_panorama
    from core.sim.room_scan import scan_truth

    return scan_truth(load_panorama(pano_path, 256), clip, GT_HEIGHT, first)


def constant_map(clip) -> torch.Tensor:
    from core.sim.room_scan import scan_constant_map

    return scan_constant_map(clip, GT_HEIGHT)


def run_mode(video: Path, clip, mode: str, workdir: Path, overrides: dict | None):
    """(artefact, cpu seconds) of the job in `mode`."""
    from core.engine import run_job
    from core.engine.params import JobParams
    from core.engine.presets import preset
    from core.sim.camera_curves import VIDEO

    # {} but for the reference camera, whose video cannot state its curve
    params: dict = {"preset": "draft", **(clip.curve.job_params(VIDEO) if clip.curve is not None else {})}
    if mode == "product+estimate":  # the user says the camera's exposure moved (docs/captures.md, "Exposure")
        params["frame_ev"] = "estimate"
    elif mode != "product":
        params["poses"] = [p.reshape(-1).tolist() for p in relative_poses(clip)]
        params["intrinsics"] = {"hfov_deg": clip.intrinsics.hfov_deg}
    if mode == "true-poses+ev":
        params["frame_ev"] = [float(e) for e in clip.evs]
    config = preset("draft").with_overrides(overrides) if overrides else None
    t0 = time.process_time()
    with warnings.catch_warnings(), knobs_of(config):
        warnings.simplefilter("ignore")
        result = run_job(video, None, JobParams.model_validate(params), workdir / f"{video.stem}-{mode}", config=config)
    return result.artefact, time.process_time() - t0


def seen_correlation(env: torch.Tensor, clip, first: int = 0) -> float:
    """Mean over the frames of the map re-projected into the frame (true rotation relative to the
    first camera) against the frame linearised with its camera curve
    (core.metrics.observed_region_correlation)."""
    from core.camera import Camera
    from core.metrics import observed_region_correlation

    vals = []
    for c2w, ldr, linear in zip(relative_poses(clip, first), clip.ldr, clip.linear()):
        rays = Camera(clip.intrinsics, c2w).pixel_rays(dtype=torch.float64)[1]
        unclipped = ldr.amax(-1) < 0.99
        if int(unclipped.sum()) < 16:
            continue
        vals.append(observed_region_correlation(env, linear, rays, unclipped))
    return sum(vals) / len(vals) if vals else 0.0


def relative_l1(a: torch.Tensor, b: torch.Tensor) -> float:
    """|a - b| / |a| over the sphere (solid-angle weighted), each map's scale as it is."""
    from core.envmap import solid_angles

    w = solid_angles(a.shape[0], dtype=torch.float64)[..., None]
    a, b = a.double(), b.double()
    return float(((a - b).abs() * w).sum() / (a.abs() * w).sum().clamp_min(1e-30))


def first_kept(artefact) -> int:
    """The scan frame the job's world is the camera of (the first frame tracking kept)."""
    cap = artefact.meta.get("capture", {})
    meta = cap.get("metadata", cap)
    tracking = meta.get("tracking", {}) if isinstance(meta, dict) else {}
    return int((tracking.get("frames_kept") or [0])[0])


def tracking_summary(artefact, clip) -> dict:
    """Tracking method, frames kept and the largest rotation error against the truth."""
    from core.tracking.geometry import rotation_angle_deg

    cap = artefact.meta.get("capture", {})
    meta = cap.get("metadata", cap)
    tracking = meta.get("tracking", {}) if isinstance(meta, dict) else {}
    out = {"method": tracking.get("method"), "frames_kept": len(tracking.get("frames_kept", []) or []),
           "frames": len(clip.poses)}
    poses = cap.get("poses")
    kept = tracking.get("frames_kept") or list(range(len(clip.poses)))
    if poses is not None and len(poses) == len(kept):
        true = relative_poses(clip)
        k0 = kept[0]
        base = torch.linalg.inv(true[k0])
        errs = [
            rotation_angle_deg(
                (base @ true[f])[:3, :3].numpy().T @ torch.tensor(p, dtype=torch.float64).reshape(4, 4)[:3, :3].numpy()
            )
            for f, p in zip(kept, poses)
        ]
        out["max_rotation_error_deg"] = round(max(errs), 3)
    return out


def evaluate_room(
    pano_path: Path, modes, workdir: Path, sphere_size: int, overrides_for=None, path: str = "scan",
    curve: str = "drawn",
) -> dict:
    from bench.suite.evaluation import score_probe
    from bench.suite.grade import job_grade

    video, clip = make_scan(pano_path, workdir, path, curve)
    gt = ground_truth(pano_path, clip)
    preds = {CONSTANT: constant_map(clip)}
    extra: dict = {}
    extra_scores: dict = {}
    for mode in modes:
        overrides = overrides_for(pano_path.name) if overrides_for else None
        art, cpu = run_mode(video, clip, mode, workdir, overrides)
        t_last = float(art.meta["time"]["t1"])
        first, _ = art.envmap(torch.zeros(3), 0.0, GT_HEIGHT)
        last, _ = art.envmap(torch.zeros(3), t_last, GT_HEIGHT)
        preds[mode] = first
        start = first_kept(art)
        if start:  # the track dropped the scan's first frames: its world is the first kept camera's
            extra_scores[mode] = score_probe({mode: first, CONSTANT: preds[CONSTANT]},
                                             ground_truth(pano_path, clip, start), sphere_size)
        extra[mode] = {"cpu_s": round(cpu, 2), "seen_corr": round(seen_correlation(first, clip, start), 4),
                       "drift": round(relative_l1(first, last), 4), "uses_time": bool(art.meta["time"]["uses_time"]),
                       "tracking": tracking_summary(art, clip), "grade": job_grade(art.meta),
                       "exposure": art.meta.get("capture", {}).get("metadata", {}).get("exposure_source")}
    scores = score_probe(preds, gt, sphere_size)
    for mode, own in extra_scores.items():  # scored at the first kept camera, against the constant map there
        scores[mode], scores[f"{CONSTANT}@{mode}"] = own[mode], own[CONSTANT]
    return {"file": pano_path.name, "curve": clip.curve.name, "span_stops": round(clip.span_stops, 2),
            "scores": scores, "modes": extra, "truth_seen_corr": round(seen_correlation(gt, clip), 4)}


def summarise(rows: list[dict], modes) -> dict:
    """Per mode: mean ratios to the constant map with a 90 % bootstrap interval over rooms, worst
    room, mean seen correlation / drift / CPU, and which targets hold."""
    from bench.suite.evaluation import ratio_interval

    out: dict = {"rooms": len(rows)}
    for mode in modes:
        m: dict = {}
        for material, metric in (("diffuse", "si_rmse_rel"), ("diffuse", "angular_deg"), ("mirror", "si_rmse_rel"),
                                 ("matte", "si_rmse_rel")):
            pairs = [(r["scores"][mode][material][metric],
                      r["scores"].get(f"{CONSTANT}@{mode}", r["scores"][CONSTANT])[material][metric]) for r in rows
                     if "non_finite" not in r["scores"].get(mode, {"non_finite": 1})]
            if not pairs:
                continue
            num, den = zip(*pairs)
            key = f"{material}_{metric}"
            m[key] = {"ratio": round(sum(num) / sum(den), 4),
                      "interval_95": ratio_interval(list(num), list(den), level=0.95),
                      "worst_room_ratio": round(max(a / b for a, b in pairs if b > 0), 3)}
        for key in ("seen_corr", "drift", "cpu_s"):
            vals = [r["modes"][mode][key] for r in rows if mode in r["modes"]]
            m[key] = round(sum(vals) / len(vals), 4) if vals else None
            m[key + "_worst"] = (min(vals) if key == "seen_corr" else max(vals)) if vals else None
        m["tracked_as_rotation"] = sum(r["modes"][mode]["tracking"].get("method") == "rotation" for r in rows
                                       if mode in r["modes"])
        errors = [r["modes"][mode]["tracking"].get("max_rotation_error_deg") for r in rows if mode in r["modes"]]
        m["tracked_within_2deg"] = sum(e is not None and e <= 2.0 for e in errors)
        m["uses_time"] = sum(bool(r["modes"][mode].get("uses_time")) for r in rows if mode in r["modes"])
        out[mode] = m
    return out


DEFAULT_REFIT = Path(__file__).resolve().parent / "results" / "cv" / "product" / "light-colour-2026-12-06.json"


def cv_overrides(hdri: Path, refit_json: Path):
    """room -> the draft's overrides for scoring that room: the elevation profile and the clip
    rule's coefficients and spill colour refitted on every other indoor room (bench.real_panoramas.cv_fits) and
    the fill settings the photo CV chose without it (its `refit` section); control rooms get the
    shipped fits (on indoor rooms only) and the all-rooms choices."""
    from bench.panoramas import indoor_rooms
    from bench.real_panoramas import cv_fits
    from core.priors.reprojection import ReprojectionSettings

    folds, _ = cv_fits(indoor_rooms(hdri))
    refit = json.loads(refit_json.read_text()).get("refit", {}) if refit_json.exists() else {}
    refit = {k: v for k, v in refit.items() if k in ReprojectionSettings.model_fields}  # settings that still exist

    def overrides_for(name: str) -> dict:
        ov = dict(folds.get(name, {}))
        for key, sel in refit.items():
            ov[f"priors.reprojection.{key}"] = sel["chosen"].get(name, sel["all_rooms"])
        return ov

    return overrides_for


def markdown(report: dict) -> list[str]:
    """The report's summary as a table (one row per mode; over the realistic camera curves, then
    per curve, the reference labelled), then one row per room and curve."""
    from core.sim.camera_curves import NAMES, REFERENCE, curve_label

    head = ("| capture | mode | rooms | diffuse si-RMSE vs const [95 %] | diffuse angle vs const [95 %] | "
            "mirror si-RMSE vs const [95 %] | seen corr. (truth) | drift | CPU s | tracked as rotation (≤ 2°) | "
            "read as changing light |")
    lines = [head, "|" + "---|" * 11]
    every = [r for r in report["rooms"] if r.get("split") != "control"]
    # the summary rows: the realistic cameras (the reference alone when only it was run), then each curve apart
    groups = [("", [r for r in every if r.get("curve") != REFERENCE] or every)]
    curves = [c for c in NAMES if any(r.get("curve") == c for r in every)]
    if len(curves) > 1 or report.get("curve", "drawn") == "drawn":
        groups += [(f", curve {curve_label(c)}", [r for r in every if r.get("curve") == c]) for c in curves]
    for suffix, rows in groups:
        truth = sum(r["truth_seen_corr"] for r in rows) / max(len(rows), 1)
        for mode in report["modes"]:
            m = summarise(rows, (mode,))[mode]

            def cell(key):
                v = m.get(key)
                return f"{v['ratio']:.2f} [{v['interval_95'][0]:.2f}, {v['interval_95'][1]:.2f}]" if v else "–"

            tracked = (
                f"{m['tracked_as_rotation']} ({m['tracked_within_2deg']})" if mode.startswith("product")
                else "poses given"
            )
            lines.append(
                f"| {report.get('path', 'scan')}{suffix} | {mode} | {len(rows)} | {cell('diffuse_si_rmse_rel')} | "
                f"{cell('diffuse_angular_deg')} | {cell('mirror_si_rmse_rel')} | {m['seen_corr']:.2f} ({truth:.2f}) | "
                f"{m['drift']:.3f} | {m['cpu_s']:.0f} | {tracked} | "
                f"{m['uses_time']} |"
            )
    rows = every
    machine = report.get("machine")
    if machine:  # CPU seconds are the host's as much as the code's
        lines += ["", f"CPU seconds on {machine.get('cpu_model')}, {machine.get('cores')} cores, at "
                      f"{str(machine.get('git_commit', ''))[:7]} ({machine.get('date_utc', '')[:10]})."]
    lines += ["", "| room | split | camera curve | mode | diffuse si-RMSE / angle / mirror vs const | job's grade | "
              "seen corr. | drift | CPU s | largest rotation error (°) | exposure span (stops) |", "|" + "---|" * 11]
    for r in rows:
        for mode, ex in r["modes"].items():
            sc, c = r["scores"][mode], r["scores"].get(f"{CONSTANT}@{mode}", r["scores"][CONSTANT])
            ratio = [
                sc[a]["si_rmse" if b == "s" else "angular_deg"]
                / max(c[a]["si_rmse" if b == "s" else "angular_deg"], 1e-12)
                for a, b in (("diffuse", "s"), ("diffuse", "a"), ("mirror", "s"))
            ]
            lines.append(
                f"| {r['file']} | {r.get('split')} | {r.get('curve', '–')} | {mode} | "
                f"{ratio[0]:.2f} / {ratio[1]:.2f} / {ratio[2]:.2f} | {ex.get('grade', '–')} | "
                f"{ex['seen_corr']:.2f} | {ex['drift']:.3f} | {ex['cpu_s']:.0f} | "
                f"{ex['tracking'].get('max_rotation_error_deg', '–')} | {r['span_stops']} |"
            )
    return lines


def main(argv=None) -> int:
    from bench.overrides import parse_set
    from bench.panoramas import read_manifest
    from bench.real_panoramas import curve_summaries
    from bench.report import sanitize
    from bench.suite.measure import machine_info
    from core.sim.camera_curves import VIDEO, add_curve_argument, run_choices

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hdri-dir", default=str(DEFAULT_HDRI_DIR))
    p.add_argument("--rooms", default=None, help="comma-separated file names (default: every indoor room)")
    p.add_argument("--splits", default="dev,test,extra", help="MANIFEST splits to score (control: reported apart)")
    p.add_argument("--modes", default="product", help=f"comma-separated subset of {','.join(MODES)}")
    p.add_argument("--sphere-size", type=int, default=64)
    p.add_argument("--workdir", default=None)
    p.add_argument("-o", "--out", default=None, help="JSON report (rewritten after every room)")
    p.add_argument("--path", default="scan", choices=("scan", "pan"), help="scan: the three-ring room scan; pan: a "
                   "20-frame half-turn at the horizon (with --modes true-poses: the posed pan of issue 44)")
    p.add_argument(
        "--no-cv", action="store_true", help="the shipped fill settings for every room (not cross-validated)"
    )
    p.add_argument(
        "--refit",
        default=str(DEFAULT_REFIT),
        help="the per-fold choices of the photo CV "
        "(bench.real_panoramas --cv: its `refit` section, e.g. fill_source_cap) to apply to each held-out room",
    )
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="draft preset override for every room's job (JSON value), e.g. distill.emitters=0 (ablations)")
    add_curve_argument(p)
    p.add_argument("--rescore", default=None, metavar="REPORT_JSON",
                   help="re-summarise a saved report (its rooms as they are) and write its table beside it (.md)")
    args = p.parse_args(argv)
    if args.rescore:
        report = json.loads(Path(args.rescore).read_text())
        indoor = [r for r in report["rooms"] if r.get("split") != "control"]
        report.update(curve_summaries(indoor, lambda rs: summarise(rs, report["modes"])))
        Path(args.rescore).write_text(json.dumps(report, indent=1))
        table = "\n".join(markdown(report)) + "\n"
        Path(args.rescore).with_suffix(".md").write_text(table)
        print(table)
        return 0
    torch.set_num_threads(1)
    hdri = Path(args.hdri_dir)
    rows = read_manifest(hdri)
    names = (
        args.rooms.split(",") if args.rooms else [r["filename"] for r in rows if r["split"] in args.splits.split(",")]
    )
    modes = tuple(args.modes.split(","))
    overrides_for = None if args.no_cv else cv_overrides(hdri, Path(args.refit))
    if args.set:
        extra = parse_set(args.set)
        fold = overrides_for
        overrides_for = lambda name: {**(fold(name) if fold else {}), **extra}  # noqa: E731
    out: dict = {"protocol": __doc__, "modes": modes, "path": args.path, "curve": args.curve, "rooms": {},
                 "targets": TARGETS,
                 "cross_validated": not args.no_cv, "machine": machine_info(),  # CPU seconds depend on the host
                 "command": "python -m bench.room_scans " + " ".join(argv if argv is not None else sys.argv[1:])}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.workdir or tmp)
        work.mkdir(parents=True, exist_ok=True)
        results = []
        for name in names:
            for curve in run_choices(args.curve, VIDEO):
                t0 = time.perf_counter()
                row = evaluate_room(hdri / name, modes, work, args.sphere_size, overrides_for, args.path, curve)
                row["split"] = next((r["split"] for r in rows if r["filename"] == name), None)
                results.append(row)
                print(json.dumps(sanitize(row)), flush=True)
                if args.out:
                    Path(args.out).write_text(json.dumps(sanitize({**out, "rooms": results, "partial": True}),
                                                         indent=1))
                print(f"{name} ({row['curve']}): {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    indoor = [r for r in results if r["split"] != "control"]
    out.update(curve_summaries(indoor, lambda rs: summarise(rs, modes)))
    control = [r for r in results if r["split"] == "control"]
    if control:
        out["summary_control"] = summarise(control, modes)
    out["rooms"] = results
    if args.out:
        Path(args.out).write_text(json.dumps(sanitize(out), indent=1))
    print(json.dumps(sanitize(out["summary"]), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
