"""Keeps the embedded mode's children (Redis, the Celery worker) alive, within bounds.

One thread polls every child each POLL_S. A child that exited is restarted after a backoff
(1, 2, 4, ... up to MAX_BACKOFF_S seconds), at most `max_restarts` times within
`window_s`; past that it is marked `failed` and left down (a crash loop would otherwise
burn the machine), and /healthz answers 503 so a liveness probe restarts the whole service.
Every death and restart is logged with the exit code. `states()` is what /healthz reports:
`running`, `restarting` (dead, restart pending) or `failed` — read from memory, no I/O.

The watcher thread also stops the children at shutdown: a child it restarted carries a
parent-death signal bound to the thread that spawned it (Linux PR_SET_PDEATHSIG follows
the thread, not the process), so that thread must outlive the orderly stop (worker first,
then Redis) or its exit would kill Redis under a worker still finishing its job.
"""
from __future__ import annotations

import logging
import subprocess
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

log = logging.getLogger("lightfield.serve")
POLL_S = 0.25
MAX_BACKOFF_S = 30.0


@dataclass
class Child:
    name: str
    start: Callable[[], subprocess.Popen]  # (re)starts the child; may raise (counted as a failed attempt)
    stop: Callable[[subprocess.Popen], None]
    before_restart: Callable[[], None] | None = None  # e.g. re-queue what the dead worker held
    max_restarts: int = 5
    window_s: float = 300.0
    proc: subprocess.Popen | None = None
    state: str = "stopped"
    restarts: deque = field(default_factory=deque)  # monotonic times of restart attempts
    next_attempt: float = 0.0


class Supervisor:
    def __init__(self, children: list[Child]):
        self.children = children
        self._stopping = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Start the children in order (raises if one cannot start), then watch them."""
        for child in self.children:
            child.proc = child.start()
            self._set(child, "running")
        self.start_watching()

    def start_watching(self) -> None:
        """Watch children started by the caller."""
        self._thread = threading.Thread(target=self._watch, name="embedded-supervisor", daemon=True)
        self._thread.start()

    def states(self) -> dict[str, str]:
        with self._lock:
            return {c.name: c.state for c in self.children}

    def _watch(self) -> None:
        while not self._stopping.wait(POLL_S):
            for child in self.children:
                try:
                    self._check(child)
                except Exception:  # never let the watcher die
                    log.exception("supervising %s failed", child.name)
        self._stop_children()

    def _check(self, child: Child) -> None:
        now = time.monotonic()
        if child.state == "running":
            code = child.proc.poll() if child.proc is not None else -1
            if code is None:
                return
            log.error("embedded %s exited with code %s", child.name, code)
            self._set(child, "restarting")
            child.next_attempt = now + self._backoff(child)
        if child.state != "restarting" or now < child.next_attempt or self._stopping.is_set():
            return
        while child.restarts and now - child.restarts[0] > child.window_s:
            child.restarts.popleft()
        if len(child.restarts) >= child.max_restarts:
            log.critical("embedded %s died %d times within %g s; not restarting it again (/healthz reports it)",
                         child.name, len(child.restarts), child.window_s)
            self._set(child, "failed")
            return
        child.restarts.append(now)
        attempt = len(child.restarts)
        try:
            if child.before_restart is not None:
                child.before_restart()
            child.proc = child.start()
        except Exception as exc:
            log.error("restarting embedded %s (attempt %d of %d) failed: %s", child.name, attempt,
                      child.max_restarts, exc)
            child.next_attempt = now + self._backoff(child)
            return
        log.warning("embedded %s restarted (attempt %d of %d within %g s)", child.name, attempt,
                    child.max_restarts, child.window_s)
        self._set(child, "running")

    @staticmethod
    def _backoff(child: Child) -> float:
        return min(MAX_BACKOFF_S, 2.0 ** len(child.restarts) / 2)  # 0.5, 1, 2, 4, ... s

    def _set(self, child: Child, state: str) -> None:
        with self._lock:
            child.state = state

    def stop(self, timeout_s: float = 120.0) -> None:
        """Stop watching and stop the children in reverse order (on the watcher thread, see above)."""
        self._stopping.set()
        if self._thread is not None and self._thread.is_alive():
            self._thread.join(timeout=timeout_s)
        else:
            self._stop_children()

    def _stop_children(self) -> None:
        for child in reversed(self.children):
            if child.proc is not None and child.state != "stopped":
                try:
                    child.stop(child.proc)
                except Exception:
                    log.exception("stopping embedded %s failed", child.name)
            self._set(child, "stopped")
