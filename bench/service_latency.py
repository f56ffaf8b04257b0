"""Env map query latency over HTTP vs bare field evaluation (issue 5, "Query speed").

For each field kind (the paper's MLP and the engine's trunk+head, both untrained: latency
does not depend on the weights) an artefact is saved and registered as a succeeded job in
a real stack (redis-server + `lightfield serve` API subprocess; no worker needed). Then,
sequentially from one client:

* bare:  `LightFieldArtefact.envmap` in this process (the floor any server can reach);
* http:  GET /lightfield/{id}/envmap?format=npy, quality=exact and quality=baked (the lattice).

Prints p50 / p99 in milliseconds per (kind, height, path) as JSON.

    python bench/service_latency.py [--reps 60] [--heights 64,128] [--kinds trunk,mlp] [--threads 2]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

TENANT, KEY = "bench", "bench-key-0123456789"


def percentiles(samples_s: list[float]) -> dict:
    ms = sorted(1000.0 * s for s in samples_s)
    p99 = ms[min(len(ms) - 1, math.ceil(0.99 * len(ms)) - 1)]
    return {"p50_ms": round(statistics.median(ms), 2), "p99_ms": round(p99, 2), "n": len(ms)}


def timed(fn, probes: list[str], reps: int) -> dict:
    fn(probes[0])  # warm-up: cache load, allocator, lazy bake
    samples = []
    for i in range(reps):
        t0 = time.perf_counter()
        fn(probes[i % len(probes)])
        samples.append(time.perf_counter() - t0)
    return percentiles(samples)


def make_artefact(kind: str, out: Path) -> Path:
    from core.fields import FieldConfig, SceneBounds, build_field
    from core.fields.stored.artefact import save_artefact

    bounds = SceneBounds((-2.5, -1.5, -4.0), (2.5, 1.5, 0.5), 0.0, 0.0)
    field = build_field(FieldConfig(kind=kind, uses_time=False), bounds)
    return save_artefact(out, field, {"bench": "service_latency"}).path


def register_job(store, data_dir: Path, artefact: Path) -> str:
    """A succeeded job record owning a copy of `artefact` (what a worker would leave)."""
    from jobs.storage import JobPaths, new_job_id
    from jobs.store import JobRecord
    from service.auth import tenant_hash

    job = new_job_id()
    paths = JobPaths.for_job(data_dir, tenant_hash(TENANT), job)
    paths.job_dir.mkdir(parents=True)
    shutil.copytree(artefact, paths.artefact_dir)
    store.create(JobRecord(id=job, tenant=TENANT, tenant_hash=tenant_hash(TENANT), input_kind="image"), 10**6)
    store.update(job, state="succeeded", progress=1.0,
                 artefact=str(paths.artefact_dir.relative_to(data_dir)), finished_at=time.time())
    return job


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=60)
    ap.add_argument("--heights", default="64,128")
    ap.add_argument("--kinds", default="trunk,mlp")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)

    import httpx
    import torch

    from core.fields.stored.artefact import LightFieldArtefact
    from jobs.store import JobStore, connect
    from service.processes import free_port, spawn, start_redis, stop

    torch.set_num_threads(args.threads)
    heights = [int(h) for h in args.heights.split(",")]
    probes = [f"{0.3 * math.cos(k)},{0.2 * math.sin(2 * k)},{-1.0 - 0.2 * k}" for k in range(7)]
    root = Path(tempfile.mkdtemp(prefix="lf-bench-"))
    data_dir = root / "data"
    redis = start_redis(root / "redis")
    api = None
    results: dict = {"threads": args.threads, "reps": args.reps, "cpu_count": os.cpu_count(),
                     "load_average_at_start": [round(v, 2) for v in os.getloadavg()], "rows": []}
    try:
        store = JobStore(connect(redis.url))
        port = free_port()
        env = {**os.environ, "LIGHTFIELD_DATA_DIR": str(data_dir), "LIGHTFIELD_BROKER_URL": redis.url,
               "LIGHTFIELD_API_KEYS": f"{TENANT}:{KEY}", "OMP_NUM_THREADS": str(args.threads)}
        api = spawn([sys.executable, "-m", "cli", "serve", "--port", str(port), "--log-level", "warning"],
                    env=env, log_path=root / "api.log")
        base = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(base + "/healthz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline or api.poll() is not None:
                raise RuntimeError(f"API did not start; see {root / 'api.log'}")
            time.sleep(0.1)
        client = httpx.Client(base_url=base, headers={"Authorization": f"Bearer {KEY}"}, timeout=60)
        for kind in args.kinds.split(","):
            artefact_dir = make_artefact(kind, root / f"artefact-{kind}")
            job = register_job(store, data_dir, artefact_dir)
            art = LightFieldArtefact.load(artefact_dir)
            for h in heights:
                def bare(x: str, h=h):
                    art.envmap([float(v) for v in x.split(",")], 0.0, h)

                def http(x: str, quality: str, h=h):
                    r = client.get(f"/lightfield/{job}/envmap",
                                   params={"x": x, "height": h, "format": "npy", "quality": quality})
                    r.raise_for_status()

                row = {"kind": kind, "height": h, "width": 2 * h,
                       "bare_exact": timed(bare, probes, args.reps),
                       "http_exact": timed(lambda x: http(x, "exact"), probes, args.reps),
                       "http_baked": timed(lambda x: http(x, "baked"), probes, args.reps)}
                row["http_overhead_p50_ms"] = round(row["http_exact"]["p50_ms"] - row["bare_exact"]["p50_ms"], 2)
                results["rows"].append(row)
                print(json.dumps(row), file=sys.stderr)
        client.close()
    finally:
        if api is not None:
            stop(api, signal.SIGTERM, grace_s=10)
        redis.stop()
        shutil.rmtree(root, ignore_errors=True)
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
