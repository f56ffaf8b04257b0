"""Shared fixtures. The service fixtures start REAL processes (redis-server, Celery workers,
uvicorn) on free ports with a temporary data dir, and always tear them down (bounded waits,
SIGKILL as the last resort; children also carry a parent-death signal)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]

pytest_plugins = ["diffusion_fixtures", "node_consumers"]  # lazy: builds/installs nothing unless a test asks

TENANTS = {"alice": "alice-key-0001", "bob": "bob-key-00002"}

# Tiny, fast jobs: the engine's draft preset cut down to a few steps, checkpointing often so
# a killed worker's job has something to resume from.
FAST_DISTILL = '{"iterations": 24, "checkpoint_every": 4, "work_height": 24, "warmup_steps": 2}'
# Client timeouts short enough that slow-client tests take seconds (defaults: 10 s headers, ...)
SHORT_TIMEOUTS = {"LIGHTFIELD_HEADER_TIMEOUT": "2", "LIGHTFIELD_BODY_TIMEOUT": "3", "LIGHTFIELD_BODY_GRACE": "2",
                  "LIGHTFIELD_MIN_BODY_RATE": "200", "LIGHTFIELD_KEEP_ALIVE": "2"}


def wait_until(predicate, timeout_s: float, interval_s: float = 0.05, what: str = "condition"):
    """Poll `predicate` until it returns a truthy value (returned) or fail after timeout_s."""
    deadline = time.monotonic() + timeout_s
    last_exc = None
    while time.monotonic() < deadline:
        try:
            value = predicate()
            if value:
                return value
        except Exception as exc:  # e.g. connection refused while a server starts
            last_exc = exc
        time.sleep(interval_s)
    raise TimeoutError(f"timed out after {timeout_s} s waiting for {what} (last error: {last_exc!r})")


@dataclass
class ServiceStack:
    """Redis + N Celery workers + a uvicorn API, all real subprocesses."""

    root: Path
    extra_env: dict[str, str] = field(default_factory=dict)
    redis: object = None
    api: subprocess.Popen | None = None
    workers: list[subprocess.Popen] = field(default_factory=list)
    port: int = 0

    @property
    def data_dir(self) -> Path:
        return self.root / "data"

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def env(self) -> dict[str, str]:
        env = dict(os.environ)
        env.update({
            "LIGHTFIELD_DATA_DIR": str(self.data_dir),
            "LIGHTFIELD_BROKER_URL": self.redis.url,
            "LIGHTFIELD_API_KEYS": ",".join(f"{t}:{k}" for t, k in TENANTS.items()),
            "LIGHTFIELD_VISIBILITY_TIMEOUT": "4",
            "LIGHTFIELD_LEASE_TTL": "3",
            "LIGHTFIELD_READINESS_TIMEOUT": "2",
            "LIGHTFIELD_DISTILL_OVERRIDES": FAST_DISTILL,
            "OMP_NUM_THREADS": "1",
            "PYTHONPATH": str(REPO),
            **SHORT_TIMEOUTS,
        })
        env.update(self.extra_env)
        return env

    def start(self, workers: int = 1) -> "ServiceStack":
        from service.processes import start_redis

        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.redis = start_redis(self.root / "redis")
        for _ in range(workers):
            self.start_worker()
        self.start_api()
        return self

    def start_worker(self) -> subprocess.Popen:
        from service.processes import spawn, worker_command

        n = len(self.workers)
        proc = spawn(worker_command(f"w{n}", loglevel="INFO"), env=self.env(), log_path=self.root / f"worker{n}.log")
        self.workers.append(proc)
        return proc

    def start_api(self) -> None:
        from service.processes import free_port, spawn

        self.port = free_port()
        cmd = [sys.executable, "-m", "cli", "serve", "--host", "127.0.0.1", "--port", str(self.port),
               "--log-level", "warning"]
        self.api = spawn(cmd, env=self.env(), log_path=self.root / "api.log")
        wait_until(self._healthy, 30, what=f"API health (log: {self.root / 'api.log'})")

    def _healthy(self) -> bool:
        import httpx

        if self.api.poll() is not None:
            raise RuntimeError(f"API exited: {self.log('api')}")
        return httpx.get(self.base_url + "/healthz", timeout=1).status_code == 200

    def stop_api(self) -> None:
        from service.processes import stop

        if self.api is not None:
            stop(self.api, signal.SIGTERM, grace_s=10)
            self.api = None

    def wait_ready(self, timeout_s: float = 60) -> None:
        import httpx

        wait_until(lambda: httpx.get(self.base_url + "/readyz", timeout=5).status_code == 200, timeout_s,
                   interval_s=0.2, what="a worker answering /readyz")

    def client(self, tenant: str = "alice", **kw):
        import httpx

        return httpx.Client(base_url=self.base_url, timeout=30,
                            headers={"Authorization": f"Bearer {TENANTS[tenant]}"}, **kw)

    def log(self, name: str) -> str:
        path = self.root / f"{name}.log"
        return path.read_text(errors="replace")[-4000:] if path.exists() else ""

    def stop(self) -> None:
        from service.processes import stop

        self.stop_api()
        for proc in self.workers:  # cold shutdown: tests keep nothing a warm one would save
            stop(proc, signal.SIGQUIT, grace_s=5)
        if self.redis is not None:
            self.redis.stop()


@contextmanager
def running_stack(root: Path, extra_env: dict[str, str] | None = None, workers: int = 1):
    """A started stack whose workers answer /readyz, stopped on exit whatever happens."""
    stack = ServiceStack(root, extra_env=dict(extra_env or {}))
    try:
        stack.start(workers=workers)
        stack.wait_ready()
        yield stack
    finally:
        stack.stop()


@pytest.fixture(scope="session")
def service_stack(tmp_path_factory):
    """One stack for the whole session (tests that break things build their own)."""
    with running_stack(tmp_path_factory.mktemp("stack")) as stack:
        yield stack


@pytest.fixture(scope="session")
def finished_job(service_stack, tiny_image) -> str:
    """A job of tenant alice on the session stack that ran to the end (a real draft
    distillation, cut short by FAST_DISTILL), with its bake and UI preview."""
    with service_stack.client("alice") as c:
        resp = c.post("/jobs", files={"file": ("room.png", tiny_image.read_bytes())})
        assert resp.status_code == 202, resp.text
        job = resp.json()["id"]

        def ended():
            body = c.get(f"/jobs/{job}").json()
            return body if body["state"] in ("succeeded", "failed", "cancelled") else None

        final = wait_until(ended, 180, interval_s=0.2, what="the job")
    assert final["state"] == "succeeded", (final, service_stack.log("worker0"))
    return job


@pytest.fixture
def make_stack(tmp_path):
    """Factory for stacks a test controls fully (kill workers, restart the API, ...)."""
    stacks: list[ServiceStack] = []

    def make(workers: int = 1, **extra_env) -> ServiceStack:
        stack = ServiceStack(tmp_path / f"stack{len(stacks)}", extra_env=extra_env)
        stacks.append(stack)
        return stack.start(workers=workers)

    try:
        yield make
    finally:
        for stack in stacks:
            stack.stop()


def room_frames(t: int = 1, h: int = 48, w: int = 64) -> np.ndarray:
    """Float frames [T, H, W, 3]: a lit wall gradient with a bright window that dims over time."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    base = 0.25 + 0.35 * (yy / h)[..., None] * np.array([1.0, 0.9, 0.8], np.float32)
    frames = []
    for k in range(t):
        img = np.broadcast_to(base, (h, w, 3)).copy()
        window = (np.abs(xx - w * 0.7) < w * 0.1) & (yy < h * 0.35)
        img[window] = 1.0 - 0.3 * k / max(t - 1, 1)
        frames.append(img)
    return np.stack(frames)


