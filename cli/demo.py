"""`lightfield demo`: the product end to end on a simulated room, through the embedded service.

1. simulate the `spatial` suite (core.sim): a room with two strong near lamps, so the lighting
   visibly varies over space; one 192x144 frame, depth, camera, and held-out probes with
   ground-truth env maps;
2. start `service.local.EmbeddedService` (its own Redis, Celery worker and uvicorn on loopback,
   data under OUT/service) and upload the capture as a user would: the frame as PNG (an MP4
   for a video), depth as .npz, intrinsics / poses / fps in `params`;
3. wait for the job (a progress line on stderr), fetch the env maps at the held-out probes over
   HTTP as EXR, and the insertion preview from the service's /insertion endpoint;
4. compare with the ground truth, next to a spatially constant baseline (one env map for the
   whole room: the field's own maps averaged over the probes), so the table shows what
   querying the field per point buys; stop the service.

`--no-service` runs the same job in-process (`core.engine.run_job`, no subprocesses)
and writes the same outputs.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from cli import choices
from cli.demo_scan import format_scan, room_scan_demo
from cli.demo_upload import Upload

HELP = "Simulate a room, estimate its light field through the embedded service, and compare with the truth."
SUITE = "spatial"
ENV_HEIGHT = 64  # of the env maps fetched and compared
SPHERE_SIZE = 64  # diffuse-sphere renders for the metric
PREVIEW_POINTS = "0.3,0.7;0.7,0.7"  # `lightfield preview`'s default points (u, v fractions of the frame)
PREVIEW_ENV_HEIGHT = 32


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", default="demo-output", help="output directory (default ./demo-output)")
    p.add_argument("--preset", choices=choices.PRESETS, metavar="PRESET", default="draft", help="one of %(choices)s")
    p.add_argument("--iterations", type=int, default=None, help="override the preset's step count")
    p.add_argument("--no-service", action="store_true",
                   help="run the job in this process instead of through the embedded service (no subprocesses)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.add_argument("--camera", choices=("rec709", "srgb", "filmic", "hlg10"), default="rec709",
                   help="the room scan's camera curve: 8-bit rec709 / srgb / filmic H.264, or hlg10, a 10-bit HLG "
                        "HEVC clip as iPhones record HDR video (default %(default)s)")
    p.add_argument("--no-scan", action="store_true",
                   help="skip the second job: a room scan of the bundled panorama (assets/sample_panorama.hdr)")


def run(args: argparse.Namespace) -> int:
    from service.local import EmbeddedServiceError

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))

    steps = 4 if args.no_scan else 5
    say(f"1/{steps} simulating the '{SUITE}' scene (core.sim) ...")
    doc, upload = _simulate(out / "capture", args.preset)
    backend = _LocalRun(out, args) if args.no_service else _ServiceRun(out, args)
    try:
        with backend:
            say(f"2/{steps} estimating the light field ({args.preset} preset, reprojection prior) {backend.where} ...")
            backend.estimate(upload)
            say(f"3/{steps} fetching env maps at the held-out probes and the insertion preview ...")
            env_dir = out / "envmaps"
            env_dir.mkdir(exist_ok=True)
            flags = [
                backend.save_envmap(p["x"], p["t"], env_dir / f"probe{k}_estimate.exr")
                for k, p in enumerate(doc["probes"])
            ]
            preview = backend.save_preview(out / "preview.png")
            meta = backend.metadata()
            job_id, artefact_dir = backend.job_id, backend.artefact_dir
            if not args.no_scan:
                say(f"4/{steps} a room scan (46 frames turning about one spot, auto-exposure on, no poses) of "
                    "the bundled panorama: tracking, HDR recovery, distillation ...")
                scan = room_scan_demo(out / "scan", backend, args.preset, args.camera)
    except EmbeddedServiceError as exc:
        print(f"demo: the service failed: {exc}", file=sys.stderr)
        return 1
    say(f"{steps}/{steps} comparing with the ground truth ...")
    rows = compare_probes(out / "capture", doc, env_dir)
    for row, flag in zip(rows, flags):
        row["extrapolated"] = flag
    _write_side_by_side(out / "capture", doc, env_dir)
    summary = {
        "mode": "in-process" if args.no_service else "embedded service",
        "job": job_id,
        "artefact": str(artefact_dir) if artefact_dir else None,
        "service_data_dir": None if args.no_service else str(out / "service"),
        "envmaps": str(env_dir),
        "preview": str(preview),
        "metric": METRIC_NOTE,
        "probes": rows,
        "wall_time_s": meta.get("training", {}).get("wall_time_s"),
        "device": meta.get("training", {}).get("device"),
    }
    if not args.no_scan:
        summary["room_scan"] = scan
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(format_table(rows))
    if not args.no_scan:
        print("\n" + format_scan(scan))
    print(f"\ndemo outputs in {out.resolve()}:\n"
          f"  light field  {summary['artefact'] or '(in the service data dir)'}\n"
          f"  env maps     {env_dir}  (probeK_estimate.exr; probeK_estimate_vs_truth.png: top estimate, bottom truth)\n"
          f"  preview      {preview}\n"
          f"  summary      {out / 'summary.json'}")
    if not args.no_service:  # the job record persists with the data dir
        print(f"query it again: LIGHTFIELD_DATA_DIR={out / 'service'} lightfield serve, then\n"
              f"  curl 'http://127.0.0.1:8000/lightfield/{job_id}/envmap?x=1.6,0.3,2.0&format=png' -o env.png")
    return 0


# ---------------------------------------------------------------------------------------
# The capture, as a user would upload it
# ---------------------------------------------------------------------------------------
def _simulate(capture_dir: Path, preset: str) -> tuple[dict, Upload]:
    from core.sim.capture import write_capture
    from core.sim.suites import suite

    scene = suite(SUITE)
    doc = write_capture(scene, capture_dir, envmap_height=ENV_HEIGHT, video=scene.frames > 1)
    k = doc["intrinsics"]
    params = {
        "intrinsics": {n: k[n] for n in ("fx", "fy", "cx", "cy")},
        "poses": doc["poses"],
        "fps": doc["fps"],
        "preset": preset,
    }
    media = doc["video"] if scene.frames > 1 else doc["frames"][0]
    return doc, Upload(capture_dir / media, capture_dir / doc["depth"], params)


# ---------------------------------------------------------------------------------------
# Two ways to run the job, with the same outputs
# ---------------------------------------------------------------------------------------
def _distill_overrides(args) -> dict:
    return {"iterations": args.iterations} if args.iterations else {}


class _ServiceRun:
    """Through `lightfield serve` (service.local.EmbeddedService), over HTTP only."""

    def __init__(self, out: Path, args):
        from service.local import EmbeddedService

        env = {"OMP_NUM_THREADS": "1"}  # the worker's distillation is single-threaded anyway
        if _distill_overrides(args):
            env["LIGHTFIELD_DISTILL_OVERRIDES"] = json.dumps(_distill_overrides(args))
        self.service = EmbeddedService(out / "service", env=env)
        self.quiet = args.quiet
        self.job_id: str | None = None
        self.artefact_dir: Path | None = None

    @property
    def where(self) -> str:
        return f"through the embedded service (data: {self.service.data_dir})"

    def __enter__(self) -> "_ServiceRun":
        self.service.start()
        return self

    def __exit__(self, *exc) -> None:
        code = self.service.stop()
        if code not in (0, None):
            print(f"demo: the service exited with code {code}; see {self.service.log_path}", file=sys.stderr)

    def estimate(self, upload: Upload) -> None:
        from cli.estimate import ProgressBar

        self.job_id = self.service.submit(upload.file, upload.params, upload.depth)
        bar = None if self.quiet else ProgressBar()
        self.service.wait(
            self.job_id, timeout_s=1800, on_update=None if bar is None else lambda body: bar(_progress_of(body))
        )
        self.artefact_dir = _stored_artefact(self.service.data_dir, self.job_id)

    def save_envmap(self, x, t: float, path: Path) -> str:
        from service.local import EmbeddedServiceError

        # exact: the table compares the field itself with the ground truth (the API's default,
        # quality=fast, trades angular detail for speed: docs/api.md "Query speed")
        query = {"x": ",".join(f"{float(v):.6g}" for v in x), "t": t, "height": ENV_HEIGHT, "format": "exr",
                 "quality": "exact"}
        resp = self.service.client.get(f"/lightfield/{self.job_id}/envmap", params=query)
        if resp.status_code != 200:
            raise EmbeddedServiceError(f"GET envmap: {resp.status_code} {resp.text}")
        path.write_bytes(resp.content)
        return resp.headers.get("X-Lightfield-Extrapolated", "unknown")

    def save_preview(self, path: Path) -> Path:
        from service.local import EmbeddedServiceError

        resp = self.service.client.get(f"/lightfield/{self.job_id}/insertion",
                                       params={"points": PREVIEW_POINTS, "t": 0.0, "env_height": PREVIEW_ENV_HEIGHT})
        if resp.status_code != 200:
            raise EmbeddedServiceError(f"GET insertion: {resp.status_code} {resp.text}")
        path.write_bytes(resp.content)
        return path

    def metadata(self) -> dict:
        resp = self.service.client.get(f"/lightfield/{self.job_id}")
        return resp.json().get("metadata", {}) if resp.status_code == 200 else {}


class _LocalRun:
    """In this process: `run_job` on the same files, the artefact read directly."""

    def __init__(self, out: Path, args):
        self.out, self.args = out, args
        self.job_id = "local"
        self.artefact_dir: Path | None = None
        self.upload: Upload | None = None
        self._art = None

    where = "in-process (--no-service)"

    def __enter__(self) -> "_LocalRun":
        return self

    def __exit__(self, *exc) -> None:
        return None

    def estimate(self, upload: Upload) -> None:
        import warnings

        from cli.estimate import ProgressBar
        from core.engine import run_job
        from core.engine.params import JobParams

        params = JobParams.model_validate(upload.params)
        distill = _distill_overrides(self.args)  # as the service's worker gets them (LIGHTFIELD_DISTILL_OVERRIDES)
        overrides = {"distill": distill} if distill else None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the service path does not show them either
            result = run_job(upload.file, upload.depth, params, self.out / upload.name, overrides=overrides,
                             progress=None if self.args.quiet else ProgressBar(),
                             checkpoint_dir=self.out / f"{upload.name}.checkpoint")
        self.upload = upload
        self.artefact_dir, self._art = result.path, result.artefact

    def save_envmap(self, x, t: float, path: Path) -> str:
        import torch

        from core.io import save_envmap

        env, flags = self._art.envmap(
            torch.tensor(x, dtype=torch.float32), t if self._art.uses_time else None, ENV_HEIGHT
        )
        save_envmap(path, env.numpy())
        return ",".join(k for k in ("x", "t") if flags[f"extrapolated_{k}"]) or "none"  # as the HTTP header

    def save_preview(self, path: Path) -> Path:
        from cli.preview import render_preview

        return render_preview(self.artefact_dir, self.upload.file, path, depth=self.upload.depth,
                              points=PREVIEW_POINTS, env_height=PREVIEW_ENV_HEIGHT)

    def metadata(self) -> dict:
        return self._art.meta


def _progress_of(body: dict):
    """A job record (GET /jobs/{id}) as the engine's Progress, for the CLI's progress bar."""
    from core.engine.progress import Progress

    done = body.get("state") == "succeeded"
    stage = "done" if done else (body.get("stage") or body.get("state") or "queued")
    return Progress(stage, int(body.get("iteration") or 0), int(body.get("total") or 0), body.get("loss"),
                    1.0 if done else float(body.get("progress") or 0.0), body.get("eta_s"),
                    f"job {body.get('id', '')}" if done else body.get("message") or "")


def _stored_artefact(data_dir: Path, job_id: str) -> Path | None:
    """The artefact directory the service stored for this job (for the user to find)."""
    hits = sorted((Path(data_dir) / "artefacts").glob(f"*/{job_id}/**/lightfield.json"))
    return hits[0].parent if hits else None


# ---------------------------------------------------------------------------------------
# Comparison with the ground truth
# ---------------------------------------------------------------------------------------
METRIC_NOTE = (
    "diffuse sphere rendered under each env map (core.metrics three-sphere protocol): "
    "si_rmse = scale-invariant RMSE vs truth (direction and colour of the light); "
    "stops = log2(mean brightness / truth's) (how bright; the spatial falloff near lamps); "
    "constant = one env map for the whole room (the field's maps averaged over the probes)"
)


def compare_probes(capture_dir: Path, doc: dict, env_dir: Path) -> list[dict]:
    """Per held-out probe: the field's env map and the constant baseline against the truth."""
    import torch

    from core.io import load_envmap
    from core.metrics import render_probe_spheres, si_rmse

    est = [torch.from_numpy(load_envmap(env_dir / f"probe{k}_estimate.exr")) for k in range(len(doc["probes"]))]
    gts = [torch.from_numpy(load_envmap(capture_dir / p["envmap"])) for p in doc["probes"]]
    constant = torch.stack(est).mean(0)
    rows = []
    for k, (probe, e, g) in enumerate(zip(doc["probes"], est, gts)):
        (se, sc, sg), mask = render_probe_spheres([e, constant, g], "diffuse", SPHERE_SIZE)
        rows.append({
            "probe": k, "x": probe["x"], "t": probe["t"],
            "field": {"si_rmse": si_rmse(se, sg, mask), "stops": _stops(se, sg, mask)},
            "constant": {"si_rmse": si_rmse(sc, sg, mask), "stops": _stops(sc, sg, mask)},
            "main_light": _main_light(e, g),
        })
    return rows


