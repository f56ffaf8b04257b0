"""Real photographs of light, end to end: indoor HDR panorama -> LDR photo -> `estimate` -> env map.

Protocol (DiffusionLight-style single-image evaluation, run as a user runs the product):
1. Panorama: the linear HDR file listed in MANIFEST.tsv (`dev` and `test` reported
   separately; `control` (not indoor) reported apart and never mixed into the indoor numbers).
2. Camera: at the panorama's centre, horizontal FOV CROP_HFOV_DEG, CROP_SIZE pixels, yaw
   uniform in [-180, 180) and pitch uniform in [-PITCH_DEG, PITCH_DEG], drawn from a
   generator seeded by SEED and the file name (fixed across runs and machines).
3. Photo: the panorama sampled bilinearly along every pixel ray, exposed with DiffusionLight's
   TonemapHDR rule (core.exposure.display_tonemap: x^(1/2.4) scaled so its 99th percentile maps
   to 0.9, clipped; core.sim.camera_curves.display_exposure: that rule as a linear exposure)
   and encoded by a camera curve (core.sim.camera_curves: `--curve`, by default drawn per photo
   from srgb, rec709 and filmic by its name), 8 bits, written as a PNG declaring what that
   camera's stills declare (the filmic tone curve is not stated; rec709 states nothing).
4. Ground truth: the panorama rotated into that camera's frame (world = camera frame, as for
   any single image the engine receives), compared at GT_HEIGHT rows.
5. Methods, all at the camera centre x = (0, 0, 0):
   - `field`: THE PRODUCT. core.engine.run_job on the PNG with {"intrinsics": {"hfov_deg":
     CROP_HFOV_DEG}}, no depth, preset PRESET (what `lightfield estimate photo.png --params ..
     --preset draft` runs), then the artefact's exact env map query (`lightfield envmap OUT
     --x 0,0,0`).
   - `prior (shortcut)`: the job's reprojection prior, with the preset's settings, bound to
     the same decoded capture and queried directly: a shortcut, labelled so, showing what
     distillation keeps or loses.
   - `mean-colour`: the trivial baseline, a constant map of the photo's mean colour, linearised
     with the photo's own camera curve (its exact inverse: the baseline is not biased by it).
Scores: the three-sphere metrics of bench.suite.evaluation (scale-invariant or percentile-
normalised, so the photo's unknown exposure does not matter), reported per split as ratios
to the mean-colour map (mean relative si-RMSE / mean angular error of the method over the
mean-colour's); and the observed-region correlation (core.metrics.observed_region_correlation):
the map re-projected into the capturing camera vs the photo linearised with its camera curve. The ground truth's
own correlation is reported as the protocol's ceiling (8-bit quantisation and clipping keep
it below 1).
"""
from __future__ import annotations

import json
import random
import sys
import tempfile
import time
from pathlib import Path

import torch

from bench.panoramas import (
    CROP_HFOV_DEG,
    CROP_SIZE,
    DEFAULT_HDRI_DIR,
    INDOOR_SPLITS,
    camera_rotation,
    indoor_rooms,
    load_panorama,
    perspective_crop,
    read_manifest,
)

SEED = 7
PITCH_DEG = 15.0
GT_HEIGHT = 128  # = core.metrics.EVAL_HEIGHT: maps are queried and compared at the metric's own resolution
PRESET = "draft"
SPLITS = ("dev", "test", "control")
FIELD, PRIOR, CONSTANT = "field", "prior (shortcut)", "mean-colour"
METHODS = (FIELD, PRIOR, CONSTANT)

PROTOCOL = (
    f"Photo: {CROP_SIZE[0]}x{CROP_SIZE[1]} px, {CROP_HFOV_DEG:g}° horizontal FOV, yaw U[-180°, 180°), pitch "
    f"U[-{PITCH_DEG:g}°, {PITCH_DEG:g}°] "
    f"(seed {SEED} + file name), DiffusionLight TonemapHDR's exposure (99th percentile of x^(1/2.4) -> 0.9), a camera "
    "curve per photo (core.sim.camera_curves; `curve` of each image), 8-bit PNG declaring what that camera's stills "
    "declare. "
    f"Ground truth: the panorama rotated into the camera frame, {GT_HEIGHT}x{2 * GT_HEIGHT}. All at the camera centre: "
    f"`field` = the product (`estimate` on the PNG with its FOV, no depth, preset {PRESET}; then the exact env map "
    "query at x=0,0,0); "
    "`prior (shortcut)` = the job's reprojection prior queried directly (not the product); `mean-colour` = constant "
    "map of the "
    "photo's mean colour linearised with its camera curve. Ratios: method's mean / mean-colour's mean over the split "
    "(< 1 beats a constant map). "
    "Observed corr. = log-luminance correlation of the map re-projected into the camera with the photo linearised by "
    "its camera curve "
    "(`truth` row: the ground-truth panorama's own, the protocol's ceiling). `control` panoramas are not indoor and "
    "are reported apart."
)


def add_split_arguments(p, iterations: int | None = None, curve: bool = True) -> None:
    """A per-panorama bench's common options: --split, --hdri-dir, --limit, --workdir, -o,
    --iterations (the draft's steps per job) where its jobs take a default, and (`curve`) the
    camera curve of its captures (--curve: core.sim.camera_curves.add_curve_argument)."""
    p.add_argument("--split", default="dev", choices=("dev", "test"))
    p.add_argument("--hdri-dir", default=str(Path(__file__).resolve().parents[2] / "shared" / "hdri"))
    p.add_argument("--limit", type=int, default=None)
    if iterations is not None:
        p.add_argument("--iterations", type=int, default=iterations)
    p.add_argument("--workdir", default=None)
    p.add_argument("-o", "--output", default=None)
    if curve:
        from core.sim.camera_curves import add_curve_argument

        add_curve_argument(p)


def rows_over(files: list[Path], evaluate, workdir=None, curves: tuple[str, ...] | None = None) -> list[dict]:
    """evaluate(file, workdir) per panorama (with `curves`, a camera-curve choice per run:
    evaluate(file, workdir, curve) per panorama and curve), each row printed as it comes (a
    run's log can rebuild its report), in `workdir` or a temporary directory."""
    import json
    import tempfile

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(workdir or tmp)
        for f in files:
            for curve in curves or (None,):
                rows.append(evaluate(f, work) if curve is None else evaluate(f, work, curve))
                print(json.dumps(rows[-1]), flush=True)
    return rows


