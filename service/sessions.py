"""What the HTTP routes and the WebSocket of a live session share: accepting frames, queueing
the next update, ending and expiring a session, and its JSON view.

Idle sessions expire lazily: whoever touches a session (a frame, a status, a subscription,
the creation of another session of the tenant) ends it as `expired` once it has received no
frame for LIGHTFIELD_SESSION_IDLE_S; ending queues a last update, which stores the final
field. A subscription keeps looking, so a session nobody posts to is found within a poll.
"""
from __future__ import annotations

import logging
import time
import uuid

from fastapi.concurrency import run_in_threadpool

from jobs.queue import SESSION_TASK_NAME
from jobs.session_files import SessionPaths, store_frame
from jobs.sessions import SessionFull, SessionRecord
from service.context import AppContext
from service.errors import Conflict, PayloadTooLarge, ServiceUnavailable, TooManyJobs, storage_errors
from service.session_frames import CheckedFrame, FrameBatch, check_batch

log = logging.getLogger("lightfield.service")
SCHEDULE_TTL_S = 60.0  # a queued update not started by then (its worker died) may be queued again


def session_view(record: SessionRecord, idle_s: float) -> dict:
    sid = record.id
    return {
        "id": sid, "state": record.state, "frames": record.frames, "bytes": record.bytes,
        "frame_size": [record.width, record.height] if record.width else None,
        "version": record.latest, "version_frames": record.latest_frames,
        "version_at": record.latest_at, "update_error": record.update_error or None,
        "final": record.final, "created_at": record.created_at, "last_active": record.last_active,
        "expires_at": record.last_active + idle_s if record.is_live else None,
        "links": {"self": f"/sessions/{sid}", "frames": f"/sessions/{sid}/frames", "events": f"/sessions/{sid}/events",
                  "stream": f"/sessions/{sid}/stream", "lightfield": f"/lightfield/{sid}"},
    }


def queue_update(ctx: AppContext, session_id: str) -> None:
    """Queue the session's next update unless one is queued already (blocking)."""
    if ctx.sessions.schedule(session_id, SCHEDULE_TTL_S):
        try:
            ctx.celery.send_task(SESSION_TASK_NAME, args=[session_id])
        except Exception:
            ctx.sessions.unschedule(session_id)
            log.exception("session %s: could not enqueue its update", session_id)
            raise ServiceUnavailable("the job queue is unreachable; the frames are kept and the next ones queue "
                                     "the update", code="broker_unavailable") from None


def expire_if_idle(ctx: AppContext, record: SessionRecord) -> SessionRecord:
    """The record, ended as `expired` (and its final update queued) when it has been idle too long."""
    if record.is_live and time.time() - record.last_active > ctx.settings.limits.session_idle_s:
        if ctx.sessions.end(record, "expired"):
            log.info("session %s: expired after %.0f s idle", record.id, time.time() - record.last_active)
            queue_update(ctx, record.id)
        return ctx.sessions.get(record.id) or record
    return record


def expire_idle_of_tenant(ctx: AppContext, thash: str) -> None:
    for sid in ctx.sessions.live_ids(thash):
        record = ctx.sessions.get(sid)
        if record is not None:
            expire_if_idle(ctx, record)


def end_session(ctx: AppContext, record: SessionRecord) -> SessionRecord:
    if ctx.sessions.end(record, "ended"):
        queue_update(ctx, record.id)
    return ctx.sessions.get(record.id) or record


async def accept_frames(ctx: AppContext, record: SessionRecord, batch: FrameBatch) -> dict:
    """Check, store and record a batch of frames, then queue an update. A 4xx ApiError names the
    first bad frame; nothing of a refused batch is kept, and the session goes on."""
    record = await run_in_threadpool(expire_if_idle, ctx, record)
    if not record.is_live:
        raise Conflict(f"session {record.id} has {record.state}; open a new one", code="session_ended")
    limits = ctx.settings.limits
    size = (record.width, record.height) if record.frames else None
    first = record.frames == 0
    frames = await ctx.upload_checks.run(check_batch, batch, size, record.with_pose if not first else None,
                                         record.with_depth if not first else None)
    if record.frames + len(frames) > limits.max_session_frames:  # before storing anything
        raise PayloadTooLarge(f"a session holds at most {limits.max_session_frames} frames; it has {record.frames}",
                              code="too_many_frames")
    paths = SessionPaths.of(ctx.settings.data_dir, record.tenant_hash, record.id)
    with storage_errors("storing the frames"):
        entries, nbytes = await run_in_threadpool(_store, ctx, paths, frames)
    try:
        start = await run_in_threadpool(ctx.sessions.append_frames, record.id, entries, nbytes,
                                        max_frames=limits.max_session_frames, max_bytes=limits.max_session_bytes,
                                        max_per_s=limits.max_session_fps)
    except SessionFull as exc:
        await run_in_threadpool(_unstore, ctx, paths, entries)
        if exc.code == "rate_limited":
            raise TooManyJobs(str(exc), retry_after_s=1) from None
        if exc.code == "not_live":
            raise Conflict(f"session {record.id} has ended; open a new one", code="session_ended") from None
        raise PayloadTooLarge(str(exc), code=exc.code) from None
    if first:
        f0 = frames[0]
        await run_in_threadpool(ctx.sessions.set, record.id, width=f0.width, height=f0.height,
                                with_pose=f0.pose is not None, with_depth=f0.depth is not None)
    await run_in_threadpool(queue_update, ctx, record.id)
    return {"accepted": len(frames), "first_index": start, "frames": start + len(frames)}


def _store(ctx: AppContext, paths: SessionPaths, frames: list[CheckedFrame]) -> tuple[list[dict], int]:
    entries, nbytes = [], 0
    for f in frames:
        stem = uuid.uuid4().hex  # server-chosen: a frame's order is its place in the Redis list
        entry = {"image": stem + f.suffix, "depth": None, "pose": f.pose, "ev": f.ev}
        store_frame(ctx.files, paths, entry["image"], f.image)
        nbytes += len(f.image)
        if f.depth is not None:
            entry["depth"] = stem + ".depth.npy"
            store_frame(ctx.files, paths, entry["depth"], f.depth)
            nbytes += len(f.depth)
        entries.append(entry)
    return entries, nbytes


def _unstore(ctx: AppContext, paths: SessionPaths, entries: list[dict]) -> None:
    for entry in entries:
        for name in (entry["image"], entry["depth"]):
            if name:
                local = paths.frames_dir / name
                local.unlink(missing_ok=True)
                if ctx.files.shared:
                    ctx.files.store.delete([ctx.files.key(local)])
