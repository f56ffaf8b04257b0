"""Physically based AR sessions (issue 61): what the product gets from an AR app in a rendered room.

    python -m bench.pbr_sessions [--quick] [--scenes a,b] [--variants full-ar,monocular,lidar,no-frame-ev]
                                 [--cache-dir bench/.cache/pbr] [-o bench/results/pbr_sessions] [--render-only]

Six rooms of our own (bench/pbr/scenes.py), rendered with Mitsuba 3 (scalar_rgb, path tracing):
furniture, textures, glossy objects; windows, ceiling panels, floor, desk and pendant lamps,
screens; a lamp switching on, one switching off, a dimmer, daylight fading; a walk with turns,
a look-around from one spot, a slow orbit around a table. `--quick`: the issue's own room only.

Each session (40 frames, 160x120, 10 fps) is captured as an AR app sends it (bench/pbr/camera.py:
lagging auto-exposure, shot + read noise, the sRGB curve, 8 bits, H.264; poses, intrinsics,
per-frame exposure, depth) in four variants: `full-ar` (renderer's planar depth, frame_ev),
`monocular` (no depth), `lidar` (LiDAR-like depth: a 4x coarser grid, noise, holes, upsampled
nearest), `no-frame-ev` (full AR without frame_ev). Each runs through `run_job` with the draft
preset, as `lightfield estimate session.mp4 --depth depth.npz --params params.json` runs it; the
stored field is then queried at the probes and times (artefact.envmaps, exact, 64 rows; the
/sh route's map: 128 rows at quality fast).

Ground truth: per probe (6 per room) and per light source, a cube of six 90 deg renders (32 px,
144 spp) converted to the product's equirect layout; a time's map is the sum of the sources'
maps scaled by their schedules (light is linear in the sources). Times: before and after each
event (3 frames off it; a fade's middle too), and the two ends of the longest static stretch.

Scores (bench/pbr/score.py): three-sphere ratios to the constant map (the capture's mean
linearised colour) with 95 % bootstrap intervals over rooms; lamp seen / absent; switch ratio;
/sh main light angle; SH irradiance error; drift; CPU seconds per job. Nothing is fitted on
these rooms. Every render is cached by a hash of what it depends on (--cache-dir), so a rerun
costs only the jobs.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from bench.overrides import knobs_of

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "pbr_sessions"
FRAME_SPP = 36
SPHERE_SIZE = 64
SH_HEIGHT = 128  # the /sh route's map (core.export.probe_queries.SH_ENVMAP_HEIGHT), evaluated at quality fast


# ---------------------------------------------------------------------------------------
# One session
# ---------------------------------------------------------------------------------------
def render_session(scene: dict, cache, spp: int, log=print) -> np.ndarray:
    """[T, H, W, 4] linear RGB + planar depth of every frame (cached renders)."""
    from bench.pbr.render import render_frame
    from bench.pbr.scenes import camera_poses, frame_times, scales_at

    out = []
    t0 = time.perf_counter()
    poses = camera_poses(scene)
    spp = int(scene["camera"].get("spp", spp))  # rooms lit by a lamp close to surfaces need more
    for i, t in enumerate(frame_times(scene)):
        out.append(render_frame(scene, scales_at(scene, float(t)), poses[i], spp, cache))
        if (i + 1) % 10 == 0:
            log(f"  {scene['name']}: frame {i + 1}/{len(poses)} ({time.perf_counter() - t0:.0f} s)")
    return np.stack(out)


def session_truth(scene: dict, cache, face_size: int, spp: int, log=print) -> list[dict]:
    from bench.pbr.truth import GT_HEIGHT, probe_truth

    t0 = time.perf_counter()
    out = [probe_truth(scene, p["x"], cache, face_size=face_size, spp=spp, height=GT_HEIGHT) for p in scene["probes"]]
    log(f"  {scene['name']}: ground truth at {len(out)} probes ({time.perf_counter() - t0:.0f} s)")
    return out


def run_variant(capture: dict, variant: str, workdir: Path, overrides: dict | None = None,
                preset_name: str = "draft"):
    """(artefact, CPU seconds, wall seconds) of the job (the `preset_name` preset) on one upload."""
    from core.engine import run_job
    from core.engine.params import JobParams
    from core.engine.presets import preset

    v = capture["variants"][variant]
    config = preset(preset_name).with_overrides(overrides or {})
    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings(), knobs_of(config):
        warnings.simplefilter("ignore")
        result = run_job(capture["video"], v["depth"], JobParams.model_validate(v["params"]),
                         workdir / f"job-{variant}", config=config)
    return result.artefact, time.process_time() - c0, time.perf_counter() - t0


def query(artefact, probes: list, t: float, height: int) -> torch.Tensor:
    """[P, height, 2 height, 3]: the stored field's maps at the probes at time t (exact)."""
    maps, _ = artefact.envmaps([list(map(float, p)) for p in probes], [float(t)] * len(probes), height)
    return maps.float()


