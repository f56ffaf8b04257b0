"""The Celery app of `celery -A worker.app worker`, built from the environment at import
(Celery needs a module-level app), with the distillation task running the project's engine.
The API builds its own app with `jobs.queue.make_celery(settings)` to enqueue."""
from __future__ import annotations

from core.engine import run_job
from jobs.queue import make_celery
from jobs.sessions import SessionStore
from jobs.settings import JobSettings
from jobs.store import JobStore, connect
from worker.prior_cache import cached_prior
from worker.runner import JobRunner
from worker.sessions import SessionUpdater
from worker.tasks import register_distill_task, register_session_task

settings = JobSettings.from_env()
app = make_celery(settings)


def _runner() -> JobRunner:
    return JobRunner(JobStore(connect(settings.broker_url)), settings, engine=run_job, prior_factory=cached_prior)


distill = register_distill_task(app, _runner)


def _updater() -> SessionUpdater:
    client = connect(settings.broker_url)
    return SessionUpdater(JobStore(client), SessionStore(client), settings, engine=run_job, prior_factory=cached_prior)


session_update = register_session_task(app, _updater)
