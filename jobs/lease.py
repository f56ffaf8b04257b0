"""A job's run lease: held while a worker runs it, renewed by a heartbeat thread.

The lease (Redis SET NX PX) is what makes "never runs twice concurrently" true when the
broker re-delivers a job whose worker is only slow, not dead. A thread renews it every
ttl/3 instead of the engine's progress callback, because one engine step (a diffusion
prior call on CPU) can take longer than any reasonable ttl; if the process dies, so does
the thread and the lease expires after ttl.
"""
from __future__ import annotations

import logging
import threading
import uuid

from jobs.store import JobStore

log = logging.getLogger("lightfield.worker")


class RunLease:
    def __init__(self, store: JobStore, job_id: str, ttl_s: float):
        self.store, self.job_id, self.ttl_s = store, job_id, ttl_s
        self.token = uuid.uuid4().hex
        self.lost = threading.Event()  # set when a renewal finds the lease gone
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def acquire(self) -> bool:
        if not self.store.acquire_lease(self.job_id, self.token, self.ttl_s):
            return False
        self._thread = threading.Thread(target=self._heartbeat, name=f"lease-{self.job_id[:8]}", daemon=True)
        self._thread.start()
        return True

    def _heartbeat(self) -> None:
        while not self._stop.wait(self.ttl_s / 3.0):
            try:
                if not self.store.renew_lease(self.job_id, self.token, self.ttl_s):
                    log.warning("job %s: run lease lost; stopping this run", self.job_id)
                    self.lost.set()
                    return
            except Exception:  # a Redis blip: try again next beat, the ttl leaves room
                log.warning("job %s: lease renewal failed", self.job_id, exc_info=True)

    def release(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        try:
            self.store.release_lease(self.job_id, self.token)
        except Exception:
            log.warning("job %s: could not release lease (it will expire)", self.job_id, exc_info=True)

    def __enter__(self) -> "RunLease":
        return self

    def __exit__(self, *exc) -> None:
        self.release()