def curve_summaries(rows: list[dict], summarise) -> dict:
    """A per-capture bench's summaries over its rows (each with the `curve` it was encoded with):
    `summary` over the realistic curves (over every row when only the reference was run),
    `summary_per_curve` per curve (core.sim.camera_curves.group_by_curve, the reference labelled)."""
    from core.sim.camera_curves import REFERENCE, group_by_curve

    realistic = [r for r in rows if r.get("curve") != REFERENCE]
    return {"summary": summarise(realistic or rows), "summary_per_curve": group_by_curve(rows, summarise)}


def view_for(filename: str, view: int = 0, views: int = 1) -> tuple[float, float]:
    """(yaw, pitch) in degrees of photo `view` of `views` taken from one panorama. View 0 is the
    file's own draw (the protocol's single photo); view k turns the yaw by k 360 / views from it
    (the photos look around the room evenly) with a pitch of its own draw."""
    rng = random.Random(f"{SEED}:{filename}")
    yaw, pitch = rng.uniform(-180.0, 180.0), rng.uniform(-PITCH_DEG, PITCH_DEG)
    if view == 0:
        return yaw, pitch
    yaw = (yaw + 360.0 * view / views + 180.0) % 360.0 - 180.0
    return yaw, random.Random(f"{SEED}:{filename}:{view}").uniform(-PITCH_DEG, PITCH_DEG)


def photo_name(filename: str, view: int = 0) -> str:
    """The name a photo's camera curve is drawn by: the file's, and the view's after the first."""
    return filename if view == 0 else f"{filename}#view{view}"


def photo_curve(filename: str, view: int = 0, choice: str = "drawn"):
    """The photo's camera curve (core.sim.camera_curves.resolve: `choice` "drawn" draws it by
    `photo_name` from the still curves, a name forces it)."""
    from core.sim.camera_curves import STILL, resolve

    return resolve(choice, photo_name(filename, view), STILL)


def ldr_photo(hdr: torch.Tensor, curve) -> torch.Tensor:
    """The photo's 8-bit codes: the protocol's exposure (TonemapHDR's rule as a linear factor),
    encoded by the camera `curve`."""
    from core.sim.camera_curves import display_exposure

    return curve.encode(hdr * display_exposure(hdr, 99.0, 0.9))


def job_params(curve=None):
    """The job's parameters: the photo's FOV (and what the reference camera's file cannot state)."""
    from core.engine.params import JobParams
    from core.sim.camera_curves import STILL

    extra = curve.job_params(STILL) if curve is not None else {}
    return JobParams.model_validate({"preset": PRESET, "intrinsics": {"hfov_deg": CROP_HFOV_DEG}, **extra})


def engine_config(overrides: dict | None):
    """The preset (None: run_job's own default), or a labelled variant of it for exploration."""
    if not overrides:
        return None
    from core.engine.presets import preset

    return preset(PRESET).with_overrides(overrides)


def estimate_field(photo_path: Path, workdir: Path, overrides: dict | None = None, curve=None,
                   graded: dict | None = None) -> torch.Tensor:
    """The product: run_job (as `lightfield estimate`) then the exact env map at the camera; the job's
    quality grade into `graded['grade']` (bench.suite.grade) when given."""
    import warnings

    from bench.suite.grade import job_grade
    from core.engine import run_job
    from core.fields.stored.artefact import LightFieldArtefact

    out = workdir / (photo_path.stem + ".lightfield")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # e.g. "no depth: assuming a box room" (expected here)
        run_job(photo_path, None, job_params(curve), out, config=engine_config(overrides))
    art = LightFieldArtefact.load(out)  # what `lightfield envmap OUT --x 0,0,0` loads
    if graded is not None:
        graded["grade"] = job_grade(art.meta)
    env, _ = art.envmap(torch.zeros(3), None, GT_HEIGHT)
    return env


def estimate_prior(photo_path: Path, overrides: dict | None = None, curve=None) -> torch.Tensor:
    """Shortcut: the job's prior (preset settings) on the same capture at the job's working
    resolution (as run_job binds it), queried directly."""
    from core.capture.load import load_capture
    from core.engine.presets import preset
    from core.priors.registry import build_prior

    params = job_params(curve)
    config = engine_config(overrides) or preset(PRESET)
    capture = load_capture(photo_path, None, params).resized(config.distill.work_height)
    prior = build_prior(params.prior, config.prior_settings(params.prior))
    prior.bind(capture)
    return prior.envmaps(torch.zeros(1, 3), 0.0, GT_HEIGHT)[0]


def estimate_mean_colour(ldr: torch.Tensor, curve) -> torch.Tensor:
    """A constant map of the photo's mean colour, linearised with the photo's own camera curve."""
    from core.conventions import equirect_width

    mean = curve.decode(ldr).reshape(-1, 3).mean(0)
    return mean.expand(GT_HEIGHT, equirect_width(GT_HEIGHT), 3).clone()


def write_photo(ldr: torch.Tensor, path: Path, curve) -> Path:
    """The photo as the camera's PNG, declaring what its stills declare."""
    from core.sim.camera_curves import write_png

    return write_png(path, ldr, curve)


def protocol_photos(hdri_dir: Path, split: str, views: int, work_height: int, curve: str = "drawn"):
    """The protocol's photos of a split, for benches that query the prior alone: per panorama
    (sorted by name) and view (view_for), a dict with the file `name`, the `pano`, the camera's
    `rotation` and `intrinsics`, the camera `curve` (`photo_curve` of `curve`), the `ldr` photo
    (its codes) and the capture `work` at `work_height` rows, loaded from its PNG as the job
    loads it (in a temporary directory, gone after the loop)."""
    from core.capture.load import load_capture

    files = sorted(
        r["filename"]
        for r in read_manifest(hdri_dir)
        if r.get("split") == split and (hdri_dir / r["filename"]).is_file()
    )
    with tempfile.TemporaryDirectory() as tmp:
        for f in files:
            pano = load_panorama(hdri_dir / f)
            for view in range(views):
                R = camera_rotation(*view_for(f, view, views))
                hdr, intr = perspective_crop(pano, R)
                cam = photo_curve(f, view, curve)
                ldr = ldr_photo(hdr, cam)
                work = load_capture(
                    write_photo(ldr, Path(tmp) / f"{f}_{view}.png", cam), None, job_params(cam)).resized(work_height)
                yield {"name": f, "pano": pano, "rotation": R, "intrinsics": intr, "curve": cam, "ldr": ldr,
                       "work": work}