def query_sh_map(artefact, probes: list, t: float) -> torch.Tensor:
    """The maps GET /lightfield/<id>/sh evaluates: SH_HEIGHT rows at quality fast."""
    from core.envmap import upsample_envmaps
    from service.queries import fast_rows

    low, _ = artefact.envmaps([list(map(float, p)) for p in probes], [float(t)] * len(probes), fast_rows(SH_HEIGHT))
    return upsample_envmaps(low, SH_HEIGHT).float()


def job_summary(artefact, cpu: float, wall: float) -> dict:
    """What the job decided and cost: time input, the temporal decision's reason, exposure and
    depth sources, whether the camera response estimated from the frames replaced the declared
    curve, the job's own quality grade (bench.suite.grade: and whether the constant map answered)."""
    from bench.suite.grade import job_grade

    meta = artefact.meta
    cap = meta.get("capture", {})
    cmeta = cap.get("metadata", {}) if isinstance(cap.get("metadata"), dict) else {}
    temporal = meta.get("temporal") if isinstance(meta.get("temporal"), dict) else {}
    response = cmeta.get("response") if isinstance(cmeta.get("response"), dict) else {}
    return {"cpu_s": round(cpu, 2), "wall_s": round(wall, 2), "uses_time": bool(meta["time"]["uses_time"]),
            "temporal_reason": temporal.get("reason"), "exposure_source": cmeta.get("exposure_source"),
            "depth_source": cap.get("depth_source"), "response_used": response.get("used"),
            "response_errors": [response.get("held_out_error_declared"), response.get("held_out_error_fitted")],
            "quality_grade": job_grade(meta)}


def lights_in_view(scene: dict) -> dict:
    """Per light: in how many frames the camera sees it (a bulb's or quad's centre, or any quad's of a
    group, inside the frame and unoccluded) while it is on, of how many, and while it is off: a
    light the camera never saw is one the product can only guess."""
    from bench.pbr.render import line_of_sight
    from bench.pbr.scenes import camera_poses, frame_times, intrinsics, scales_at

    poses, k = camera_poses(scene), intrinsics(scene)
    out = {}
    for name, light in scene["lights"].items():
        targets = [np.asarray(q["centre"], float) for q in light["quads"]] if light["kind"] == "quads" else [
            np.asarray(light["centre"], float)]
        on = off = n_on = 0
        for c2w, t in zip(poses, frame_times(scene)):
            seen = False
            for target in targets:
                p = np.linalg.inv(c2w) @ np.r_[target, 1.0]
                if p[2] >= 0:
                    continue
                u, v = k["fx"] * p[0] / -p[2] + k["cx"], -k["fy"] * p[1] / -p[2] + k["cy"]
                if 0 <= u < k["width"] and 0 <= v < k["height"] and line_of_sight(scene, c2w[:3, 3], light, target):
                    seen = True
                    break
            if scales_at(scene, float(t))[name] > 0:
                n_on += 1
                on += seen
            else:
                off += seen
        out[name] = {"kind": light["kind"], "in_view_on": on, "frames_on": n_on, "in_view_off": off}
    return out


