"""What a shared object store costs a query (issue 47): an API whose light fields live in an
S3-compatible store (moto's S3 server on a loopback port, started here) and a worker on its own
directory, sharing only Redis and the store. For each of several draft jobs:

* first fetch: the API (warmed up by a query on another job: its first query ever pays for
  imports) has never seen the job (nothing on its disk, nothing in memory): the
  query fetches the artefact from the store (verified against each object's SHA-256), loads it
  (verifying its own checksums) and answers;
* disk-warm: the artefact is in the API's local cache but not in memory (LIGHTFIELD_FIELD_CACHE_SIZE=1
  and another job queried in between): load from disk and answer;
* warm: the field is in memory: the ordinary query.

Queries are GET /lightfield/{id}/envmap, 64x128, default quality and format, x at the capture's
camera. Jobs are the draft preset's field (the architecture decides the artefact's size; the
distillation is cut to a few steps to keep the benchmark short).

    python bench/storage_fetch.py [--jobs 3] [--warm 20] [-o bench/results]

Writes storage_fetch.json and storage_fetch.md. Target (issue 47): first fetch of a draft field
over loopback S3 <= 1 s.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if __name__ == "__main__" and not os.environ.get("PYTHONPATH"):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

TARGET_FIRST_FETCH_S = 1.0
QUERY = {"x": "0,0,-1", "height": 64}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=3)
    ap.add_argument("--warm", type=int, default=20)
    ap.add_argument("-o", "--out", type=Path, default=Path("bench/results"))
    args = ap.parse_args(argv)

    import logging

    import boto3
    import httpx

    logging.getLogger("werkzeug").setLevel(logging.ERROR)  # moto's request log
    from moto.server import ThreadedMotoServer

    import bench.hostile_inputs as h
    from service.processes import free_port, spawn, start_redis, stop, worker_command

    repo = Path(__file__).resolve().parents[1]
    root = Path(tempfile.mkdtemp(prefix="storage-fetch-"))
    s3_port = free_port()
    s3 = ThreadedMotoServer(ip_address="127.0.0.1", port=s3_port, verbose=False)
    s3.start()
    aws = {"AWS_ACCESS_KEY_ID": "bench", "AWS_SECRET_ACCESS_KEY": "bench", "AWS_DEFAULT_REGION": "us-east-1",
           "AWS_ENDPOINT_URL": f"http://127.0.0.1:{s3_port}"}
    client = boto3.client("s3", endpoint_url=aws["AWS_ENDPOINT_URL"], aws_access_key_id="bench",
                          aws_secret_access_key="bench", region_name="us-east-1")
    client.create_bucket(Bucket="bench")
    redis = start_redis(root / "redis")
    base = {**os.environ, **aws, "PYTHONPATH": str(repo), "OMP_NUM_THREADS": "2",
            "LIGHTFIELD_BROKER_URL": redis.url, "LIGHTFIELD_STORAGE_URL": "s3://bench/jobs",
            "LIGHTFIELD_FIELD_CACHE_SIZE": "1",
            "LIGHTFIELD_DISTILL_OVERRIDES": json.dumps({"iterations": 8, "work_height": 24, "warmup_steps": 1})}
    worker = spawn(
        worker_command("bench", loglevel="WARNING"),
        env={**base, "LIGHTFIELD_DATA_DIR": str(root / "worker")},
        log_path=root / "worker.log",
    )
    port = free_port()
    api = spawn([sys.executable, "-m", "cli", "serve", "--port", str(port), "--log-level", "warning"],
                env={**base, "LIGHTFIELD_DATA_DIR": str(root / "api")}, log_path=root / "api.log")
    url = f"http://127.0.0.1:{port}"
    result = {"when": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": platform.processor() or platform.machine(),
              "cpu_count": os.cpu_count(), "load_average_start": [round(v, 2) for v in os.getloadavg()],
              "commit": subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], capture_output=True,
                                       text=True).stdout.strip(), "target_first_fetch_s": TARGET_FIRST_FETCH_S}
    try:
        with httpx.Client(base_url=url, timeout=120) as c:
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                try:
                    if c.get("/readyz").status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                time.sleep(0.3)
            image = h.png_bytes(160, 120)
            jobs = []
            for _ in range(args.jobs + 1):  # one at a time: the per-tenant limit is 4
                job = c.post(
                    "/jobs", files={"file": ("room.png", image)}, data={"params": '{"preset": "draft"}'}
                ).json()["id"]
                while (state := c.get(f"/jobs/{job}").json()["state"]) in ("queued", "running"):
                    time.sleep(0.3)
                assert state == "succeeded", (state, (root / "worker.log").read_text()[-2000:])
                jobs.append(job)
            sizes = {}
            for job in jobs:
                objects = [o for o in client.list_objects_v2(Bucket="bench", Prefix="jobs/artefacts/")["Contents"]
                           if f"/{job}/lightfield/" in o["Key"]]
                sizes[job] = {o["Key"].rsplit("/", 1)[-1]: o["Size"] for o in objects}

            def timed(job: str) -> float:
                t0 = time.perf_counter()
                resp = c.get(f"/lightfield/{job}/envmap", params=QUERY)
                elapsed = time.perf_counter() - t0
                assert resp.status_code == 200, resp.text
                return elapsed

            timed(jobs.pop(0))  # the API process's first query ever (imports, first field build) is not a fetch's cost
            first = [timed(job) for job in jobs]  # each: never on the API's disk, not in memory
            disk = []
            for i, job in enumerate(jobs):  # cache size 1: querying another job evicted this one from memory
                timed(jobs[(i + 1) % len(jobs)])
                disk.append(timed(job))
            warm = [timed(jobs[0]) for _ in range(args.warm + 1)][1:]
    finally:
        stop(api, signal.SIGTERM, grace_s=10)
        stop(worker, signal.SIGQUIT, grace_s=5)
        redis.stop()
        s3.stop()
    result.update({
        "jobs": len(jobs), "artefact_bytes": sizes[jobs[0]], "query": QUERY,
        "first_fetch_s": [round(v, 4) for v in first], "disk_warm_s": [round(v, 4) for v in disk],
        "warm_s": {"n": len(warm), "p50": round(statistics.median(warm), 4), "max": round(max(warm), 4)},
        "load_average_end": [round(v, 2) for v in os.getloadavg()],
    })
    met = max(first) <= TARGET_FIRST_FETCH_S
    md = "\n".join(
        [
            "# First fetch from the object store vs warm queries (`bench/storage_fetch.py`)",
            "",
            f"Generated {result['when']} on {result['machine']} ({result['cpu_count']} CPUs), commit "
            f"{result['commit']}; "
            f"load average at start {result['load_average_start']}, at end {result['load_average_end']}. moto's S3 "
            "server on loopback; API and worker on separate directories sharing only Redis and the store.",
            "",
            "Artefact of a draft field in the store: "
            f"{', '.join(f'{k} {v} B' for k, v in sorted(result['artefact_bytes'].items()))}.",
            "",
            "| query (64x128 env map, default quality) | seconds |",
            "|---|---|",
            f"| first fetch (not on the API's disk, not in memory), {len(first)} jobs | "
            f"{', '.join(str(v) for v in result['first_fetch_s'])} |",
            "| disk-warm (in the API's local cache, not in memory) | "
            f"{', '.join(str(v) for v in result['disk_warm_s'])} |",
            f"| warm (in memory), p50 / max of {len(warm)} | {result['warm_s']['p50']} / {result['warm_s']['max']} |",
            "",
            f"Target: first fetch <= {TARGET_FIRST_FETCH_S} s: {'met' if met else '**missed**'} (worst "
            f"{max(first):.3f} s).",
            "",
        ]
    )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "storage_fetch.json").write_text(json.dumps(result, indent=2) + "\n")
    (args.out / "storage_fetch.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