def evaluate_panorama(path: Path, sphere_size: int, workdir: Path, methods=METHODS, overrides: dict | None = None,
                      view: int = 0, views: int = 1, curve: str = "drawn") -> dict:
    """One photo, scored; `curve`: the camera curve's choice (`photo_curve`), recorded as the
    row's `curve`."""
    from bench.suite.evaluation import score_probe
    from core.camera import Camera
    from core.envmap import resize_envmap, rotate_envmap
    from core.metrics import observed_region_correlation

    pano = load_panorama(path)
    yaw, pitch = view_for(path.name, view, views)
    R = camera_rotation(yaw, pitch)
    hdr, intr = perspective_crop(pano, R)
    cam = photo_curve(path.name, view, curve)
    ldr = ldr_photo(hdr, cam)
    stem = path.stem + (f"_view{view}" if view else "") + ("" if curve == "drawn" else f"_{cam.name}")
    photo = write_photo(ldr, workdir / (stem + ".png"), cam)
    gt = rotate_envmap(resize_envmap(pano, GT_HEIGHT), R.T)  # camera frame: gt(d) = pano(R d)
    graded: dict = {}
    run = {FIELD: lambda: estimate_field(photo, workdir, overrides, cam, graded),
           PRIOR: lambda: estimate_prior(photo, overrides, cam),
           CONSTANT: lambda: estimate_mean_colour(ldr, cam)}
    preds, seconds = {}, {}
    for name in methods:
        t0 = time.perf_counter()
        preds[name] = run[name]()
        seconds[name] = time.perf_counter() - t0
    scores = score_probe(preds, gt, sphere_size)
    # the photo's own camera, in the camera frame the estimates live in (identity pose)
    rays = Camera(intr, torch.eye(4, dtype=torch.float64)).pixel_rays(dtype=torch.float64)[1]
    linear = cam.decode(ldr)
    corr = {name: observed_region_correlation(env, linear, rays) for name, env in {**preds, "truth": gt}.items()}
    return {"file": path.name, "view": view, "curve": cam.name, "yaw_deg": round(yaw, 2), "pitch_deg": round(pitch, 2),
            "clipped_fraction": float((ldr.amax(-1) >= 0.99).float().mean()), "seconds": seconds, "scores": scores,
            "observed_corr": corr, "grade": graded.get("grade", "–")}


def summarise(images: list[dict], methods=METHODS) -> dict:
    """Per method: mean scores, ratios to the mean-colour map with their 90 % bootstrap
    interval over the panoramas (`interval_90`: a split of 7 rooms leaves a ratio uncertain by
    several hundredths), how many photos it scores lower than the mean-colour map on
    (`photos_beating_constant`), mean observed correlation."""
    from bench.suite.evaluation import mean_scores, ratio_interval

    def mean(vals):
        vals = [v for v in vals if v is not None]
        return sum(vals) / len(vals) if vals else None

    out: dict = {}
    for name in methods:
        out[name] = {"images": len(images), "seconds_per_image": mean([im["seconds"][name] for im in images]),
                     "metrics": mean_scores([im["scores"][name] for im in images]),
                     "observed_corr": mean([im["observed_corr"][name] for im in images])}
    base = out.get(CONSTANT)
    for name in methods:
        m, ratios, intervals, wins = out[name]["metrics"], {}, {}, {}
        for mat in ("diffuse", "matte"):
            for metric in ("si_rmse_rel", "angular_deg"):
                num, den = m[mat][metric], base["metrics"][mat][metric] if base else None
                ratios[f"{mat}_{metric}"] = num / den if num is not None and den else None
                if base and name != CONSTANT:
                    pairs = _panorama_pairs(images, name, mat, metric)
                    intervals[f"{mat}_{metric}"] = ratio_interval(*zip(*pairs)) if pairs else None
                    both = [
                        im for im in images if _scored(im, name, mat, metric) and _scored(im, CONSTANT, mat, metric)
                    ]
                    wins[f"{mat}_{metric}"] = [sum(im["scores"][name][mat][metric] < im["scores"][CONSTANT][mat][metric]
                                                   for im in both), len(both)]
        out[name]["vs_constant"] = ratios
        if intervals:
            out[name]["interval_90"] = intervals
            out[name]["photos_beating_constant"] = wins  # [photos where the method scores lower, photos scored]
    out["truth"] = {"images": len(images), "observed_corr": mean([im["observed_corr"]["truth"] for im in images])}
    return out


def _panorama_pairs(images: list[dict], method: str, material: str, metric: str) -> list[tuple[float, float]]:
    """Per panorama, the mean of `method`'s and of the constant map's score over its photos: the
    bootstrap resamples panoramas, not photos, since the views of one room are not independent."""
    rooms: dict[str, list[tuple[float, float]]] = {}
    for k, im in enumerate(images):
        if _scored(im, method, material, metric) and _scored(im, CONSTANT, material, metric):
            rooms.setdefault(im.get("file", f"photo {k}"), []).append((im["scores"][method][material][metric],
                                                     im["scores"][CONSTANT][material][metric]))
    return [(sum(a for a, _ in v) / len(v), sum(b for _, b in v) / len(v)) for v in rooms.values()]


def _scored(image: dict, method: str, material: str, metric: str) -> bool:
    score = image["scores"].get(method, {})
    return "non_finite" not in score and score.get(material, {}).get(metric) is not None


def rescore(report: dict) -> dict:
    """Re-summarise a saved report from its per-image results (no estimate is rerun): how a
    report written before a summary statistic existed gets it."""
    for split in report.get("splits", {}).values():
        methods = tuple(k for k in split["methods"] if k != "truth")
        split["methods"] = summarise(split["images"], methods)
        if any("curve" in im for im in split["images"]):
            split["per_curve"] = per_curve(split["images"], lambda ims: summarise(ims, methods))
    return report


COMPARED = (("diffuse", "si_rmse_rel"), ("diffuse", "angular_deg"), ("matte", "si_rmse_rel"), ("matte", "angular_deg"))
SAME_WITHIN = 0.005  # a photo's score moving less than this counts as unchanged


