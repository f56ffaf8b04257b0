"""`lightfield serve`: the API, plus (with no broker configured) its own Redis and worker.

Embedded mode (no LIGHTFIELD_BROKER_URL): start a private Redis (loopback, random password,
AOF in <data_dir>/redis) and one Celery worker subprocess, both supervised
(service.supervisor: restarted when they die, with bounds, logged; /healthz reports them),
and uvicorn in this process. Before the worker starts, and whenever it is restarted, the
jobs the previous worker held are given back to the queue at once (it was the only worker,
so nothing else can hold them) instead of after the visibility timeout. On SIGINT/SIGTERM
uvicorn stops first, then the worker (warm shutdown, its unfinished job stays in the queue
and resumes from its checkpoint next time), then Redis.
Distributed mode (LIGHTFIELD_BROKER_URL=redis://...): only the API; run `lightfield worker`
anywhere that reaches the same Redis and storage root.
"""
from __future__ import annotations

import logging
import os
import secrets
import signal

from service.auth import KeyRing, require_loopback
from service.config import ServiceSettings
from service.processes import child_env, free_port, spawn, start_redis, stop, worker_command
from service.supervisor import Child, Supervisor

log = logging.getLogger("lightfield.serve")
WORKER_GRACE_S = 20.0


def recover_abandoned_jobs(settings: ServiceSettings) -> None:
    """Re-queue what a dead (only) worker held and drop its run leases, so its job resumes now."""
    from jobs.queue import make_celery, requeue_unacknowledged  # noqa: PLC0415 — jobs.queue pulls in celery: imported when used
    from jobs.store import JobStore, connect  # noqa: PLC0415 — jobs.store pulls in redis: imported when used

    requeued = requeue_unacknowledged(make_celery(settings))
    leases = JobStore(connect(settings.broker_url)).clear_leases()
    if requeued or leases:
        log.warning("re-queued %d unacknowledged job message(s), dropped %d stale run lease(s)", requeued, leases)


def embedded_children(settings: ServiceSettings) -> tuple[list[Child], str]:
    """Redis and the worker as supervised children, and the broker URL they share."""
    redis_dir = settings.data_dir / "redis"
    port, password = free_port(), secrets.token_hex(16)
    url = f"redis://:{password}@127.0.0.1:{port}/0"
    settings = settings.model_copy(update={"broker_url": url})
    env = child_env(LIGHTFIELD_BROKER_URL=url, LIGHTFIELD_DATA_DIR=str(settings.data_dir.resolve()))
    log_path = settings.data_dir / "worker.log"
    redis = Child("redis", start=lambda: start_redis(redis_dir, port=port, password=password).proc,
                  stop=lambda proc: stop(proc, signal.SIGTERM, grace_s=15.0))  # SIGTERM: Redis flushes its AOF
    worker = Child("worker", start=lambda: spawn(worker_command("embedded"), env=env, log_path=log_path,
                                                 death_signal=signal.SIGKILL),  # no orphan finishing its job
                   stop=lambda proc: stop(proc, signal.SIGTERM, grace_s=WORKER_GRACE_S),
                   before_restart=lambda: recover_abandoned_jobs(settings))
    return [redis, worker], url


def serve(host: str, port: int, settings: ServiceSettings, log_level: str = "info") -> int:
    from service.frontdoor import FrontDoorServer  # noqa: PLC0415 — service.frontdoor pulls in uvicorn: imported when used
    from service.routes.health import health_probe  # noqa: PLC0415 — service.routes.health pulls in celery, prometheus_client, redis, torch: imported when used
    from service.server import server_config  # noqa: PLC0415 — service.server pulls in uvicorn: imported when used

    require_loopback(host, KeyRing.parse(settings.api_keys))
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    supervisor: Supervisor | None = None
    # uvicorn re-raises the signal that stopped it once it has shut down; with the default
    # handlers that would kill this process before the children are stopped in order.
    received: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: received.append(signum))
    try:
        if not settings.broker_url:
            children, url = embedded_children(settings)
            os.environ["LIGHTFIELD_BROKER_URL"] = url
            os.environ["LIGHTFIELD_DATA_DIR"] = str(settings.data_dir.resolve())
            settings = settings.model_copy(update={"broker_url": url})
            redis, worker = children
            supervisor = Supervisor(children)
            # Redis first; then what a previous run's worker held goes back to the queue
            # before this run's worker starts (a killed `serve` leaves it unacknowledged)
            redis.proc, redis.state = redis.start(), "running"
            recover_abandoned_jobs(settings)
            worker.proc, worker.state = worker.start(), "running"
            supervisor.start_watching()
            log.info("embedded mode: Redis and one worker started (logs in %s)", settings.data_dir)
        from service.app import create_app  # noqa: PLC0415 — service.app pulls in celery, prometheus_client, redis, torch: imported when used

        if received:  # asked to stop while starting up
            return 0
        states = supervisor.states if supervisor else None
        app = create_app(settings, dependency_states=states)
        probe = health_probe(states, app.state.metrics)
        # connections are accepted on a thread of its own, which answers /healthz itself
        # (service.frontdoor): a liveness probe never waits for the event loop's turn
        FrontDoorServer(server_config(app, host, port, settings.timeouts, log_level, probe), probe).run()
        return 0
    finally:
        if supervisor is not None:
            supervisor.stop()
