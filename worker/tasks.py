"""The Celery task: a thin shim over worker.runner.JobRunner, registered on an app by
`register_distill_task` (worker.app with the project's engine; tests with scripted ones)."""
from __future__ import annotations

import logging
from functools import lru_cache
from typing import Callable

from celery import Celery

from jobs.queue import SESSION_TASK_NAME, TASK_NAME
from worker.runner import JobRunner, Outcome
from worker.sessions import SessionOutcome, SessionUpdater

log = logging.getLogger("lightfield.worker")


def register_distill_task(app: Celery, make_runner: Callable[[], JobRunner]):
    """Register the distillation task on `app`; the runner is built on the first delivery."""
    runner_once = lru_cache(maxsize=1)(make_runner)

    @app.task(name=TASK_NAME, bind=True, acks_late=True, max_retries=None)
    def distill(self, job_id: str) -> str:
        runner = runner_once()
        try:
            outcome = runner.run(job_id)
        except Exception as exc:  # e.g. Redis unreachable: keep the job, try again later
            log.exception("job %s: delivery failed, retrying", job_id)
            raise self.retry(exc=exc, countdown=max(runner.settings.lease_ttl_s, 1.0))  # noqa: B904 — Celery's retry idiom
        if outcome is Outcome.STORAGE_RETRY:  # resumes from its checkpoint once the storage is back
            self.apply_async(args=[job_id], countdown=runner.retry_delay_s)
        elif outcome in (Outcome.REQUEUE, Outcome.ABANDONED):
            # Another delivery holds the lease, or this run lost it (its renewals failed while
            # Redis was away). Re-queue (not drop): if no other delivery runs the job, this copy
            # is its only message; one that finds the job finished skips it.
            self.apply_async(args=[job_id], countdown=max(runner.settings.lease_ttl_s / 2, 0.5))
        log.info("job %s: %s", job_id, outcome.value)
        return outcome.value

    return distill


SESSION_REQUEUE_S = 0.5  # a delivery that found another updating the session looks again this soon


def register_session_task(app: Celery, make_updater: Callable[[], SessionUpdater]):
    """Register the live-session update task on `app`; the updater is built on the first delivery."""
    updater_once = lru_cache(maxsize=1)(make_updater)

    @app.task(name=SESSION_TASK_NAME, bind=True, acks_late=True, max_retries=None)
    def session_update(self, session_id: str) -> str:
        updater = updater_once()
        try:
            outcome = updater.run(session_id)
        except Exception as exc:  # e.g. Redis unreachable: the session's frames wait for the next try
            log.exception("session %s: update delivery failed, retrying", session_id)
            raise self.retry(exc=exc, countdown=max(updater.settings.lease_ttl_s, 1.0))  # noqa: B904 — Celery's retry idiom
        if outcome in (SessionOutcome.REQUEUE, SessionOutcome.ABANDONED):
            self.apply_async(args=[session_id], countdown=SESSION_REQUEUE_S)
        return outcome.value

    return session_update