def compare_reports(before: dict, after: dict, method: str = FIELD) -> list[str]:
    """Photo by photo, how `method`'s scores moved between two saved reports of the same
    photos (a change's runs): per split and metric, how many photos got better or worse by
    more than SAME_WITHIN, and the median of after / before. A mean can move on a few photos
    while most move the other way; this says which."""
    import statistics

    lines = ["| split | metric | photos | better | worse | median after / before |", "|---|---|---|---|---|---|"]
    for name, split in after.get("splits", {}).items():
        old = {(i["file"], i.get("view", 0)): i for i in before.get("splits", {}).get(name, {}).get("images", [])}
        pairs = [(old[k], i) for i in split["images"] if (k := (i["file"], i.get("view", 0))) in old]
        if not pairs:
            continue
        for material, metric in COMPARED:
            a = [p["scores"][method][material][metric] for p, _ in pairs]
            b = [q["scores"][method][material][metric] for _, q in pairs]
            better = sum(y < x - SAME_WITHIN for x, y in zip(a, b))
            worse = sum(y > x + SAME_WITHIN for x, y in zip(a, b))
            ratio = statistics.median(y / x for x, y in zip(a, b) if x > 0)
            lines.append(f"| {name} | {material} {metric} | {len(pairs)} | {better} | {worse} | {ratio:.3f} |")
    return lines


def curve_groups(name: str, curve: str) -> list[tuple[str, str]]:
    """(group name, curve choice) of one split or CV group under `--curve curve`: the group
    itself for "drawn" or one curve; with "all", one group per curve, named after it (the
    reference labelled so)."""
    from core.sim.camera_curves import ALL, STILL, curve_label, run_choices

    if curve != ALL:
        return [(name, curve)]
    return [(f"{name} · curve {curve_label(c)}", c) for c in run_choices(ALL, STILL)]


def per_curve(images: list[dict], summarise_fn) -> dict:
    """The group's summary per camera curve its photos were encoded with (reference last)."""
    from core.sim.camera_curves import group_by_curve

    return group_by_curve(images, summarise_fn)


def run_panoramas(hdri_dir: Path, limit: int | None, sphere_size: int, quick: bool = False,
                  workdir: Path | None = None, splits=SPLITS, log=None, overrides: dict | None = None,
                  views: int = 1, curve: str = "drawn") -> dict:
    """Per split: every method's mean scores over the photos (`views` per panorama, see
    `view_for`), ratios with their interval over the panoramas, per camera curve the same
    (`per_curve`), and per-photo results (`skipped` if no data). `curve`: the photos' camera
    curve (core.sim.camera_curves: "drawn" per photo, a name, or "all": each split once per
    curve, as its own group)."""
    hdri_dir = Path(hdri_dir)
    if not (hdri_dir / "MANIFEST.tsv").is_file():
        return {"skipped": f"no MANIFEST.tsv in {hdri_dir} (pass --hdri-dir); the real-panorama section was not run"}
    rows = read_manifest(hdri_dir)
    out: dict = {"protocol": PROTOCOL, "hdri_dir": str(hdri_dir), "limit_per_split": limit, "preset": PRESET,
                 "views_per_panorama": views, "curve": curve, "splits": {}}
    if views > 1:
        out["protocol"] += (
            f" {views} photos per panorama: the first as above, the others at its yaw turned by multiples "
            f"of {360.0 / views:g}° with pitches of their own; intervals resample panoramas."
        )
    if overrides:
        out["protocol"] += f" VARIANT, not the shipped preset: {PRESET} with {json.dumps(overrides)}."
        out["overrides"] = overrides
    own_tmp = workdir is None
    workdir = Path(tempfile.mkdtemp(prefix="lightfield-panoramas-")) if own_tmp else Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    for split in splits:
        files = sorted(r["filename"] for r in rows if r.get("split") == split)
        files = [f for f in files if (hdri_dir / f).is_file()]
        if limit is not None:
            files = files[:limit]
        if not files:
            continue
        for group, choice in curve_groups(split + (" (not indoor)" if split == "control" else ""), curve):
            images = []
            for f in files:
                for view in range(views):
                    t0 = time.perf_counter()
                    images.append(evaluate_panorama(hdri_dir / f, sphere_size, workdir, overrides=overrides,
                                                    view=view, views=views, curve=choice))
                    if log:
                        im = images[-1]
                        log(f"panorama {split}/{f} view {view} curve {im['curve']}: {time.perf_counter() - t0:.0f}s, "
                            "observed corr " + ", ".join(f"{k} {v:.2f}" for k, v in im["observed_corr"].items()))
            out["splits"][group] = {"files": files, "curve": choice, "methods": summarise(images),
                                    "per_curve": per_curve(images, summarise), "images": images}
    if own_tmp:
        import shutil

        shutil.rmtree(workdir, ignore_errors=True)
    return out

# ---------------------------------------------------------------------------------------
# Leave-one-room-out cross-validation (`--cv`)
# ---------------------------------------------------------------------------------------
CV_LEVEL = 0.95  # bootstrap interval over rooms
CV_SEED = 0
ANGLE_FAILURE = 1.5  # a room "fails" where its diffuse angular error is > this x its constant map's
CV_MATERIALS = ("diffuse", "matte", "mirror")
CV_METRICS = ("si_rmse_rel", "angular_deg", "nrmse")
METHOD_ALIASES = {"field": FIELD, "prior": PRIOR, "constant": CONSTANT, "mean-colour": CONSTANT}
GAIN_KEY = "priors.reprojection.elevation_gain"
CLIP_KEY = "priors.reprojection.clip_coefficients"
SPILL_KEY = "priors.reprojection.spill_colour"

# Switches of the accuracy mechanisms (preset overrides), each turned off alone under CV
# (`--variant NAME`; docs/engine.md "Accuracy mechanisms under cross-validation").
CV_VARIANTS: dict[str, dict] = {
    "shipped": {},
    "no elevation gain": {GAIN_KEY: [1.0, 1.0]},  # flat profile: the unseen fill at pull-push's level
    "no source cap": {"priors.reprojection.fill_source_cap": None},
    "no light colour": {"priors.reprojection.light_colour_knee": None},  # the unseen fill in the walls' colour
    "clip rule fixed": {"priors.reprojection.clip_rule": "fixed"},
    "unseen fill push-pull": {"priors.reprojection.unseen_fill": "push-pull"},
    "no emitters": {"distill.emitters": 0},
    "no observed surfaces": {"distill.observed_surfaces": 0},
    "no room lattice": {"field.room_lattice": []},
    "no view fit": {"distill.envmap_view_directions": 0, "field.view_detail_heights": []},
    "no free-space probes": {"distill.envmap_free_probes": 0},
}


