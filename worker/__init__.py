"""Celery side of the service: the app (worker.app) and the distillation task (worker.tasks)."""
