"""A succeeded job's light field for the query routes, or the error that says why not.

Loading verifies every file of the artefact (core.fields.stored.artefact: the checksums recorded
when it was written). A file that fails is never served and never retried: the job is
marked `failed` with error `artefact_corrupt` (the one transition out of `succeeded`), its
files are left for an operator to inspect, and every later query answers 410 at once from
the record. An I/O error while reading (a storage hiccup) is a 503 and marks nothing.

Hot path: a job found succeeded less than RECENT_S ago whose field is loaded is answered
without asking Redis again (`recent_field`, no I/O, on the event loop). A succeeded record
only changes by deletion or by the corruption mark; this process applies both to its own
cache at once, another API replica's deletion is seen within RECENT_S.
"""
from __future__ import annotations

import logging
import time

from jobs.jobfiles import ObjectCorrupt
from jobs.storage import JobPaths
from jobs.store import JobRecord
from service.context import AppContext, Tenant, owned_job
from service.errors import Conflict, Gone, NotFound, ServiceUnavailable
from service.fieldcache import CachedField
from service.session_versions import session_field

log = logging.getLogger("lightfield.service")
ARTEFACT_CORRUPT = "artefact_corrupt"


def succeeded_job(job_id: str, tenant: Tenant, ctx: AppContext, what: str = "its light field") -> JobRecord:
    record = owned_job(job_id, tenant, ctx)
    if record.state == "failed" and record.error_code == ARTEFACT_CORRUPT:
        raise Gone(f"job {job_id}: {record.error_message}", code=ARTEFACT_CORRUPT)
    if record.state != "succeeded":
        raise Conflict(f"job {job_id} is {record.state}; {what} exists once it has succeeded", code="not_ready")
    return record


def load_field(record: JobRecord, ctx: AppContext) -> CachedField:
    """The job's loaded field. With a shared store the artefact is first fetched into this host's
    cache (jobs.jobfiles; verified against the SHA-256 of every object), and a cached copy that
    fails verification is fetched once more before the job is marked corrupt."""
    from core.fields.stored.artefact import ArtefactError  # noqa: PLC0415 — core.fields.stored.artefact pulls in safetensors: imported when used

    directory = ctx.settings.data_dir / record.artefact
    paths = JobPaths.for_job(ctx.settings.data_dir, record.tenant_hash, record.id)
    cached = ctx.fields.peek(record.id)
    if cached is not None:
        return cached
    try:
        for attempt in (0, 1):
            try:
                if not ctx.files.fetch_artefact(paths, refresh=attempt > 0):
                    raise ArtefactError("lightfield.json: missing from storage")
                return ctx.fields.get(record.id, directory)
            except ArtefactError:
                if attempt or not ctx.files.shared:
                    raise
                log.warning("job %s: the cached light field failed verification; fetching it again", record.id)
    except (ArtefactError, ObjectCorrupt) as exc:
        detail = str(exc).replace(str(directory), "lightfield")  # no server paths in client messages
        message = f"the stored light field failed verification and will not be served: {detail}"
        log.error("job %s: %s", record.id, message)
        ctx.store.update(record.id, allowed=("succeeded",), state="failed", error_code=ARTEFACT_CORRUPT,
                         error_message=message[:2000])
        raise Gone(f"job {record.id}: {message}", code=ARTEFACT_CORRUPT) from None
    except OSError:
        log.exception("job %s: reading the artefact failed", record.id)
        raise ServiceUnavailable("the light field could not be read from storage; try again shortly",
                                 code="storage_unavailable") from None
    raise AssertionError("unreachable")


RECENT_S = 1.0


def job_field(job_id: str, tenant: Tenant, ctx: AppContext) -> CachedField:
    """The caller's succeeded job's light field, or the latest version of the caller's live
    session of that id (service.session_versions; blocking: run in the threadpool)."""
    try:
        record = succeeded_job(job_id, tenant, ctx)
    except NotFound:
        if ctx.sessions is None:
            raise
        try:
            return session_field(job_id, tenant, ctx)
        except NotFound:
            raise NotFound(f"no job or session {job_id!r}", code="job_not_found") from None
    cf = load_field(record, ctx)
    now = time.monotonic()
    if len(ctx.recent_jobs) > 4096:  # bounded: drop the expired entries
        for key in [k for k, (_, expiry) in list(ctx.recent_jobs.items()) if expiry < now]:
            ctx.recent_jobs.pop(key, None)
    ctx.recent_jobs[job_id] = (tenant.name, now + RECENT_S)
    return cf


def recent_field(job_id: str, tenant: Tenant, ctx: AppContext) -> CachedField | None:
    """The field of a job of this tenant found succeeded within RECENT_S, if loaded; else None."""
    seen = ctx.recent_jobs.get(job_id)
    if seen is None or seen[0] != tenant.name or seen[1] < time.monotonic():
        return None
    return ctx.fields.peek(job_id)


def forget(job_id: str, ctx: AppContext) -> None:
    ctx.recent_jobs.pop(job_id, None)
    ctx.fields.evict(job_id)
