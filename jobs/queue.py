"""The job queue: its name, the task's name and the Celery app configuration, shared by the
API (to enqueue, ping) and the workers (worker.app, which registers the task).

Delivery guarantees (see docs/api.md, "Queue"):
* acks_late + reject_on_worker_lost: a message is acknowledged only after the task returns,
  so a worker that dies mid-job leaves it unacknowledged and the broker re-delivers it after
  the visibility timeout (LIGHTFIELD_VISIBILITY_TIMEOUT) to a live worker;
* prefetch multiplier 1: a busy worker does not hoard queued jobs;
* a run lease in Redis (jobs.lease) keeps a re-delivered copy from running while the
  original is still alive, and checkpoints let the copy resume when it is not.
"""
from __future__ import annotations

from celery import Celery

from jobs.settings import JobSettings

TASK_NAME = "lightfield.distill"
SESSION_TASK_NAME = "lightfield.session_update"  # a live session's next version (worker.sessions)
QUEUE = "lightfield"


def make_celery(settings: JobSettings) -> Celery:
    app = Celery("lightfield")
    vt = settings.visibility_timeout_s
    app.conf.update(
        broker_url=settings.broker_url or "redis://unconfigured.invalid:6379/0",
        broker_connection_retry_on_startup=True,
        broker_transport_options={
            "visibility_timeout": vt,
            # sweep for abandoned (unacked) messages often enough that vt is the real bound
            "unacked_restore_interval": max(1, int(vt / 4)),
            "unacked_restore_throttle": 1,
            "socket_timeout": 30,
            "socket_connect_timeout": 10,
        },
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        task_ignore_result=True,  # job state lives in the JobStore, not in a result backend
        task_default_queue=QUEUE,
        task_serializer="json",
        accept_content=["json"],
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
        worker_enable_remote_control=True,  # /readyz pings workers
    )
    return app



def requeue_unacknowledged(app: Celery) -> int:
    """Put every delivered-but-unacknowledged message back at the head of its queue; returns
    how many. Only correct when NO worker is alive (embedded mode: its one worker just died,
    or the service is starting): a live worker's messages would then run twice. Without this
    a job whose worker was killed waits for the visibility timeout (10 min by default)."""
    with app.connection_for_write() as conn:
        channel = conn.default_channel
        client = channel.client
        tags = client.hkeys(channel.unacked_key)
        for tag in tags:
            channel.qos.restore_by_tag(tag, client=client, leftmost=True)
    return len(tags)