def evaluate_session(scene: dict, cache, workdir: Path, variants, spp: int, face_size: int, cube_spp: int,
                     sphere_size: int = SPHERE_SIZE, overrides: dict | None = None, log=print,
                     render_only: bool = False, preset_name: str = "draft") -> dict:
    from bench.pbr import score
    from bench.pbr.camera import write_session
    from bench.pbr.scenes import probe_times, scales_at
    from bench.pbr.truth import GT_HEIGHT, shares, truth_map
    from bench.suite.evaluation import score_probe
    from core.envmap import upsample_envmaps

    t_render = time.perf_counter()
    misses0 = cache.misses
    rgbd = render_session(scene, cache, spp, log)
    truths = session_truth(scene, cache, face_size, cube_spp, log)
    render_s = time.perf_counter() - t_render
    renders = cache.misses - misses0
    if render_only:
        return {"scene": scene["name"], "render_s": round(render_s, 1), "renders": renders}
    capture = write_session(scene, rgbd, workdir / scene["name"])
    probes = [p["x"] for p in scene["probes"]]
    times = probe_times(scene)
    const = score.constant_map(capture["ldr"], GT_HEIGHT)

    jobs, est, est_sh = {}, {}, {}
    for v in variants:
        art, cpu, wall = run_variant(capture, v, workdir / scene["name"], overrides, preset_name)
        jobs[v] = job_summary(art, cpu, wall)
        est[v] = {row["t"]: query(art, probes, row["t"], GT_HEIGHT) for row in times}
        est_sh[v] = {row["t"]: query_sh_map(art, probes, row["t"]) for row in times}
        log(f"  {scene['name']}: {v} job {cpu:.0f} CPU s, uses time: {jobs[v]['uses_time']}")

    records = []
    for row in times:
        t = row["t"]
        sc = scales_at(scene, t)
        for j, probe in enumerate(scene["probes"]):
            tr = truths[j]
            gt = truth_map(tr["maps"], sc)
            preds = {v: est[v][t][j] for v in variants} | {"mean-colour": const}
            rec = {"probe": j, "label": probe["label"], "t": t, "roles": row["roles"], "scales": sc,
                   "shares": {k: round(s, 4) for k, s in shares(tr["maps"], sc).items()},
                   "fluence": {"truth": score.fluence(gt)} | {v: score.fluence(est[v][t][j]) for v in variants},
                   "spheres": score_probe(preds, gt, sphere_size)}
            # lamps: seen while on, absent while off (where the truth passes the same test)
            lamps = {}
            for name, src in tr["sources"].items():
                if src["kind"] != "bulb" or not src["line_of_sight"]:
                    continue
                s = sc[name]
                state = "on" if s >= score.ON_SCALE else ("off" if s <= 0.0 else None)
                if state is None:
                    continue
                truth_seen = score.lamp_seen(gt, src["direction"])
                if truth_seen != (state == "on"):
                    lamps[name] = {"state": state, "truth_passes": False}
                    continue
                lamps[name] = {"state": state, "truth_passes": True,
                               "seen": {v: score.lamp_seen(est[v][t][j], src["direction"]) for v in variants}}
            rec["lamps"] = lamps
            # the /sh main light where one source dominates and is in sight
            top = max(rec["shares"], key=rec["shares"].get)
            src = tr["sources"][top]
            if rec["shares"][top] >= score.MAIN_SHARE and src["line_of_sight"]:
                gt128 = upsample_envmaps(gt[None], SH_HEIGHT)[0]
                truth_light = score.main_light(gt128)
                ml = {"source": top, "share": rec["shares"][top],
                      "truth_map_angle_deg": round(score.angle_deg(truth_light["direction"], src["direction"]), 2)}
                for v in variants:
                    light = score.main_light(est_sh[v][t][j])
                    ml[v] = {"angle_deg": round(score.angle_deg(light["direction"], src["direction"]), 2),
                             "found": light["found"], "confidence": round(light["confidence"], 3)}
                rec["main_light"] = ml
            records.append(rec)

    # SH irradiance error, one scale per session and method
    gts = [truth_map(truths[r["probe"]]["maps"], r["scales"]) for r in records]
    sh = {}
    for v in [*variants, "mean-colour"]:
        maps = [const if v == "mean-colour" else est[v][r["t"]][r["probe"]] for r in records]
        errs, stops = score.sh_errors(maps, gts)
        sh[v] = {"mean": float(np.mean(errs)), "scale_stops": round(stops, 3)}
        for r, e in zip(records, errs):
            r.setdefault("sh_error", {})[v] = round(e, 4)

    # switch ratios per event and probe
    switches = []
    for k, ev in enumerate(scene["events"]):
        before = next(r["t"] for r in times if {"role": "before", "event": k} in r["roles"])
        after = next(r["t"] for r in times if {"role": "after", "event": k} in r["roles"])
        per_probe = []
        for j in range(len(probes)):
            rb = next(r for r in records if r["t"] == before and r["probe"] == j)
            ra = next(r for r in records if r["t"] == after and r["probe"] == j)
            entry = {"probe": j, "truth": ra["fluence"]["truth"] / rb["fluence"]["truth"]}
            for v in variants:
                entry[v] = ra["fluence"][v] / max(rb["fluence"][v], 1e-30)
            per_probe.append(entry)
        switches.append({"event": ev, "before": before, "after": after, "probes": per_probe})

    # drift over the static stretch
    drift = None
    static = [r["t"] for r in times if any(x["role"] in ("static-start", "static-end") for x in r["roles"])]
    if len(static) == 2:
        drift = {v: [score.relative_l1(est[v][static[0]][j], est[v][static[1]][j]) for j in range(len(probes))]
                 for v in variants}
        drift["truth"] = [score.relative_l1(truth_map(truths[j]["maps"], scales_at(scene, static[0])),
                                            truth_map(truths[j]["maps"], scales_at(scene, static[1])))
                          for j in range(len(probes))]
        drift["times"] = static
    sources = [{name: {"line_of_sight": s["line_of_sight"], "direction": [round(float(c), 4) for c in s["direction"]]}
                for name, s in tr["sources"].items()} for tr in truths]
    return {"scene": scene["name"], "render_s": round(render_s, 1), "renders": renders, "jobs": jobs,
            "probes": scene["probes"], "sources": sources, "times": times, "records": records, "sh": sh,
            "switches": switches, "drift": drift, "frame_ev": [round(e, 3) for e in capture["evs"]],
            "lights_in_view": lights_in_view(scene)}


