"""Drive an embedded `lightfield serve` from Python: start it, run a job through the HTTP API,
download results, stop it cleanly. Used by the embedded-mode test and by `make demo`.

    with EmbeddedService(Path("demo-output/service")) as svc:
        job = svc.submit(Path("room.mp4"), {"preset": "draft"})
        svc.wait(job, on_update=print)
        svc.save_envmap(job, (0.0, 1.2, -2.0), t=0.0, path=Path("env.exr"))
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from jobs.store import TERMINAL_STATES
from service.processes import free_port


class EmbeddedServiceError(RuntimeError):
    """The server did not start, or a request or job failed (the message says which)."""


class EmbeddedService:
    def __init__(self, data_dir: Path, port: int | None = None, env: dict[str, str] | None = None,
                 startup_timeout_s: float = 120.0):
        self.data_dir = Path(data_dir)
        self.port = port or free_port()
        self.base_url = f"http://127.0.0.1:{self.port}"
        self.log_path = self.data_dir / "serve.log"
        self.extra_env = env or {}
        self.startup_timeout_s = startup_timeout_s
        self.proc: subprocess.Popen | None = None
        self._client = None

    # -- lifecycle -------------------------------------------------------------------------
    def start(self) -> "EmbeddedService":
        import httpx  # noqa: PLC0415 — httpx is heavy: imported when used

        self.data_dir.mkdir(parents=True, exist_ok=True)
        env = {k: v for k, v in os.environ.items() if k not in ("LIGHTFIELD_BROKER_URL", "LIGHTFIELD_API_KEYS")}
        env.update(LIGHTFIELD_DATA_DIR=str(self.data_dir.resolve()), **self.extra_env)
        with open(self.log_path, "ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "cli", "serve", "--host", "127.0.0.1", "--port", str(self.port),
                 "--log-level", "warning"], env=env, stdout=log, stderr=subprocess.STDOUT)
        self._client = httpx.Client(base_url=self.base_url, timeout=60)
        deadline = time.monotonic() + self.startup_timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise EmbeddedServiceError(f"lightfield serve exited ({self.proc.returncode}); see {self.log_path}")
            try:
                if self._client.get("/readyz", timeout=5).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        self.stop()
        raise EmbeddedServiceError(f"lightfield serve was not ready within {self.startup_timeout_s:g} s")

    def stop(self, timeout_s: float = 60.0) -> int | None:
        """SIGTERM (the server stops its worker and Redis in order); returns the exit code."""
        if self._client is not None:
            self._client.close()
            self._client = None
        if self.proc is None or self.proc.poll() is not None:
            return None if self.proc is None else self.proc.returncode
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(timeout=10)

    def __enter__(self) -> "EmbeddedService":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def client(self):
        if self._client is None:
            raise EmbeddedServiceError("the service is not running")
        return self._client

    # -- jobs ------------------------------------------------------------------------------
    def submit(self, input_path: Path, params: dict | None = None, depth_path: Path | None = None) -> str:
        files = {"file": (Path(input_path).name, Path(input_path).read_bytes())}
        if depth_path is not None:
            files["depth"] = (Path(depth_path).name, Path(depth_path).read_bytes())
        resp = self.client.post("/jobs", files=files, data={"params": json.dumps(params or {})})
        if resp.status_code != 202:
            raise EmbeddedServiceError(f"POST /jobs: {resp.status_code} {resp.text}")
        return resp.json()["id"]

    def wait(self, job: str, timeout_s: float = 3600.0, on_update: Callable[[dict], None] | None = None) -> dict:
        """Poll until the job ends; returns its final record (raises if it did not succeed)."""
        deadline = time.monotonic() + timeout_s
        version = None
        while time.monotonic() < deadline:
            body = self.client.get(f"/jobs/{job}").json()
            if on_update is not None and body.get("updated_at") != version:
                version = body.get("updated_at")
                on_update(body)
            if body["state"] in TERMINAL_STATES:
                if body["state"] != "succeeded":
                    raise EmbeddedServiceError(f"job {job} {body['state']}: {body.get('error')}")
                return body
            time.sleep(0.25)
        raise EmbeddedServiceError(f"job {job} did not finish within {timeout_s:g} s")

    def envmap(self, job: str, x, t: float = 0.0, height: int = 64, fmt: str = "npy", **query) -> bytes:
        params = {"x": ",".join(f"{float(v):.6g}" for v in x), "t": t, "height": height, "format": fmt, **query}
        resp = self.client.get(f"/lightfield/{job}/envmap", params=params)
        if resp.status_code != 200:
            raise EmbeddedServiceError(f"GET envmap: {resp.status_code} {resp.text}")
        return resp.content

    def save_envmap(self, job: str, x, t: float, path: Path, height: int = 64, **query) -> Path:
        path = Path(path)
        path.write_bytes(self.envmap(job, x, t, height, fmt=path.suffix.lstrip(".").lower(), **query))
        return path
