"""A Celery app for tests: the real task and runner, with a scripted engine passed to the
runner instead of core.engine's run_job, so a real worker process runs a job in seconds.

    celery -A scripted_worker worker      (with tests/ on PYTHONPATH)
"""
from __future__ import annotations

from jobs.queue import make_celery
from jobs.settings import JobSettings
from jobs.store import JobStore, connect
from worker.runner import JobRunner
from worker.tasks import register_distill_task


def engine_bad_depth(*a, **kw):
    """Fails as an engine does on an upload whose depth has no valid pixel."""
    from core.capture.base import CaptureError

    raise CaptureError("depth", "no valid pixels")


settings = JobSettings.from_env()
app = make_celery(settings)
register_distill_task(app, lambda: JobRunner(JobStore(connect(settings.broker_url)), settings, engine=engine_bad_depth))