# Values chosen from panoramas other than the elevation profile: refitted per fold (`run_cv`,
# refit=True) by the prior shortcut's mean score over the fold's other rooms, among a grid.
# setting -> (grid, material, metric minimised).
# One setting at a time, the others at their defaults.
CV_REFIT: dict[str, tuple[tuple, str, str]] = {
    "fill_source_cap": ((1.0, 2.0, 4.0, 8.0, None), "diffuse", "si_rmse_rel"),
    "light_colour_knee": ((0.25, 0.5, 1.0, 2.0, None), "diffuse", "angular_deg"),
}


def cv_select(rooms: list[Path], folds: dict[str, dict], overrides: dict, sphere_size: int, workdir: Path,
              log=None, curve: str = "drawn") -> dict:
    """Per CV_REFIT setting not fixed by `overrides`: every room's prior-shortcut score (its
    fold's fits, `folds[room]`: `cv_fits`) at every grid value, then per fold the value with the lowest
    mean over the OTHER rooms (`chosen[room]`) and over all rooms (`all_rooms`: what a user
    gets; control rooms use it). The scored room never takes part in its own choice. (The
    other rooms are scored with their own folds' profiles, which include the held-out room's
    row means: a second-order leak through the profile, not through the choice's score.)"""
    out: dict = {}
    for key, (grid, material, metric) in CV_REFIT.items():
        full = f"priors.reprojection.{key}"
        if full in overrides:
            continue
        scores = {}  # room -> [score per grid value]
        for path in rooms:
            ov = {**folds[path.name], **overrides}
            scores[path.name] = [
                evaluate_panorama(path, sphere_size, workdir, methods=(PRIOR,), overrides={**ov, full: v},
                                  curve=curve)["scores"][
                    PRIOR
                ][material][metric]
                for v in grid
            ]
            if log:
                log(f"refit {key} {path.name}: " + ", ".join(f"{v}: {x:.3f}" for v, x in zip(grid, scores[path.name])))

        def best(names):
            totals = [sum(scores[n][i] for n in names) for i in range(len(grid))]
            return grid[min(range(len(grid)), key=totals.__getitem__)]

        names = list(scores)
        out[key] = {"grid": list(grid), "criterion": f"prior (shortcut) {material} {metric}", "scores": scores,
                    "chosen": {n: best([m for m in names if m != n]) for n in names}, "all_rooms": best(names)}
    return out


def cv_gains(rooms: list[Path]) -> tuple[dict[str, list[float]], list[float]]:
    """The elevation profile of each fold (bench.calibration.indoor_fill's fit on every room but that one)
    and the one fitted on all of them (what a user gets: core.priors.indoor_fill.ELEVATION_GAIN)."""
    from bench.calibration.indoor_fill import gain_from_profiles, panorama_profiles

    profiles = panorama_profiles(rooms)
    folds = {p.name: gain_from_profiles(torch.cat([profiles[:i], profiles[i + 1:]])) for i, p in enumerate(rooms)}
    return folds, gain_from_profiles(profiles)


def cv_fits(rooms: list[Path]) -> tuple[dict[str, dict], dict]:
    """What the product fits on panoramas, as overrides: per room the fits on every other room
    (room name -> overrides for scoring it) and the fits on all of them (what a user gets; for
    rooms outside the folds): the unseen fill's elevation profile (`cv_gains`) and the clip
    rule's coefficients and its spill colour's settings (bench.calibration.clip_rule.cv_coefficients,
    cv_spill_colour)."""
    from bench.calibration.clip_rule import blob_samples, cv_coefficients, cv_spill_colour

    gains, all_gain = cv_gains(rooms)
    samples = {p.name: blob_samples(p) for p in rooms}
    clips, all_clip = cv_coefficients(rooms, samples)
    spills, all_spill = cv_spill_colour(samples)
    return ({p.name: {GAIN_KEY: gains[p.name], CLIP_KEY: clips[p.name], SPILL_KEY: spills[p.name]} for p in rooms},
            {GAIN_KEY: all_gain, CLIP_KEY: all_clip, SPILL_KEY: all_spill})


def cv_summary(images: list[dict], methods) -> dict:
    """Per method (one photo per room): mean scores; for every material and metric the ratio of
    the mean to the constant map's with its CV_LEVEL bootstrap interval over rooms (seed
    CV_SEED) and the rooms it beats the constant map on; the rooms whose diffuse angular error
    is > ANGLE_FAILURE x the constant map's; mean observed correlation."""
    import statistics

    from bench.suite.evaluation import mean_scores, ratio_interval

    out: dict = {}
    for name in methods:
        scored = [im for im in images if "non_finite" not in im["scores"][name]]
        m = {"images": len(images), "non_finite": len(images) - len(scored),
             "seconds_per_image": sum(im["seconds"][name] for im in images) / max(1, len(images)),
             "metrics": mean_scores([im["scores"][name] for im in images]),
             "observed_corr": sum(im["observed_corr"][name] for im in images) / max(1, len(images))}
        if name != CONSTANT and CONSTANT in methods:
            ratios, intervals, wins, medians, floors = {}, {}, {}, {}, {}
            for mat in CV_MATERIALS:
                for metric in CV_METRICS:
                    pairs = [(im["scores"][name][mat][metric], im["scores"][CONSTANT][mat][metric]) for im in scored
                             if _scored(im, name, mat, metric) and _scored(im, CONSTANT, mat, metric)]
                    if not pairs:
                        continue
                    key = f"{mat}_{metric}"
                    a, b = zip(*pairs)
                    ratios[key] = round(sum(a) / max(sum(b), 1e-30), 4)
                    intervals[key] = ratio_interval(list(a), list(b), seed=CV_SEED, level=CV_LEVEL)
                    wins[key] = [sum(x < y for x, y in pairs), len(pairs)]
                    medians[key] = round(statistics.median(x / y for x, y in pairs if y > 0), 4)
                    floors[key] = round(sum(min(x, y) for x, y in pairs) / max(sum(b), 1e-30), 4)
            m["vs_constant"] = ratios
            m[f"interval_{round(CV_LEVEL * 100)}"] = intervals
            m["rooms_beating_constant"] = wins
            m["median_room_ratio"] = medians  # the typical room, not swayed by the rooms with the largest errors
            # an oracle, not a method: each room scored by the better of this method and the
            # constant map, i.e. the most that a rule keeping the map "never worse than the
            # constant" could bring, had it known room by room which is better
            m["oracle_floor_at_constant"] = floors
            fails = [im["file"] for im in scored if im["scores"][name]["diffuse"]["angular_deg"]
                     > ANGLE_FAILURE * im["scores"][CONSTANT]["diffuse"]["angular_deg"]]
            m["rooms_diffuse_angle_over_1.5x_constant"] = {"count": len(fails), "of": len(scored), "rooms": fails}
        out[name] = m
    out["truth"] = {"observed_corr": sum(im["observed_corr"]["truth"] for im in images) / max(1, len(images))}
    return out