# ---------------------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------------------
METRICS = (("diffuse", "si_rmse_rel"), ("diffuse", "angular_deg"), ("mirror", "si_rmse_rel"), ("matte", "si_rmse_rel"))


def _mean(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return sum(xs) / len(xs) if xs else None


def summarise_variant(sessions: list[dict], v: str) -> dict:
    from bench.suite.evaluation import ratio_interval

    out: dict = {"rooms": len(sessions)}
    for material, metric in METRICS:
        num, den = [], []
        for s in sessions:
            pairs = [(r["spheres"][v][material][metric], r["spheres"]["mean-colour"][material][metric])
                     for r in s["records"] if "non_finite" not in r["spheres"].get(v, {"non_finite": 1})]
            if pairs:
                num.append(sum(a for a, _ in pairs) / len(pairs))
                den.append(sum(b for _, b in pairs) / len(pairs))
        if num:
            out[f"{material}_{metric}"] = {
                "ratio": round(sum(num) / sum(den), 4),
                "interval_95": ratio_interval(num, den, level=0.95) if len(num) > 1 else [None, None],
                "per_room": [round(a / b, 3) for a, b in zip(num, den)]}
    on = [r["lamps"][n]["seen"][v] for s in sessions for r in s["records"] for n in r["lamps"]
          if r["lamps"][n]["truth_passes"] and r["lamps"][n]["state"] == "on"]
    off = [r["lamps"][n]["seen"][v] for s in sessions for r in s["records"] for n in r["lamps"]
           if r["lamps"][n]["truth_passes"] and r["lamps"][n]["state"] == "off"]
    out["lamp_seen_on"] = [sum(on), len(on)]
    out["lamp_seen_off"] = [sum(off), len(off)]
    # does the estimate's answer follow the lamp? per (room, lamp, probe) scored both on and off
    same = []
    for s in sessions:
        answers: dict = {}
        for r in s["records"]:
            for n, lamp in r["lamps"].items():
                if lamp["truth_passes"]:
                    answers.setdefault((n, r["probe"]), {}).setdefault(lamp["state"], set()).add(lamp["seen"][v])
        same += [a["on"] == a["off"] and len(a["on"]) == 1 for a in answers.values() if "on" in a and "off" in a]
    out["lamp_same_on_and_off"] = [sum(same), len(same)]
    errs, captured, spread = [], [], []
    for s in sessions:
        for sw in s["switches"]:
            lt = [math.log2(p["truth"]) for p in sw["probes"]]
            le = [math.log2(max(p[v], 1e-30)) for p in sw["probes"]]
            errs += [abs(a - b) for a, b in zip(le, lt)]
            captured += [a / b for a, b in zip(le, lt) if abs(b) > 0.1]
            if len(lt) > 1 and statistics.pstdev(lt) > 1e-6:
                spread.append(statistics.pstdev(le) / statistics.pstdev(lt))
    out["switch_error_stops"] = round(_mean(errs), 3) if errs else None
    out["switch_captured_median"] = round(statistics.median(captured), 3) if captured else None
    out["switch_spread"] = round(_mean(spread), 3) if spread else None
    angles = [r["main_light"][v]["angle_deg"] for s in sessions for r in s["records"] if "main_light" in r]
    found = [r["main_light"][v]["found"] for s in sessions for r in s["records"] if "main_light" in r]
    truth_angles = [r["main_light"]["truth_map_angle_deg"] for s in sessions for r in s["records"]
                    if "main_light" in r]
    out["main_light"] = {"n": len(angles), "median_deg": round(statistics.median(angles), 1) if angles else None,
                         "within_20deg": sum(a <= 20 for a in angles), "found": sum(found),
                         "truth_map_median_deg": round(statistics.median(truth_angles), 1) if truth_angles else None}
    out["sh_error"] = round(_mean([s["sh"][v]["mean"] for s in sessions]), 4)
    out["sh_error_constant"] = round(_mean([s["sh"]["mean-colour"]["mean"] for s in sessions]), 4)
    out["sh_scale_stops"] = [s["sh"][v]["scale_stops"] for s in sessions]
    drifts = [_mean(s["drift"][v]) for s in sessions if s.get("drift")]
    out["drift"] = round(_mean(drifts), 4) if drifts else None
    cpu = [s["jobs"][v]["cpu_s"] for s in sessions]
    out["cpu_s"] = round(_mean(cpu), 1)
    out["cpu_s_max"] = round(max(cpu), 1)
    out["uses_time"] = sum(s["jobs"][v]["uses_time"] for s in sessions)
    return out


def compact(value):
    """The report as plain JSON with floats at 5 significant digits (the scores carry no more)."""
    from bench.report import sanitize

    def rnd(x):
        if isinstance(x, dict):
            return {k: rnd(v) for k, v in x.items()}
        if isinstance(x, list):
            return [rnd(v) for v in x]
        return float(f"{x:.5g}") if isinstance(x, float) else x

    return rnd(sanitize(value))


def _cell(m: dict, key: str) -> str:
    v = m.get(key)
    if not v:
        return "–"
    lo, hi = v["interval_95"]
    return f"{v['ratio']:.2f} [{lo:.2f}, {hi:.2f}]" if lo is not None else f"{v['ratio']:.2f}"


def markdown(report: dict) -> str:
    lines = ["# Physically based AR sessions (issue 61)", "",
             f"Command: `{report['command']}`" + (f" (tables regenerated from its JSON by `{report['rescored']}`)"
                                                  if report.get("rescored") else ""), ""]
    m = report["machine"]
    lines += [f"Machine: {m.get('cpu_model')}, {m.get('cores')} cores, load {m.get('load_average_1_5_15min')}, "
              f"torch {m.get('torch_version')}, mitsuba {report.get('mitsuba')}; commit "
              f"{str(m.get('git_commit', ''))[:10]} (tracked files modified: {m.get('git_tracked_files_modified')}); "
              f"{m.get('date_utc')}. Wall time {report.get('wall_s', 0) / 60:.0f} min (renders "
              f"{report.get('render_s', 0) / 60:.0f} min, {report.get('renders', 0)} not cached).", ""]
    lines += ["Protocol: see the docstrings of `bench/pbr_sessions.py` and `bench/pbr/score.py`. "
              f"{len(report['sessions'])} rooms, {sum(len(s['probes']) for s in report['sessions'])} probes; "
              "ratios are the variant's mean over a room's probe-times / the constant map's (the capture's mean "
              "linearised colour), pooled over rooms, 95 % bootstrap interval over rooms (< 1 beats the constant "
              "map). Lamp seen: probe-times with the lamp in sight where the estimate shows it among its brightest "
              "0.5 % of the sphere within 15 deg (on: want all; off: want none). Switch: |log2| error of the "
              "fluence ratio after/before each event (stops), median share of the truth's log change captured, "
              "spread = std over probes of the estimate's log ratio / the truth's (1: localised, 0: uniform over "
              "the room). Main light: /sh dominant light vs the direction of the source giving >= 30 % of the "
              "fluence (median angle, within 20 deg, found) — the truth map's own is in brackets. SH error: "
              "relative RMS irradiance error after one scale per session (constant map in brackets). Drift: "
              "relative L1 between the maps at the ends of the static stretch (truth 0).", ""]
    head = ("| variant | diffuse si-RMSE vs const | diffuse angle vs const | mirror si-RMSE vs const | lamp seen on | "
            "lamp seen off | lamp answer same on and off | switch err (stops) / captured / spread | "
            "main light angle (truth map) / ≤20° / found | SH err (const) | drift | CPU s (max) | uses time |")
    lines += [head, "|" + "---|" * 13]
    for v, s in report["summary"].items():
        ml = s["main_light"]
        lines.append(
            f"| {v} | {_cell(s, 'diffuse_si_rmse_rel')} | {_cell(s, 'diffuse_angular_deg')} | "
            f"{_cell(s, 'mirror_si_rmse_rel')} | {s['lamp_seen_on'][0]}/{s['lamp_seen_on'][1]} | "
            f"{s['lamp_seen_off'][0]}/{s['lamp_seen_off'][1]} | "
            f"{s['lamp_same_on_and_off'][0]}/{s['lamp_same_on_and_off'][1]} | {s['switch_error_stops']} / "
            f"{s['switch_captured_median']} / {s['switch_spread']} | {ml['median_deg']}° "
            f"({ml['truth_map_median_deg']}°) / {ml['within_20deg']}/{ml['n']} / {ml['found']}/{ml['n']} | "
            f"{s['sh_error']:.3f} ({s['sh_error_constant']:.3f}) | {s['drift'] if s['drift'] is not None else '–'} | "
            f"{s['cpu_s']} ({s['cpu_s_max']}) | {s['uses_time']}/{s['rooms']} |")
    lines += ["", "Per room:", "",
              "| room | variant | diffuse / angle / mirror vs const | lamp on | lamp off | switch err (stops) | "
              "main light median | SH err (const) | SH scale (stops) | drift | CPU s | uses time | response fitted | "
              "job's grade |",
              "|" + "---|" * 14]
    for s in report["sessions"]:
        for v in report["variants"]:
            one = summarise_variant([s], v)
            ratios = " / ".join(f"{one[k]['ratio']:.2f}" if k in one else "–" for k in (
                "diffuse_si_rmse_rel", "diffuse_angular_deg", "mirror_si_rmse_rel"))
            job = s["jobs"][v]
            lines.append(
                f"| {s['scene']} | {v} | {ratios} | {one['lamp_seen_on'][0]}/{one['lamp_seen_on'][1]} | "
                f"{one['lamp_seen_off'][0]}/{one['lamp_seen_off'][1]} | {one['switch_error_stops']} | "
                f"{one['main_light']['median_deg']}° | {s['sh'][v]['mean']:.3f} ({s['sh']['mean-colour']['mean']:.3f})"
                f" | {s['sh'][v]['scale_stops']} | {one['drift'] if one['drift'] is not None else '–'} | "
                f"{job['cpu_s']:.0f} | {job['uses_time']} | {job.get('response_used')} | {job.get('quality_grade')} |")
    lines += ["", "Lights in the camera's view (frames showing the light's centre unoccluded, while on / frames on; "
              "while off):", "", "| room | light | kind | in view while on | while off |", "|---|---|---|---|---|"]
    for s in report["sessions"]:
        for name, L in (s.get("lights_in_view") or {}).items():
            lines.append(f"| {s['scene']} | {name} | {L['kind']} | {L['in_view_on']}/{L['frames_on']} | "
                         f"{L['in_view_off']} |")
    lines += ["", "Switches (fluence after / before, per probe: truth → " + ", ".join(report["variants"]) + "):", ""]
    for s in report["sessions"]:
        for sw in s["switches"]:
            ev = sw["event"]
            cells = "; ".join(f"{s['probes'][p['probe']]['label']}: {p['truth']:.2f} → "
                              + ", ".join(f"{p[v]:.2f}" for v in report["variants"]) for p in sw["probes"])
            lines.append(f"* {s['scene']}, {ev['light']} {ev['kind']} ({sw['before']:.1f} s → {sw['after']:.1f} s): "
                         f"{cells}")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------
def main(argv=None) -> int:
    from bench.overrides import parse_set
    from bench.pbr.camera import VARIANTS
    from bench.pbr.render import DEFAULT_CACHE_DIR, RenderCache, mitsuba
    from bench.pbr.scenes import QUICK_SCENES, SCENES, get_scene
    from bench.pbr.truth import CUBE_SPP, FACE_SIZE
    from bench.report import sanitize
    from bench.suite.measure import machine_info

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help=f"one room ({', '.join(QUICK_SCENES)})")
    p.add_argument("--scenes", default=None, help=f"comma-separated subset of {','.join(SCENES)}")
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--cache-dir", default=str(DEFAULT_CACHE_DIR), help="render cache (git-ignored by default)")
    p.add_argument("-o", "--out", default=str(DEFAULT_OUT), help="directory of RESULTS.md and results.json")
    p.add_argument("--workdir", default=None, help="captures and artefacts (default: a temporary directory)")
    p.add_argument("--spp", type=int, default=FRAME_SPP, help="samples per pixel of the frames")
    p.add_argument("--face-size", type=int, default=FACE_SIZE)
    p.add_argument("--cube-spp", type=int, default=CUBE_SPP)
    p.add_argument("--sphere-size", type=int, default=SPHERE_SIZE)
    p.add_argument("--render-only", action="store_true", help="fill the render cache, run no job")
    p.add_argument("--preset", default="draft", help="the engine preset every job runs (default: draft)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="draft preset override for every job (JSON value): ablations, not the product")
    p.add_argument("--rescore", default=None, metavar="RESULTS_JSON",
                   help="re-summarise a saved report (its sessions as they are; what a session lacks that the scene "
                        "gives without rendering, e.g. lights_in_view, is added) and write RESULTS.md beside it")
    args = p.parse_args(argv)
    if args.rescore:
        path = Path(args.rescore)
        report = json.loads(path.read_text())
        for s in report["sessions"]:
            if "lights_in_view" not in s:
                s["lights_in_view"] = lights_in_view(get_scene(s["scene"]))
        report["summary"] = {v: summarise_variant(report["sessions"], v) for v in report["variants"]}
        report["rescored"] = "python -m bench.pbr_sessions " + " ".join(argv if argv is not None else sys.argv[1:])
        path.write_text(json.dumps(compact(report), indent=1))
        (path.parent / "RESULTS.md").write_text(markdown(sanitize(report)))
        print(markdown(sanitize(report)))
        return 0
    names = list(QUICK_SCENES) if args.quick else (args.scenes.split(",") if args.scenes else list(SCENES))
    variants = tuple(args.variants.split(","))
    overrides = parse_set(args.set) if args.set else None
    torch.set_num_threads(1)
    cache = RenderCache(args.cache_dir)
    out_dir = Path(args.out)
    command = "python -m bench.pbr_sessions " + " ".join(argv if argv is not None else sys.argv[1:])
    report: dict = {"command": command.strip(), "machine": machine_info(), "mitsuba": mitsuba().__version__,
                    "variants": variants, "overrides": overrides, "preset": args.preset,
                    "settings": {"frame_spp": args.spp, "face_size": args.face_size, "cube_spp": args.cube_spp,
                                 "sphere_size": args.sphere_size}, "sessions": []}
    t0 = time.perf_counter()

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.workdir or tmp)
        for name in names:
            log(f"{name} ({time.perf_counter() - t0:.0f} s)")
            s = evaluate_session(get_scene(name), cache, work, variants, args.spp, args.face_size, args.cube_spp,
                                 args.sphere_size, overrides, log, args.render_only, args.preset)
            report["sessions"].append(s)
            if not args.render_only:
                out_dir.mkdir(parents=True, exist_ok=True)
                (out_dir / "results.json").write_text(json.dumps(compact({**report, "partial": True}), indent=1))
    report["wall_s"] = round(time.perf_counter() - t0, 1)
    report["render_s"] = round(sum(s["render_s"] for s in report["sessions"]), 1)
    report["renders"] = sum(s["renders"] for s in report["sessions"])
    if args.render_only:
        log(f"rendered {report['renders']} (cache {cache.root}) in {report['wall_s']:.0f} s")
        return 0
    report["summary"] = {v: summarise_variant(report["sessions"], v) for v in variants}
    (out_dir / "results.json").write_text(json.dumps(compact(report), indent=1))
    (out_dir / "RESULTS.md").write_text(markdown(sanitize(report)))
    print(markdown(sanitize(report)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