@pytest.fixture(scope="session")
def tiny_image(tmp_path_factory) -> Path:
    from core.io.images import write_png

    return write_png(tmp_path_factory.mktemp("media") / "room.png", room_frames(1)[0])


@pytest.fixture(scope="session")
def tiny_video(tmp_path_factory) -> Path:
    from core.io.video import write_video

    return write_video(tmp_path_factory.mktemp("media") / "room.mp4", room_frames(6), fps=6.0)


@dataclass
class S3Server:
    """moto's S3-API server: a real HTTP server speaking S3, on a loopback port."""

    endpoint: str
    bucket: str = "lightfield-test"

    @property
    def env(self) -> dict[str, str]:
        """The standard AWS variables a client (boto3, the service) reads."""
        return {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
                "AWS_DEFAULT_REGION": "us-east-1", "AWS_ENDPOINT_URL": self.endpoint}

    def client(self):
        import boto3

        return boto3.client("s3", endpoint_url=self.endpoint, aws_access_key_id="testing",
                            aws_secret_access_key="testing", region_name="us-east-1")

    def keys(self, prefix: str = "") -> list[str]:
        pages = self.client().get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=prefix)
        return [o["Key"] for page in pages for o in page.get("Contents", [])]


@pytest.fixture(scope="session")
def s3_server():
    """moto in server mode (Flask in a thread of the test process; the service's processes reach
    it over HTTP like any S3 endpoint) on a free loopback port, with one bucket."""
    from moto.server import ThreadedMotoServer

    from service.processes import free_port

    port = free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    s3 = S3Server(f"http://127.0.0.1:{port}")
    try:
        wait_until(lambda: s3.client().list_buckets() is not None, 30, what="the moto server")
        s3.client().create_bucket(Bucket=s3.bucket)
        yield s3
    finally:
        server.stop()