def run_cv(hdri_dir: Path, sphere_size: int = 64, methods=METHODS, overrides: dict | None = None, control: bool = True,
           limit: int | None = None, log=None, workdir: Path | None = None, refit: bool = True,
           curve: str = "drawn") -> dict:
    """Leave-one-room-out: every indoor room (INDOOR_SPLITS together) scored with everything
    fitted from panoramas refitted without it. Today that is the elevation profile of the
    unseen fill (bench.calibration.indoor_fill, row means of the other rooms' panoramas), passed to the job
    as the reprojection prior's `elevation_gain`, the clip rule's coefficients
    (bench.calibration.clip_rule.cv_coefficients, `clip_coefficients`), and (`refit`) the CV_REFIT settings chosen
    per fold by `cv_select`; an override that sets one itself (an ablation) wins. Nothing else
    the job runs is chosen on these panoramas (the draft's field settings were chosen on the
    simulator). `control` rooms (not indoor) get the profile and choices fitted on all indoor
    rooms and are summarised apart."""
    from bench.suite.measure import machine_info
    from core.sim.camera_curves import ALL, STILL, curve_label, run_choices

    hdri_dir = Path(hdri_dir)
    if not (hdri_dir / "MANIFEST.tsv").is_file():
        return {"skipped": f"no MANIFEST.tsv in {hdri_dir} (pass --hdri-dir)"}
    if curve == ALL:  # the whole CV once per curve (its refit too); each curve's groups named after it
        runs = {c: run_cv(hdri_dir, sphere_size, methods, overrides, control, limit, log, workdir, refit, c)
                for c in run_choices(ALL, STILL)}
        out = {**next(iter(runs.values())), "curve": ALL, "splits": {}, "refit": {}}
        for c, res in runs.items():
            out["splits"].update({f"{g} · curve {curve_label(c)}": v for g, v in res["splits"].items()})
            out["refit"][curve_label(c)] = res["refit"]
        return out
    overrides = dict(overrides or {})
    methods = tuple(methods)
    rooms = indoor_rooms(hdri_dir, limit)
    folds, all_rooms = cv_fits(rooms)
    protocol = PROTOCOL + (
        f" Leave-one-room-out over the {len(rooms)} indoor rooms ({', '.join(INDOOR_SPLITS)} together, one photo "
        "each): "
        "each room's job gets the unseen fill's elevation profile (bench.calibration.indoor_fill) and the clip rule's "
        "coefficients (bench.calibration.clip_rule) refitted on the other rooms"
        + (
            f" and {', '.join(CV_REFIT)} chosen per fold on the other rooms (the prior shortcut, `refit` in the JSON); "
            if refit
            else "; "
        )
        + f"intervals: {round(CV_LEVEL * 100)} % bootstrap over rooms (seed {CV_SEED}, {2000} draws) of the ratio of "
          "means. "
        f"Rooms failing: diffuse angular error > {ANGLE_FAILURE:g}x the constant map's."
    )
    if overrides:
        protocol += f" VARIANT, not the shipped preset: {PRESET} with {json.dumps(overrides)}."
    out: dict = {"protocol": protocol, "hdri_dir": str(hdri_dir), "preset": PRESET, "methods": list(methods),
                 "overrides": overrides, "curve": curve, "all_rooms_elevation_gain": all_rooms[GAIN_KEY],
                 "all_rooms_clip_coefficients": all_rooms[CLIP_KEY], "splits": {},
                 "machine": machine_info()}  # seconds per photo depend on the host
    own_tmp = workdir is None
    workdir = Path(tempfile.mkdtemp(prefix="lightfield-cv-")) if own_tmp else Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    split_of = {r["filename"]: r["split"] for r in read_manifest(hdri_dir)}
    selected = cv_select(rooms, folds, overrides, sphere_size, workdir, log, curve) if refit else {}
    out["refit"] = selected

    def fold_overrides(name: str | None) -> dict:
        ov = {**(folds[name] if name is not None else all_rooms), **overrides}
        for key, sel in selected.items():
            ov = {**ov, f"priors.reprojection.{key}": sel["all_rooms"] if name is None else sel["chosen"][name]}
        return ov

    groups = {"indoor (leave-one-room-out)": rooms}
    if control:
        ctrl = sorted(r["filename"] for r in read_manifest(hdri_dir)
                      if r.get("split") == "control" and (hdri_dir / r["filename"]).is_file())
        groups["control (not indoor)"] = [hdri_dir / f for f in ctrl]
    for group, items in groups.items():
        images = []
        for path in items:
            t0 = time.perf_counter()
            ov = fold_overrides(path.name if path.name in folds else None)
            im = evaluate_panorama(path, sphere_size, workdir, methods=methods, overrides=ov, curve=curve)
            im["split"] = split_of.get(path.name)
            im["fold_overrides"] = {k: v for k, v in ov.items() if k not in overrides}
            images.append(im)
            if log:
                log(f"{group} {path.name}: {time.perf_counter() - t0:.0f}s " + ", ".join(
                    f"{k} diffuse si {v['diffuse']['si_rmse_rel']:.3f} ang {v['diffuse']['angular_deg']:.1f}"
                    for k, v in im["scores"].items() if "non_finite" not in v))
        out["splits"][group] = {"files": [p.name for p in items], "curve": curve,
                                "methods": cv_summary(images, methods),
                                "per_curve": per_curve(images, lambda ims: cv_summary(ims, methods)),
                                "images": images}
    if own_tmp:
        import shutil

        shutil.rmtree(workdir, ignore_errors=True)
    return out


