"""Structure from motion's starts on walks: what each initial pair gives, and what the rule keeps.

    python -m bench.sfm_starts --split dev [--limit N] [--variants walk-noisy,walk-dim] \
        [--starts 4,8,16] [--curve drawn|NAME|all] [-o bench/results/handheld/dev_sfm_starts.json]

COLMAP's incremental mapper grows its model from one pair of frames, and on a phone's noisy
walk the pair it starts from decides whether the model drifts (core.tracking.sfm). Per
panorama of MANIFEST.tsv (`--split`; tune on dev, report test once) and per walk of
bench.handheld (WALKS, the same clips and camera curves: `--curve`), COLMAP runs once per start (`--starts`: the initial
pair's minimum triangulation angle, degrees) on the analysis frames, as structure from motion
alone (not track_camera: no rotation track, no fallback). Reported per start: frames
registered, the largest rotation error against the true poses (degrees, world = the first
kept frame) and the pooled median reprojection error (core.tracking.sfm.pooled_median_error,
over all the starts' tracks); then the start `choose_model` keeps. Per variant: the largest
rotation error of the first start alone, of the kept model and of the best start for the clip
(an oracle: it needs the true poses). A clip counts where some start registers half its frames.
"""
from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

from bench.handheld import FRAMES, WALKS, clips


def evaluate(path: Path, variants: dict, starts: tuple[float, ...], curve: str = "drawn") -> dict:
    import core.tracking.sfm as sfm
    from bench.handheld import clip_curve
    from core.tracking.features import analysis_frames
    from core.tracking.geometry import relative_to_first, rotation_angle_deg

    out = {"file": path.name, "curve": clip_curve(path.name, curve).name, "clips": {}}
    for name, ldr, intr, true in clips(path, variants, curve):
        images, k = analysis_frames(ldr, intr)
        models = []
        for angle in starts:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                model = sfm.run_sfm(images, k, starts=(angle,))
            if model is not None and len(model.kept) >= FRAMES // 2:
                models.append(model)
        clip = {}
        if models:
            pool = [t for m in models for t in sfm.feature_tracks(m)]
            for m in models:
                truth = relative_to_first(true[m.kept])[0]
                clip[str(m.stats["init_min_tri_angle_deg"])] = {
                    "frames": len(m.kept),
                    "max_rotation_error_deg": round(max(rotation_angle_deg(e[:3, :3].T @ t[:3, :3])
                                                        for e, t in zip(m.poses, truth)), 3),
                    "pooled_median_px": round(sfm.pooled_median_error(m, pool, k), 4)}
            clip["kept"] = sfm.choose_model(models, k).stats["init_min_tri_angle_deg"]
        out["clips"][name] = clip
    return out


def summarise(rows: list[dict], variants: dict, starts: tuple[float, ...]) -> dict:
    out = {}
    for name in variants:
        first, kept, best = [], [], []
        for r in rows:
            c = r["clips"][name]
            if "kept" not in c:
                continue
            most = max(v["frames"] for a, v in c.items() if a != "kept")
            err = {a: v["max_rotation_error_deg"] for a, v in c.items() if a != "kept" and v["frames"] == most}
            first.append(err.get(str(starts[0])))
            kept.append(err[str(c["kept"])])
            best.append(min(err.values()))
        known = [e for e in first if e is not None]

        def stats(errs):
            s = sorted(errs)
            return {"worst": s[-1], "median": s[len(s) // 2], "over_5_deg": sum(e > 5 for e in s)} if s else None
        out[name] = {"clips": len(kept), "first_start_alone": stats(known),
                     "first_start_short_of_the_most_frames": len(first) - len(known),
                     "kept": stats(kept), "best_start_oracle": stats(best)}
    return out


def main(argv: list[str] | None = None) -> int:
    from bench.panoramas import split_files
    from bench.real_panoramas import add_split_arguments, curve_summaries
    from core.sim.camera_curves import VIDEO, run_choices
    from core.tracking.config import tracking_config

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_split_arguments(p)  # its --workdir is not used: nothing here is written but the report
    p.add_argument("--variants", default="walk-noisy,walk-dim", help="comma-separated names of bench.handheld's WALKS")
    p.add_argument("--starts", default=None, help="comma-separated initial-pair angles (default: the product's)")
    args = p.parse_args(argv)

    unknown = set(args.variants.split(",")) - set(WALKS)
    if unknown:
        p.error(f"unknown variants {sorted(unknown)}; known: {', '.join(WALKS)}")
    variants = {k: v for k, v in WALKS.items() if k in args.variants.split(",")}
    product_starts = tracking_config().sfm.init_min_tri_angles_deg
    starts = tuple(float(a) for a in args.starts.split(",")) if args.starts else product_starts
    rows = []
    for f in split_files(args.hdri_dir, args.split, args.limit):
        for curve in run_choices(args.curve, VIDEO):  # bench.handheld's clips and their camera curves
            rows.append(evaluate(f, variants, starts, curve))
            print(json.dumps(rows[-1]), flush=True)
    report = {
        "split": args.split,
        "starts": list(starts),
        "curve": args.curve,
        **curve_summaries(rows, lambda rs: summarise(rs, variants, starts)),
        "panoramas": rows,
    }
    from bench.report import show_and_write

    show_and_write(report["summary"], report, args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
