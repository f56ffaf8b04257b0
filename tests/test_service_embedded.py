"""`lightfield serve` with no configuration: it starts its own Redis and worker, runs a job,
shuts every child down on SIGTERM, and a restart on the same data dir still knows the job."""
from __future__ import annotations

import io
import os
import signal
import subprocess
import sys

import httpx
import numpy as np
import psutil
import pytest

from conftest import FAST_DISTILL, REPO, wait_until

pytestmark = pytest.mark.slow


def _serve(data_dir, port: int, log_path, host: str = "127.0.0.1") -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items()
           if k not in ("LIGHTFIELD_BROKER_URL", "LIGHTFIELD_API_KEYS")}
    env.update(LIGHTFIELD_DATA_DIR=str(data_dir), LIGHTFIELD_DISTILL_OVERRIDES=FAST_DISTILL, PYTHONPATH=str(REPO),
               OMP_NUM_THREADS="1")
    with open(log_path, "ab") as log:
        return subprocess.Popen([sys.executable, "-m", "cli", "serve", "--host", host, "--port", str(port),
                                 "--log-level", "warning"], env=env, stdout=log, stderr=subprocess.STDOUT,
                                cwd=REPO)


def _stop_and_check_children(proc: subprocess.Popen) -> None:
    children = psutil.Process(proc.pid).children(recursive=True)
    assert len(children) >= 2  # redis-server + the Celery worker
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=60) == 0
    gone, alive = psutil.wait_procs(children, timeout=30)
    assert not alive, f"leaked children: {alive}"


def test_embedded_serve_runs_a_job_and_restarts_with_its_records(tmp_path, tiny_image):
    from service.processes import free_port

    data = tmp_path / "data"
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    proc = _serve(data, port, tmp_path / "serve.log")
    try:
        wait_until(lambda: httpx.get(base + "/readyz", timeout=5).status_code == 200, 90, interval_s=0.2,
                   what="embedded API + worker ready")
        with httpx.Client(base_url=base, timeout=30) as c:  # no keys: the 'local' tenant, no header
            created = c.post("/jobs", files={"file": ("room.png", tiny_image.read_bytes())})
            assert created.status_code == 202, created.text
            job = created.json()["id"]
            final = wait_until(lambda: (b := c.get(f"/jobs/{job}").json())["state"] in
                               ("succeeded", "failed", "cancelled") and b, 120, interval_s=0.2, what="job done")
            assert final["state"] == "succeeded", (tmp_path / "serve.log").read_text()[-3000:]
            exact = c.get(f"/lightfield/{job}/envmap", params={"x": "0,0,-1", "height": 8, "format": "npy"})
            assert exact.status_code == 200
            for fmt in ("exr", "png", "hdr"):
                assert c.get(f"/lightfield/{job}/envmap", params={"x": "0,0,-1", "height": 8,
                                                                  "format": fmt}).status_code == 200
        assert (data / "redis" / "appendonly.aof").stat().st_size > 0  # records are persisted
        _stop_and_check_children(proc)

        proc = _serve(data, port, tmp_path / "serve2.log")
        wait_until(lambda: httpx.get(base + "/healthz", timeout=5).status_code == 200, 90, interval_s=0.2,
                   what="restarted API")
        with httpx.Client(base_url=base, timeout=30) as c:
            again = c.get(f"/jobs/{job}")
            assert again.status_code == 200 and again.json()["state"] == "succeeded"
            assert job in [j["id"] for j in c.get("/jobs").json()["jobs"]]
            same = c.get(f"/lightfield/{job}/envmap", params={"x": "0,0,-1", "height": 8, "format": "npy"})
            np.testing.assert_array_equal(np.load(io.BytesIO(same.content)), np.load(io.BytesIO(exact.content)))
        _stop_and_check_children(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)


def test_serve_without_keys_refuses_a_public_bind(tmp_path):
    from service.processes import free_port

    proc = _serve(tmp_path / "data", free_port(), tmp_path / "serve.log", host="0.0.0.0")
    assert proc.wait(timeout=60) == 2
    log = (tmp_path / "serve.log").read_text()
    assert "LIGHTFIELD_API_KEYS" in log and "0.0.0.0" in log
    assert not (tmp_path / "data" / "redis").exists()  # refused before starting anything