def resummarised(report: dict, splits: list[str] | None = None) -> dict:
    """A saved CV report with its summaries re-made from its per-room results (this code's
    statistics), keeping only the rooms of the MANIFEST `splits` when given."""
    for g in report.get("splits", {}).values():
        if splits:
            g["images"] = [im for im in g["images"] if im.get("split") in splits]
        g["methods"] = cv_summary(g["images"], tuple(report["methods"]))
        if any("curve" in im for im in g["images"]):
            g["per_curve"] = per_curve(g["images"], lambda ims: cv_summary(ims, tuple(report["methods"])))
    return report


def cv_markdown(res: dict, rows: bool = True) -> list[str]:
    """A CV report as markdown: per group and method the ratios to the constant map with their
    intervals, the rooms failing on angle, then (rows) each room's ratios."""
    def cell(m, key):
        r, iv = m.get("vs_constant", {}).get(key), m.get(f"interval_{round(CV_LEVEL * 100)}", {}).get(key)
        return "–" if r is None else f"{r:.3f} [{iv[0]:.2f}, {iv[1]:.2f}]"

    keys = [f"{mat}_{metric}" for mat in CV_MATERIALS for metric in ("si_rmse_rel", "angular_deg")] + ["matte_nrmse"]
    out = [res.get("protocol", ""), ""]
    head = (
        ["group", "method", "rooms", "s / photo"]
        + [k.replace("_rel", "").replace("_", " ") + " vs const" for k in keys]
        + ["median room ratio diffuse si / ang", f"rooms diffuse ang > {ANGLE_FAILURE:g}x const", "observed corr."]
    )
    out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for group, g in res.get("splits", {}).items():
        for name, m in g["methods"].items():
            if name == "truth":
                continue
            fails = m.get("rooms_diffuse_angle_over_1.5x_constant")
            out.append(
                "| "
                + " | ".join(
                    [group, name, str(m["images"]), f"{m['seconds_per_image']:.1f}"]
                    + [cell(m, k) for k in keys]
                    + [_medians(m)]
                    + ["–" if not fails else f"{fails['count']} / {fails['of']}", f"{m['observed_corr']:.3f}"]
                )
                + " |"
            )
    out += curve_table(res, lambda m, k: cell(m, k), ("diffuse_si_rmse_rel", "diffuse_angular_deg"))
    for group, g in res.get("splits", {}).items():
        for name, m in g["methods"].items():
            floor = m.get("oracle_floor_at_constant", {})
            if "diffuse_angular_deg" in floor:
                out += ["", f"Oracle bound, {group}, {name}: scored room by room by the better of it and the constant "
                        "map (per metric; not a method: the most a 'never worse than the constant' rule could "
                        "bring): diffuse "
                        f"si-RMSE {floor['diffuse_si_rmse_rel']:.3f}, "
                        f"diffuse angle {floor['diffuse_angular_deg']:.3f}."]
    if rows:
        for group, g in res.get("splits", {}).items():
            methods = [k for k in g["methods"] if k not in ("truth", CONSTANT)]
            out += ["", f"Per room, {group} (ratio to the room's constant map: diffuse si-RMSE / diffuse angle):", "",
                    "| room | split | " + " | ".join(methods) + " | job's grade | constant diffuse ang (°) |",
                    "|---|---|" + "---|" * (len(methods) + 2)]
            for im in g["images"]:
                c = im["scores"][CONSTANT]["diffuse"]
                cells = []
                for name in methods:
                    s = im["scores"][name]
                    cells.append(
                        "non-finite"
                        if "non_finite" in s
                        else f"{s['diffuse']['si_rmse_rel'] / c['si_rmse_rel']:.2f} / "
                             f"{s['diffuse']['angular_deg'] / c['angular_deg']:.2f}"
                    )
                out.append(
                    f"| {im['file']} | {im.get('split')} | " + " | ".join(cells)
                    + f" | {im.get('grade', '–')} | {c['angular_deg']:.1f} |"
                )
    return out


