"""Celery tasks: a thin shim over worker.runner.JobRunner."""
from __future__ import annotations

import logging
from functools import lru_cache

from service.config import ServiceSettings
from service.store import JobStore, connect
from worker.app import TASK_NAME, app
from worker.prior_cache import get_prior
from worker.runner import JobRunner, Outcome

log = logging.getLogger("lightfield.worker")


@lru_cache(maxsize=1)
def _runner() -> JobRunner:
    settings = ServiceSettings.from_env()
    return JobRunner(JobStore(connect(settings.broker_url)), settings, prior_provider=get_prior)


@app.task(name=TASK_NAME, bind=True, acks_late=True, max_retries=None)
def distill(self, job_id: str) -> str:
    runner = _runner()
    try:
        outcome = runner.run(job_id)
    except Exception as exc:  # e.g. Redis unreachable: keep the job, try again later
        log.exception("job %s: delivery failed, retrying", job_id)
        raise self.retry(exc=exc, countdown=max(runner.settings.lease_ttl_s, 1.0))
    if outcome is Outcome.REQUEUE:
        # Another delivery holds the lease. Re-queue (not drop): if that holder dies, this
        # copy may be the only message left for the job.
        self.apply_async(args=[job_id], countdown=max(runner.settings.lease_ttl_s / 2, 0.5))
    log.info("job %s: %s", job_id, outcome.value)
    return outcome.value
