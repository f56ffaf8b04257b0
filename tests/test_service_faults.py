"""Fault injection against the embedded service (`lightfield serve` with its own Redis and
worker, real processes): kill -9 of the worker and of Redis mid-job, SIGTERM and restart,
bounded restarts of a crash-looping child, and the keyless server's Host/Origin checks.

What must hold (issue 14): the supervisor restarts a dead child (logged), /healthz reports
the dead dependency meanwhile, requests during a Redis outage are 503 broker_unavailable
with Retry-After (never 500), and every job still ends `succeeded`, resumed from its
checkpoint, well within the 10-minute visibility timeout (the dead worker's job is re-queued
at once). Jobs are short draft runs that checkpoint every 2 steps.
"""
from __future__ import annotations

import json
import shutil
import signal
import time

import httpx
import psutil
import pytest

from conftest import REPO, SHORT_TIMEOUTS, wait_until

pytestmark = pytest.mark.slow

DISTILL = json.dumps({"iterations": 48, "checkpoint_every": 2, "work_height": 24, "warmup_steps": 2})
TERMINAL = ("succeeded", "failed", "cancelled")


@pytest.fixture(scope="module")
def embedded(tmp_path_factory):
    from service.local import EmbeddedService

    data = tmp_path_factory.mktemp("faults") / "data"
    env = {"LIGHTFIELD_DISTILL_OVERRIDES": DISTILL, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1",
           **SHORT_TIMEOUTS}
    svc = EmbeddedService(data, env=env).start()
    try:
        yield svc
    finally:
        svc.stop()


def child(svc, needle: str) -> psutil.Process:
    for proc in psutil.Process(svc.proc.pid).children(recursive=True):
        if needle in " ".join(proc.cmdline()):
            return proc
    raise AssertionError(f"no child matching {needle!r}")


def submit_and_wait_for_checkpoint(svc, tiny_image) -> str:
    job = svc.submit(tiny_image)
    wait_until(lambda: list(svc.data_dir.glob(f"artefacts/*/{job}/checkpoint/*.json")), 120, interval_s=0.05,
               what="a checkpoint")
    return job


def final_state(svc, job: str, timeout_s: float = 240) -> dict:
    def done():
        try:
            resp = svc.client.get(f"/jobs/{job}", timeout=5)
        except httpx.HTTPError:
            return None
        if resp.status_code != 200:
            return None
        body = resp.json()
        return body if body["state"] in TERMINAL else None

    return wait_until(done, timeout_s, interval_s=0.25, what=f"job {job} to end")


def watch_health(svc, until, timeout_s: float = 30) -> list[tuple[int, str]]:
    """Poll /healthz every 20 ms until `until()`; returns (status, code) of each answer."""
    seen, deadline = [], time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            resp = svc.client.get("/healthz", timeout=2)
            seen.append((resp.status_code, resp.json().get("error", {}).get("code", "")))
        except httpx.HTTPError:
            seen.append((0, "no answer"))
        if until():
            return seen
        time.sleep(0.02)
    raise AssertionError(f"condition not reached within {timeout_s} s; /healthz said {seen[-5:]}")


def replaced(svc, needle: str, old_pid: int) -> bool:
    try:
        return child(svc, needle).pid != old_pid
    except (AssertionError, psutil.Error):
        return False