def curve_table(res: dict, cell, keys) -> list[str]:
    """Per group and camera curve (the groups' `per_curve`), each method's `cell(m, key)` for
    `keys`: how the score moves with the camera's curve (the reference row labelled so)."""
    rows = [(group, label, name, m) for group, g in res.get("splits", {}).items()
            for label, ms in g.get("per_curve", {}).items() for name, m in ms.items()
            if name not in ("truth", CONSTANT) and "vs_constant" in m]
    if not rows:
        return []
    head = ["group", "camera curve", "method", "photos"] + [k.replace("_rel", "").replace("_", " ") + " vs const"
                                                            for k in keys]
    out = ["", "Per camera curve (core.sim.camera_curves; each photo's curve is its row's `curve`):", "",
           "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for group, label, name, m in rows:
        out.append("| " + " | ".join([group, label, name, str(m.get("images"))] + [cell(m, k) for k in keys]) + " |")
    return out


def _medians(m: dict) -> str:
    med = m.get("median_room_ratio")
    return "–" if not med else f"{med['diffuse_si_rmse_rel']:.3f} / {med['diffuse_angular_deg']:.3f}"


def cv_ablation_table(reports: dict[str, dict], method: str, base_name: str = "shipped") -> list[str]:
    """reports: variant name -> CV report (indoor group). One row per variant: its `method`'s
    ratios to the constant map, the change from the `base_name` row, and the rooms failing on angle."""
    keys = (
        "diffuse_si_rmse_rel",
        "diffuse_angular_deg",
        "matte_si_rmse_rel",
        "matte_angular_deg",
        "mirror_angular_deg",
    )
    group = "indoor (leave-one-room-out)"
    base = reports.get(base_name, {}).get("splits", {}).get(group, {}).get("methods", {}).get(method)
    head = (
        ["variant (one mechanism off)", "overrides"]
        + [k.replace("_rel", "").replace("_", " ") + " vs const [95 %]" for k in keys]
        + [
            "Δ diffuse si / Δ diffuse ang vs shipped",
            "median room ratio diffuse si / ang",
            f"rooms diffuse ang > {ANGLE_FAILURE:g}x",
        ]
    )
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, rep in reports.items():
        m = rep.get("splits", {}).get(group, {}).get("methods", {}).get(method)
        if not m:
            continue
        iv = m.get(f"interval_{round(CV_LEVEL * 100)}", {})
        cells = [f"{m['vs_constant'][k]:.3f} [{iv[k][0]:.2f}, {iv[k][1]:.2f}]" for k in keys]
        delta = "–" if base is None or name == base_name else " / ".join(
            f"{m['vs_constant'][k] - base['vs_constant'][k]:+.3f}" for k in keys[:2])
        fails = m["rooms_diffuse_angle_over_1.5x_constant"]
        out.append("| " + " | ".join([name, f"`{json.dumps(rep.get('overrides', {}))}`", *cells, delta, _medians(m),
                                      f"{fails['count']} / {fails['of']}"]) + " |")
    return out


def main(argv=None) -> int:
    """`python -m bench.real_panoramas --splits dev --limit 3 -o dev.json`: this section alone."""
    import argparse

    from bench.report import panorama_markdown, sanitize
    from core.sim.camera_curves import add_curve_argument

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hdri-dir", default=str(DEFAULT_HDRI_DIR))
    p.add_argument("--splits", default="dev", help="comma-separated subset of dev,test,control (tune on dev only)")
    p.add_argument(
        "--limit",
        type=int,
        default=None,
        help="panoramas per split (default 3; 0: all); with --cv: the first indoor rooms (default all)",
    )
    p.add_argument("--sphere-size", type=int, default=64)
    p.add_argument(
        "--views", type=int, default=1, help="photos per panorama (view_for): more photos, tighter intervals"
    )
    p.add_argument("-o", "--out", default=None, help="JSON file to write")
    p.add_argument("--overrides", default=None, help='explore a variant of the preset (labelled in the output), e.g. '
                   '\'{"priors.reprojection.env_height": 64}\'')
    p.add_argument("--rescore", default=None, metavar="REPORT_JSON", help="re-summarise a saved report from its "
                   "per-image results (nothing is estimated again); with -o, write the result")
    p.add_argument("--compare", nargs=2, default=None, metavar=("BEFORE_JSON", "AFTER_JSON"),
                   help="photo by photo, how the field's scores moved between two saved reports; nothing is estimated")
    p.add_argument("--cv", action="store_true", help="leave-one-room-out over every indoor room (dev, test, extra "
                   "together; control apart): anything fitted from panoramas is refitted without the scored room")
    p.add_argument("--methods", default="field,prior,constant", help="with --cv: of field, prior (shortcut), constant")
    p.add_argument("--variant", default=None, choices=tuple(CV_VARIANTS),
                   help="with --cv: one accuracy mechanism switched off (CV_VARIANTS; adds to --overrides)")
    p.add_argument("--no-control", action="store_true", help="with --cv: skip the control (not indoor) rooms")
    p.add_argument("--no-refit", action="store_true", help="with --cv: keep the CV_REFIT settings at their defaults "
                   "instead of choosing them per fold (only the elevation profile is refitted)")
    p.add_argument("--cv-table", nargs="+", default=None, metavar="CV_JSON",
                   help="the ablation table of saved --cv reports (nothing is estimated); with --table-method")
    p.add_argument("--table-method", default="field", help="with --cv-table: field or prior")
    p.add_argument(
        "--table-splits",
        default=None,
        help="with --cv-table: only the rooms of these MANIFEST splits, e.g. "
        "test,extra (the rooms no value was ever chosen on before the CV)",
    )
    p.add_argument("--md", default=None, help="with --cv / --cv-table / --cv-report: also write the markdown here")
    add_curve_argument(p)
    p.add_argument("--cv-report", default=None, metavar="CV_JSON", help="a saved --cv report as markdown, its "
                   "summaries re-made from the per-room results (nothing is estimated)")
    args = p.parse_args(argv)
    if args.cv_report:
        lines = cv_markdown(resummarised(json.loads(Path(args.cv_report).read_text())))
        if args.md:
            Path(args.md).write_text("\n".join(lines) + "\n")
        print("\n".join(lines))
        return 0
    if args.cv_table:
        reports = {}
        for f in args.cv_table:
            rep = resummarised(json.loads(Path(f).read_text()),
                               args.table_splits.split(",") if args.table_splits else None)
            name = rep.get("variant") or Path(f).stem
            if rep.get("refit"):
                name += f" ({', '.join(rep['refit'])} chosen per fold)"
            reports[name] = rep
        lines = cv_ablation_table(reports, METHOD_ALIASES.get(args.table_method, args.table_method))
        if args.md:
            Path(args.md).write_text("\n".join(lines) + "\n")
        print("\n".join(lines))
        return 0
    if args.cv:
        torch.set_num_threads(1)
        overrides = {
            **(json.loads(args.overrides) if args.overrides else {}),
            **CV_VARIANTS.get(args.variant or "shipped", {}),
        }
        methods = tuple(dict.fromkeys(METHOD_ALIASES[m.strip()] for m in args.methods.split(",")) )
        if CONSTANT not in methods:
            methods += (CONSTANT,)
        res = run_cv(
            Path(args.hdri_dir),
            args.sphere_size,
            methods,
            overrides,
            control=not args.no_control,
            refit=not args.no_refit,
            limit=args.limit or None,
            log=lambda m: print(m, file=sys.stderr, flush=True),
            curve=args.curve,
        )
        res["variant"] = args.variant or ("shipped" if not args.overrides else "overrides")
        res["command"] = "python -m bench.real_panoramas " + " ".join(sys.argv[1:] if argv is None else argv)
        if args.out:
            Path(args.out).write_text(json.dumps(sanitize(res), indent=1))
        lines = cv_markdown(res)
        if args.md:
            Path(args.md).write_text("\n".join(lines) + "\n")
        print("\n".join(lines))
        return 0
    if args.compare:
        before, after = (json.loads(Path(f).read_text()) for f in args.compare)
        print("\n".join(compare_reports(before, after)))
        return 0
    if args.rescore:
        res = rescore(json.loads(Path(args.rescore).read_text()))
        if args.out:
            Path(args.out).write_text(json.dumps(sanitize(res), indent=1))
        print("\n".join(panorama_markdown(res)))
        return 0
    torch.set_num_threads(1)
    res = run_panoramas(
        Path(args.hdri_dir),
        3 if args.limit is None else (args.limit or None),
        args.sphere_size,
        splits=tuple(args.splits.split(",")),
        log=lambda m: print(m, file=sys.stderr, flush=True),
        overrides=json.loads(args.overrides) if args.overrides else None,
        views=max(1, args.views),
        curve=args.curve,
    )
    if args.out:
        Path(args.out).write_text(json.dumps(sanitize(res), indent=1))
    print("\n".join(panorama_markdown(res)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
