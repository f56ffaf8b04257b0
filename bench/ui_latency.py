"""Latency of the web page's own endpoints (service.routes.ui) at the largest preview size.

    python -m bench.ui_latency [--probes 4] [--repeats 10]

Builds, in-process (real Redis, FastAPI TestClient, no worker), a succeeded job whose
capture preview is PREVIEW_MAX_HEIGHT rows high and whose artefact is the draft preset's
MLP, then times what one click or one time-slider step costs the page: /frame, /probe,
/insertion with N probes and /envmap (PNG, 128 rows). Prints median and 90th percentile
milliseconds as JSON. The numbers are machine-dependent; no test asserts them.
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def _job(ctx, height: int) -> str:
    import torch

    from core.camera import Intrinsics
    from core.engine.presets import preset
    from core.fields import SceneBounds, build_field
    from core.fields.stored.artefact import save_artefact
    from jobs.capture_preview import CapturePreview, save_preview
    from jobs.storage import JobPaths, new_job_id
    from jobs.store import JobRecord
    from service.auth import LOCAL_TENANT, tenant_hash

    width, frames = height * 4 // 3, 16
    field = build_field(preset("draft").field.with_kind("mlp"),
                        SceneBounds((-3.0, -2.0, -5.0), (3.0, 2.0, 0.5), t0=0.0, t1=(frames - 1) / 8.0))
    torch.manual_seed(0)
    job = new_job_id()
    record = JobRecord(id=job, tenant=LOCAL_TENANT, tenant_hash=tenant_hash(LOCAL_TENANT), input_kind="video")
    ctx.store.create(record, max_in_flight=100)
    paths = JobPaths.for_job(ctx.settings.data_dir, record.tenant_hash, job)
    save_artefact(paths.artefact_dir, field, {})
    rng = np.random.default_rng(0)
    save_preview(CapturePreview(
        frames=rng.integers(0, 256, (frames, height, width, 3), dtype=np.uint8),
        depth=np.full((frames, height, width), 3.0, np.float32), poses=np.repeat(np.eye(4)[None], frames, 0),
        times=(np.arange(frames) / 8.0).astype(np.float32), intrinsics=Intrinsics.from_hfov(width, height).as_dict(),
        fps=8.0, depth_source="bench", source_frames=frames), paths.job_dir)
    ctx.store.update(job, allowed=("queued",), state="succeeded",
                     artefact=str(paths.artefact_dir.relative_to(ctx.settings.data_dir)))
    return job


def _time(client, path: str, params: dict, repeats: int) -> dict:
    client.get(path, params=params).raise_for_status()  # warm: field load, imports
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        client.get(path, params=params).raise_for_status()
        samples.append(1000.0 * (time.perf_counter() - t0))
    return {"median_ms": round(statistics.median(samples), 1),
            "p90_ms": round(float(np.percentile(samples, 90)), 1)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--probes", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args(argv)

    from fastapi.testclient import TestClient

    from jobs.capture_preview import PREVIEW_MAX_HEIGHT
    from service.app import create_app
    from service.config import ServiceSettings
    from service.processes import start_redis

    with tempfile.TemporaryDirectory() as tmp:
        redis = start_redis(Path(tmp) / "redis")
        try:
            app = create_app(ServiceSettings(data_dir=Path(tmp) / "data", broker_url=redis.url))
            with TestClient(app) as client:
                job = _job(app.state.ctx, PREVIEW_MAX_HEIGHT)
                probe = client.get(f"/lightfield/{job}/probe", params={"u": 0.5, "v": 0.5, "t": 1.0}).json()
                points = ";".join(f"{0.15 + 0.7 * i / max(args.probes - 1, 1):.3f},0.5,2.5" for i in range(args.probes))
                x = ",".join(str(v) for v in probe["x"])
                results = {
                    "preview_height": PREVIEW_MAX_HEIGHT,
                    "frame": _time(client, f"/lightfield/{job}/frame", {"t": 1.0}, args.repeats),
                    "probe": _time(client, f"/lightfield/{job}/probe", {"u": 0.3, "v": 0.6, "t": 1.0}, args.repeats),
                    f"insertion_{args.probes}_probes": _time(client, f"/lightfield/{job}/insertion",
                                                             {"t": 1.0, "points": points}, args.repeats),
                    "envmap_png_128": _time(client, f"/lightfield/{job}/envmap",
                                            {"x": x, "t": 1.0, "format": "png", "height": 128}, args.repeats),
                }
        finally:
            redis.stop()
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
