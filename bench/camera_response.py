"""The camera's response, per curve: the same captures encoded with each camera curve
(core.sim.camera_curves) and scored as a user gets them. Writes
bench/results/camera_response/RESULTS.md from the reports of two benches run per curve:

    python -m bench.room_scans --rooms A,B,C,D --modes product --curve all --workdir W -o scans.json
    python -m bench.real_panoramas --splits dev --limit 12 --curve srgb -o photos_dev_srgb.json   # per curve
    python -m bench.camera_response --scans scans.json --photos photos_dev_*.json --workdir W

Per curve: ratios to the constant map (diffuse si-RMSE, diffuse angle, mirror si-RMSE), the
scans' seen correlation, how many scans of static light were read as static, and (from the
jobs' artefacts in the scans' workdir) where the response was estimated and used and what it
cost against the whole job. The gamma2.4 rows are the curve the product used to assume: a
labelled reference, not a camera.
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results" / "camera_response"
REFERENCE = "gamma2.4"


def _ratio(scores: dict, sphere: str, metric: str) -> float:
    return scores["product"][sphere][metric] / max(scores["mean-colour"][sphere][metric], 1e-12)


def _artefact(workdir: Path | None, room: dict) -> dict:
    if workdir is None:
        return {}
    path = workdir / f"{Path(room['file']).stem}-scan-{room['curve']}-product" / "lightfield.json"
    if not path.is_file():
        return {}
    meta = json.loads(path.read_text())
    timings = meta["training"]["stage_timings"]
    total = sum(v["seconds"] for v in timings.values())
    response = meta["capture"]["metadata"].get("response") or {}
    return {"response_used": bool(response.get("used")), "response_s": timings.get("response", {}).get("seconds", 0.0),
            "job_stage_s": total, "transfer": (meta["capture"]["metadata"].get("transfer") or {}).get("curve"),
            "grade": (meta.get("quality") or {}).get("grade")}


def scan_rows(report: dict, workdir: Path | None) -> list[dict]:
    rows = []
    for room in report["rooms"]:
        product = room["modes"]["product"]
        rows.append({"room": Path(room["file"]).stem, "curve": room["curve"],
                     "si": _ratio(room["scores"], "diffuse", "si_rmse"),
                     "angle": _ratio(room["scores"], "diffuse", "angular_deg"),
                     "mirror": _ratio(room["scores"], "mirror", "si_rmse"),
                     "seen_corr": product.get("seen_corr"), "static": not product.get("uses_time"),
                     "drift": product.get("drift"), "cpu_s": product.get("cpu_s"), **_artefact(workdir, room)})
    return rows


def _curves(rows: list[dict]) -> list[str]:
    seen = list(dict.fromkeys(r["curve"] for r in rows))
    return [c for c in seen if c != REFERENCE] + ([REFERENCE] if REFERENCE in seen else [])


def _label(curve: str) -> str:
    return f"{curve} (reference: the curve the product used to assume)" if curve == REFERENCE else curve


def scan_table(rows: list[dict]) -> list[str]:
    out = ["| curve | rooms | diffuse si-RMSE vs constant | diffuse angle vs constant | mirror vs constant | "
           "seen corr | static light read as static | response used | response CPU / job |",
           "|---|---|---|---|---|---|---|---|---|"]
    for curve in _curves(rows):
        rs = [r for r in rows if r["curve"] == curve]
        share = [r["response_s"] / r["job_stage_s"] for r in rs if r.get("job_stage_s")]
        out.append(
            f"| {_label(curve)} | {len(rs)} | {statistics.mean(r['si'] for r in rs):.2f} | "
            f"{statistics.mean(r['angle'] for r in rs):.2f} | {statistics.mean(r['mirror'] for r in rs):.2f} | "
            f"{statistics.mean(r['seen_corr'] for r in rs if r['seen_corr'] is not None):.2f} | "
            f"{sum(r['static'] for r in rs)} of {len(rs)} | "
            f"{sum(bool(r.get('response_used')) for r in rs)} of {len(rs)} | "
            + (f"{100 * statistics.mean(share):.1f} % |" if share else "— |"))
    return out


def scan_room_table(rows: list[dict]) -> list[str]:
    out = ["| room | curve | si | angle | mirror | seen corr | static | response used | grade |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["room"], _curves(rows).index(r["curve"]))):
        out.append(f"| {r['room']} | {r['curve']} | {r['si']:.2f} | {r['angle']:.2f} | {r['mirror']:.2f} | "
                   f"{r['seen_corr']:.2f} | {'yes' if r['static'] else 'no'} | "
                   f"{'yes' if r.get('response_used') else 'no'} | {r.get('grade', '—')} |")
    return out


def photo_rows(paths: list[Path]) -> list[dict]:
    rows = []
    for path in paths:
        report = json.loads(path.read_text())
        for split, body in report["splits"].items():
            field = body["methods"]["field"]
            groups = field.get("per_curve") or {report.get("curve", path.stem.rsplit("_", 1)[-1]): field}
            for curve, group in groups.items():
                vs = group.get("vs_constant", field["vs_constant"])
                rows.append({"curve": curve, "split": split, "photos": group.get("images", field["images"]),
                             "si": vs["diffuse_si_rmse_rel"], "angle": vs["diffuse_angular_deg"],
                             "seconds": field.get("seconds_per_image")})
    return rows


def photo_table(rows: list[dict]) -> list[str]:
    out = ["| curve | photos | diffuse si-RMSE vs constant | diffuse angle vs constant | s / photo |",
           "|---|---|---|---|---|"]
    for curve in _curves(rows):
        for r in (r for r in rows if r["curve"] == curve):
            out.append(f"| {_label(curve)} | {r['photos']} ({r['split']}) | {r['si']:.2f} | {r['angle']:.2f} | "
                       f"{r['seconds']:.0f} |")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scans", type=Path, required=True)
    p.add_argument("--photos", type=Path, nargs="*", default=[])
    p.add_argument("--workdir", type=Path, default=None, help="the scans' --workdir (their artefacts)")
    p.add_argument("--note", action="append", default=[], help="a line under the tables (what differs about the run)")
    p.add_argument("-o", "--out", type=Path, default=RESULTS / "RESULTS.md")
    args = p.parse_args(argv)
    scans = json.loads(args.scans.read_text())
    rows = scan_rows(scans, args.workdir)
    machine = scans.get("machine", {})
    lines = ["# The camera's response, per curve", "",
             f"Commands: `{scans.get('command')}`" + "".join(f"; `{json.loads(p.read_text()).get('command', p.name)}`"
                                                             for p in args.photos) + ".",
             f"Machine: {machine.get('cpu_model')}, {machine.get('cores')} cores (load "
             f"{machine.get('load_average_1_5_15min')}); commit {machine.get('git_commit')}; date "
             f"{machine.get('date_utc')}. Written by `python -m bench.camera_response`.", "",
             "## Room scans (46 frames, lagging auto-exposure, no poses, a plain MP4 declaring what a phone's does)",
             "",
             *scan_table(rows), "", *scan_room_table(rows), ""]
    photos = photo_rows(args.photos)
    if photos:
        lines += ["## Single photos (60° crops, a PNG declaring what a phone's file declares)", "",
                  *photo_table(photos), ""]
    lines += ["Ratios: the product's error over the constant map's (< 1 beats it), means over the rooms. "
              "`filmic` files declare sRGB and carry an undeclared tone curve; `hlg10` is a 10-bit HLG HEVC clip; "
              f"`{REFERENCE}` is the product's former assumption, kept as a labelled reference.", "",
              *(f"* {note}" for note in args.note), ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
