"""A static camera's clipped sources over time, against the simulator's HDR truth.

    python -m bench.clip_tracks [--suite temporal] [-o bench/results/clip_tracks_temporal.json]

For each source the clip rule follows over the frames (core.capture.highlights.source_tracks)
it prints, per frame, the blob's estimate in stops over its linearised value (white = 0) made
frame by frame by the rule alone (`blob_boost`) and along the track (`stops_over_time`, what
the reprojection prior uses for a static camera), next to the truth: log2 of the blob's mean
true luminance (the capture's HDR frames, at its exposure) over its mean linearised luminance,
as bench/calibration/clip_rule.py defines it. Summaries: mean absolute error in stops, and the change from
the first frame to the last (log2), estimated vs true. A component benchmark of the clip rule
on the simulator's own scenes, not of what a user gets (bench.accuracy_probe measures that).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np


def track_report(suite_name: str, curve: str | None = None) -> dict:
    import torch

    from bench.run import default_cache_dir
    from bench.suite.simulated import load_suite
    from core.capture.highlights import (
        blob_boost,
        clipped_mask,
        find_blobs,
        pixel_solid_angle,
        source_tracks,
        stops_over_time,
    )
    from core.capture.prepare import load_prepared_capture
    from core.conventions import expose, inverse_tonemap
    from core.exposure import LUMINANCE_WEIGHTS
    from core.io.exr import read_exr

    suite = load_suite(suite_name, default_cache_dir(), None, 64, curve)
    cap = load_prepared_capture(suite.capture_dir)
    if not cap.static_camera:
        raise SystemExit(f"suite {suite_name!r} has a moving camera: the rule follows sources only for a static one")
    doc = json.loads((suite.capture_dir / "capture.json").read_text())
    ev = float(doc.get("exposure_ev") or 0.0)
    ldr = cap.frames.clamp(0, 1)
    lin = inverse_tonemap(ldr)
    clipped = clipped_mask(ldr).numpy()
    weights = np.asarray(LUMINANCE_WEIGHTS)
    truth_y = [expose(torch.from_numpy(read_exr(suite.capture_dir / p)[..., :3].copy()).float(), ev).numpy() @ weights
               for p in doc["hdr_frames"]]
    found = [find_blobs(lin[t].numpy(), clipped[t], pixel_solid_angle(cap.intrinsics)) for t in range(cap.num_frames)]
    over_time = stops_over_time(found, lin)
    tracks = []
    for track in source_tracks([lab for lab, _ in found], [len(b) for _, b in found]):
        if len(track) < 2:
            continue
        rows = []
        for t, k in track:
            own = found[t][0] == k + 1
            y_lin = float((lin[t].numpy()[own] @ weights).mean())
            rows.append({"frame": t, "area_px": found[t][1][k].area_px,
                         "true_stops": math.log2(max(float(truth_y[t][own].mean()) / max(y_lin, 1e-9), 1e-9)),
                         "rule_stops": math.log2(blob_boost(found[t][1][k])), "over_time_stops": over_time[t][k]})
        tracks.append({"frames": len(rows), "per_frame": rows, **{
            name: {"mean_abs_error_stops": float(np.mean([abs(r[f"{name}_stops"] - r["true_stops"]) for r in rows])),
                   "first_to_last_stops": rows[-1][f"{name}_stops"] - rows[0][f"{name}_stops"]}
            for name in ("rule", "over_time")},
            "true_first_to_last_stops": rows[-1]["true_stops"] - rows[0]["true_stops"]})
    return {"suite": suite_name, "curve": suite.describe()["camera_curve"], "frames": cap.num_frames, "exposure_ev": ev,
            "tracks": tracks}


def main(argv: list[str] | None = None) -> int:
    from core.sim.camera_curves import add_curve_argument

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suite", default="temporal", help="a simulator suite with a static camera")
    p.add_argument("-o", "--out", default=None)
    add_curve_argument(p, allow_all=False)  # the suite's camera curve: drawn by its name, or forced
    args = p.parse_args(argv)
    report = track_report(args.suite, args.curve)
    for i, tr in enumerate(report["tracks"]):
        print(
            f"track {i}: {tr['frames']} frames; first -> last: true {tr['true_first_to_last_stops']:+.2f} stops, "
            f"rule {tr['rule']['first_to_last_stops']:+.2f}, over time {tr['over_time']['first_to_last_stops']:+.2f}; "
            f"mean |error| rule {tr['rule']['mean_abs_error_stops']:.2f}, over time "
            f"{tr['over_time']['mean_abs_error_stops']:.2f} stops"
        )
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
