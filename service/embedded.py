"""`lightfield serve`: the API, plus (with no broker configured) its own Redis and worker.

Embedded mode (no LIGHTFIELD_BROKER_URL): start a private Redis (loopback, random password,
AOF in <data_dir>/redis), one Celery worker subprocess (restarted if it dies) and uvicorn in
this process; on SIGINT/SIGTERM uvicorn stops first, then the worker (warm shutdown, its
unfinished job stays in the queue and resumes from its checkpoint next time), then Redis.
Distributed mode (LIGHTFIELD_BROKER_URL=redis://...): only the API; run `lightfield worker`
anywhere that reaches the same Redis and storage root.
"""
from __future__ import annotations

import logging
import os
import signal
import subprocess
import threading
from dataclasses import dataclass, field
from pathlib import Path

from service.auth import KeyRing, require_loopback
from service.config import ServiceSettings
from service.processes import RedisProcess, child_env, spawn, start_redis, stop, worker_command

log = logging.getLogger("lightfield.serve")
WORKER_GRACE_S = 20.0
RESTART_BACKOFF_S = 2.0


@dataclass
class WorkerSupervisor:
    """Keeps one worker subprocess alive until stopped."""

    env: dict[str, str]
    log_path: Path
    proc: subprocess.Popen | None = None
    _stopping: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def start(self) -> None:
        self.proc = spawn(worker_command("embedded"), env=self.env, log_path=self.log_path)
        self._thread = threading.Thread(target=self._watch, name="worker-supervisor", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        while not self._stopping.wait(RESTART_BACKOFF_S):
            if self.proc is not None and self.proc.poll() is not None:
                log.warning("worker exited with %s; restarting (see %s)", self.proc.returncode, self.log_path)
                self.proc = spawn(worker_command("embedded"), env=self.env, log_path=self.log_path)

    def stop(self) -> None:
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        if self.proc is not None:
            stop(self.proc, signal.SIGTERM, grace_s=WORKER_GRACE_S)


def serve(host: str, port: int, settings: ServiceSettings, log_level: str = "info") -> int:
    import uvicorn

    require_loopback(host, KeyRing.parse(settings.api_keys))
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    redis_proc: RedisProcess | None = None
    supervisor: WorkerSupervisor | None = None
    # uvicorn re-raises the signal that stopped it once it has shut down; with the default
    # handlers that would kill this process before the children are stopped in order.
    received: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: received.append(signum))
    try:
        if not settings.broker_url:
            redis_proc = start_redis(settings.data_dir / "redis")
            os.environ["LIGHTFIELD_BROKER_URL"] = redis_proc.url
            os.environ["LIGHTFIELD_DATA_DIR"] = str(settings.data_dir.resolve())
            settings = settings.model_copy(update={"broker_url": redis_proc.url})
            supervisor = WorkerSupervisor(child_env(), settings.data_dir / "worker.log")
            supervisor.start()
            log.info("embedded mode: Redis and one worker started (logs in %s)", settings.data_dir)
        from service.app import create_app

        if received:  # asked to stop while starting up
            return 0
        config = uvicorn.Config(create_app(settings), host=host, port=port, log_level=log_level,
                                timeout_graceful_shutdown=5)
        uvicorn.Server(config).run()  # handles SIGINT/SIGTERM itself and returns
        return 0
    finally:
        if supervisor is not None:
            supervisor.stop()
        if redis_proc is not None:
            redis_proc.stop()
