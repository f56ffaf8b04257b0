"""`lightfield serve` with no configuration: it starts its own Redis and worker, runs a job,
shuts every child down on SIGTERM, and a restart on the same data dir still knows the job."""
from __future__ import annotations

import io
import os
import subprocess
import sys

import numpy as np
import psutil
import pytest

from conftest import FAST_DISTILL, REPO

pytestmark = pytest.mark.slow


def _stop_and_check_children(svc) -> None:
    children = psutil.Process(svc.proc.pid).children(recursive=True)
    assert len(children) >= 2  # redis-server + the Celery worker
    assert svc.stop() == 0
    gone, alive = psutil.wait_procs(children, timeout=30)
    assert not alive, f"leaked children: {alive}"


def test_embedded_serve_runs_a_job_and_restarts_with_its_records(tmp_path, tiny_image):
    from service.local import EmbeddedService

    data = tmp_path / "data"
    env = {"LIGHTFIELD_DISTILL_OVERRIDES": FAST_DISTILL, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    svc = EmbeddedService(data, env=env).start()
    try:
        job = svc.submit(tiny_image)  # no keys: the 'local' tenant, no Authorization header
        updates = []
        final = svc.wait(job, timeout_s=120, on_update=updates.append)
        assert final["state"] == "succeeded" and updates[-1]["state"] == "succeeded"
        exact = svc.envmap(job, (0, 0, -1), height=8, fmt="npy")
        for fmt in ("exr", "png", "hdr"):
            assert svc.save_envmap(job, (0, 0, -1), 0.0, tmp_path / f"env.{fmt}", height=8).stat().st_size > 0
        # records are persisted: Redis 6 writes appendonly.aof, Redis 7 a multi-part appendonlydir/
        aof = [f for f in (data / "redis").rglob("appendonly*") if f.is_file()]
        assert sum(f.stat().st_size for f in aof) > 0, sorted(p.name for p in (data / "redis").rglob("*"))
        _stop_and_check_children(svc)

        svc = EmbeddedService(data, port=svc.port, env=env).start()
        again = svc.client.get(f"/jobs/{job}")
        assert again.status_code == 200 and again.json()["state"] == "succeeded"
        assert job in [j["id"] for j in svc.client.get("/jobs").json()["jobs"]]
        same = svc.envmap(job, (0, 0, -1), height=8, fmt="npy")
        np.testing.assert_array_equal(np.load(io.BytesIO(same)), np.load(io.BytesIO(exact)))
        _stop_and_check_children(svc)
    finally:
        svc.stop()


def _serve(data_dir, port: int, log_path, host: str) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k not in ("LIGHTFIELD_BROKER_URL", "LIGHTFIELD_API_KEYS")}
    env.update(LIGHTFIELD_DATA_DIR=str(data_dir), PYTHONPATH=str(REPO))
    with open(log_path, "ab") as log:
        return subprocess.Popen([sys.executable, "-m", "cli", "serve", "--host", host, "--port", str(port)],
                                env=env, stdout=log, stderr=subprocess.STDOUT, cwd=REPO)


def test_serve_without_keys_refuses_a_public_bind(tmp_path):
    from service.processes import free_port

    proc = _serve(tmp_path / "data", free_port(), tmp_path / "serve.log", host="0.0.0.0")
    assert proc.wait(timeout=60) == 2
    log = (tmp_path / "serve.log").read_text()
    assert "LIGHTFIELD_API_KEYS" in log and "0.0.0.0" in log
    assert not (tmp_path / "data" / "redis").exists()  # refused before starting anything