def _main_light(estimate, truth) -> dict:
    """The AR main light (core.lights) of the estimated map, and its angle to the true map's."""
    import math

    from core.lights import extract_dominant_light

    est, gt = extract_dominant_light(estimate), extract_dominant_light(truth)
    cos = float((est.direction.double() @ gt.direction.double()).clamp(-1, 1))
    return {"found": est.found, "confidence": est.confidence, "reason": est.reason,
            "angle_to_truth_deg": math.degrees(math.acos(cos)) if est.found and gt.found else None}


def _stops(pred, gt, mask) -> float:
    import math

    p, g = float(pred[mask].mean()), float(gt[mask].mean())
    return math.log2(max(p, 1e-12) / max(g, 1e-12))


def format_table(rows: list[dict]) -> str:
    head = (f"{'probe':<6}{'x (m)':<22}{'si-RMSE field':>14}{'constant':>10}{'stops field':>13}{'constant':>10}"
            f"{'main light':>12}{'vs truth':>10}")
    lines = ["Held-out probes vs ground truth (diffuse sphere; lower |value| is better):", head]
    for r in rows:
        x = "(" + ", ".join(f"{v:.2f}" for v in r["x"]) + ")"
        f, c = r["field"], r["constant"]
        light = r.get("main_light") or {}
        found = f"{light['confidence']:.2f}" + ("" if light.get("found") else " (no)") if light else "-"
        angle = light.get("angle_to_truth_deg")
        lines.append(f"{r['probe']:<6}{x:<22}{f['si_rmse']:>14.3f}{c['si_rmse']:>10.3f}{f['stops']:>+13.2f}{c['stops']:>+10.2f}"
                     f"{found:>12}{'-' if angle is None else f'{angle:.0f} deg':>10}")
    n = len(rows)
    if n:
        mean = lambda who, key: sum(abs(r[who][key]) for r in rows) / n  # noqa: E731
        lines.append(f"{'mean':<28}{mean('field', 'si_rmse'):>14.3f}{mean('constant', 'si_rmse'):>10.3f}"
                     f"{mean('field', 'stops'):>13.2f}{mean('constant', 'stops'):>10.2f}   (stops: mean |.|)")
        wins = sum(r["field"]["si_rmse"] < r["constant"]["si_rmse"] for r in rows)
        lines.append(f"The field beats one room-wide env map on si-RMSE at {wins} of {n} probes.")
        found = sum(bool((r.get("main_light") or {}).get("found")) for r in rows)
        lines.append(f"Main light (AR: /sh) found at {found} of {n} probes; 'main light' = its confidence, "
                     "'vs truth' = angle to the true map's main light.")
    return "\n".join(lines)


def _write_side_by_side(capture_dir: Path, doc: dict, env_dir: Path) -> None:
    import numpy as np

    from core.io import load_envmap, write_png
    from core.io.envmap_io import tonemapped_preview

    for k, probe in enumerate(doc["probes"]):
        est = load_envmap(env_dir / f"probe{k}_estimate.exr")
        gt = load_envmap(capture_dir / probe["envmap"])
        write_png(env_dir / f"probe{k}_estimate_vs_truth.png",
                  np.concatenate([tonemapped_preview(est), tonemapped_preview(gt)], axis=0))