def healthy(svc) -> bool:
    try:
        return svc.client.get("/healthz", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def test_kill_9_of_the_worker_mid_job_restarts_it_and_the_job_resumes_at_once(embedded, tiny_image):
    svc = embedded
    job = submit_and_wait_for_checkpoint(svc, tiny_image)
    worker = child(svc, "celery")
    t0 = time.monotonic()
    worker.send_signal(signal.SIGKILL)
    worker.wait(timeout=10)
    seen = watch_health(svc, lambda: healthy(svc) and replaced(svc, "celery", worker.pid))
    assert (503, "dependency_down") in seen, seen  # a liveness probe notices
    final = final_state(svc, job)
    assert final["state"] == "succeeded", final
    assert final["attempts"] == 2 and final["resumed"] is True
    assert time.monotonic() - t0 < 200  # re-queued at the restart, not after the 600 s visibility timeout
    log = (svc.data_dir / "serve.log").read_text()
    assert "embedded worker exited" in log and "embedded worker restarted" in log and "re-queued" in log


def test_kill_9_of_redis_mid_job_is_503_then_recovers_and_the_job_finishes(embedded, tiny_image):
    svc = embedded
    job = submit_and_wait_for_checkpoint(svc, tiny_image)
    redis = child(svc, "redis-server")
    redis.send_signal(signal.SIGKILL)
    redis.wait(timeout=10)
    answers = []

    def recovered() -> bool:
        try:
            resp = svc.client.get("/jobs", timeout=5)
        except httpx.HTTPError:
            return False
        answers.append((resp.status_code, resp.json().get("error", {}).get("code"), resp.headers.get("retry-after")))
        return resp.status_code == 200 and healthy(svc)

    seen = watch_health(svc, recovered)
    assert (503, "dependency_down") in seen, seen
    assert all(s == 200 or (s == 503 and c == "broker_unavailable" and int(r) > 0) for s, c, r in answers), answers
    final = final_state(svc, job)
    assert final["state"] == "succeeded", final
    log = (svc.data_dir / "serve.log").read_text()
    assert "embedded redis exited" in log and "embedded redis restarted" in log


def test_sigterm_mid_job_then_restart_resumes_the_job(embedded, tiny_image):
    svc = embedded
    job = submit_and_wait_for_checkpoint(svc, tiny_image)
    children = psutil.Process(svc.proc.pid).children(recursive=True)
    assert svc.stop() == 0
    _, alive = psutil.wait_procs(children, timeout=30)
    assert not alive
    svc.start()
    final = final_state(svc, job)
    # the warm shutdown may let the run finish (1 attempt); else the next start re-queues it at
    # once and it resumes from its checkpoint (or records the artefact its first run saved)
    assert final["state"] == "succeeded" and final["attempts"] <= 2, final
    assert "Traceback" not in (svc.data_dir / "serve.log").read_text()


def test_keyless_server_refuses_foreign_hosts_and_cross_site_posts(embedded, tiny_image):
    """Issue: a keyless loopback server accepted POST /jobs with Host: attacker.example and a
    foreign Origin (DNS rebinding, cross-site form posts)."""
    base = embedded.base_url
    files = {"file": ("room.png", tiny_image.read_bytes())}

    def refused(resp, status, code):
        assert resp.status_code == status, resp.text
        assert resp.json()["error"]["code"] == code

    with httpx.Client(base_url=base, timeout=30) as c:
        refused(c.post("/jobs", files=files, headers={"Host": "attacker.example"}), 400, "host_not_allowed")
        refused(c.get("/jobs", headers={"Host": "attacker.example:8000"}), 400, "host_not_allowed")
        refused(c.post("/jobs", files=files, headers={"Origin": "http://attacker.example"}), 403, "origin_not_allowed")
        refused(c.post("/jobs", files=files, headers={"Origin": "null"}), 403, "origin_not_allowed")
        refused(c.delete("/jobs/6f1c7c1e-3d0b-4c55-9a2f-0d8f2b7c1a11", headers={"Sec-Fetch-Site": "cross-site"}),
                403, "origin_not_allowed")
        assert c.get("/healthz", headers={"Host": "localhost:1234"}).status_code == 200
        own = c.post("/jobs", files=files, headers={"Origin": base})  # the page this server serves
        assert own.status_code == 202, own.text
        assert c.delete(f"/jobs/{own.json()['id']}").status_code in (202, 204)  # no Origin: curl, scripts


def test_a_crash_looping_child_is_restarted_a_bounded_number_of_times(tmp_path, caplog):
    """Real processes that exit at once: restarted with backoff, then given up on (failed),
    which /healthz turns into a 503."""
    from service.processes import spawn, stop
    from service.supervisor import Child, Supervisor

    starts = []

    def start():
        starts.append(time.monotonic())
        return spawn([shutil.which("false")])  # exits 1 at once

    sup = Supervisor([Child("flaky", start=start, stop=lambda p: stop(p), max_restarts=3, window_s=60)])
    sup.start()
    try:
        wait_until(lambda: sup.states()["flaky"] == "failed", 30, what="the supervisor to give up")
        time.sleep(1.0)
        assert len(starts) == 4  # the first start + 3 restarts, then no more
        gaps = [b - a for a, b in zip(starts, starts[1:])]
        assert gaps == sorted(gaps)  # backing off
    finally:
        sup.stop()
    assert "not restarting it again" in caplog.text


def test_healthz_is_503_when_a_supervised_dependency_is_down(tmp_path):
    from service.app import create_app
    from service.config import ServiceSettings
    from service.processes import start_redis

    redis = start_redis(tmp_path / "redis")
    states = {"redis": "running", "worker": "running"}
    try:
        import asyncio

        app = create_app(ServiceSettings(data_dir=tmp_path / "data", broker_url=redis.url),
                         dependency_states=lambda: dict(states))

        async def get():
            transport = httpx.ASGITransport(app=app)
            async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as c:
                return await c.get("/healthz")

        ok = asyncio.run(get())
        assert ok.status_code == 200 and ok.json()["dependencies"] == states
        states["worker"] = "failed"
        down = asyncio.run(get())
        assert down.status_code == 503 and down.json()["error"]["code"] == "dependency_down"
        assert "worker is failed" in down.json()["error"]["message"] and "retry-after" in down.headers
    finally:
        redis.stop()
