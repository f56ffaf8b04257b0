"""The Celery app of `celery -A worker.app worker`, built from the environment at import
(Celery needs a module-level app). The API builds its own with `make_celery(settings)`."""
from __future__ import annotations

from service.config import ServiceSettings
from worker.celery_config import QUEUE, TASK_NAME, make_celery

__all__ = ["app", "QUEUE", "TASK_NAME"]

app = make_celery(ServiceSettings.from_env())
