"""Celery side of the service: the app (worker.app), the task shim (worker.tasks) and one
delivery of a job (worker.runner)."""
