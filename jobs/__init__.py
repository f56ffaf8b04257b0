"""What the HTTP service and the Celery workers share, so neither imports the other: job
records and their Redis store, the run lease, the storage layout, the settings both read,
the queue, the error codes and the UI preview's stored format.
"""
