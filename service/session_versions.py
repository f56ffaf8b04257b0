"""The query routes on a live session: its latest version's field, and the headers that say
which version answered and how many frames it had seen.

Every /lightfield/<id>/... route takes a session id as it takes a job id (service.lightfields
falls back here when no job has the id). The routes build their responses in many ways, so
the headers are added on the way out by `SessionVersionHeaders` from a per-request note that
`session_field` fills (a mutable holder in a context variable: the route runs in a copy of
the request's context, the holder is shared).
"""
from __future__ import annotations

import contextvars

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from jobs.session_files import SessionPaths, fetch_version
from jobs.storage import is_job_id
from service.context import AppContext, Tenant
from service.errors import Conflict, NotFound, ServiceUnavailable
from service.fieldcache import CachedField

VERSION_HEADER = "X-Lightfield-Session-Version"
FRAMES_HEADER = "X-Lightfield-Session-Frames"
_NOTE: contextvars.ContextVar[dict | None] = contextvars.ContextVar("lightfield_session_note", default=None)


def owned_session(session_id: str, tenant: Tenant, ctx: AppContext):
    """The caller's session or 404: another tenant's is indistinguishable from a missing one."""
    record = ctx.sessions.get(session_id) if is_job_id(session_id) else None
    if record is None or record.tenant != tenant.name:
        raise NotFound(f"no session {session_id!r}", code="session_not_found")
    return record


def session_field(session_id: str, tenant: Tenant, ctx: AppContext) -> CachedField:
    """The latest version's loaded field of the caller's session (blocking: run in a thread).
    404 when there is no such session, 409 not_ready before its first version."""
    from core.fields.stored.artefact import ArtefactError  # noqa: PLC0415 — core.fields.stored.artefact pulls in safetensors: imported when used

    record = owned_session(session_id, tenant, ctx)
    if not record.latest:
        raise Conflict(f"session {session_id} has no version yet ({record.frames} frames received; the first "
                       "version lands once a worker has refined the first frames)", code="not_ready")
    paths = SessionPaths.of(ctx.settings.data_dir, record.tenant_hash, record.id)
    try:
        if not fetch_version(ctx.files, paths, record.latest):
            raise ArtefactError("lightfield.json: missing from storage")
        cf = ctx.fields.get(f"{record.id}@{record.latest}", paths.version_dir(record.latest))
    except (ArtefactError, OSError):
        raise ServiceUnavailable(f"version {record.latest} of session {session_id} could not be read; try again "
                                 "shortly", code="storage_unavailable") from None
    note = _NOTE.get()
    if note is not None:
        note.update(version=record.latest, frames=record.latest_frames)
    return cf


class SessionVersionHeaders:
    """Adds VERSION_HEADER and FRAMES_HEADER to a response that a session's version answered."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not scope.get("path", "").startswith("/lightfield/"):
            await self.app(scope, receive, send)
            return
        note: dict = {}
        token = _NOTE.set(note)

        async def send_noted(message: Message) -> None:
            if message["type"] == "http.response.start" and note:
                message = {**message, "headers": [*message.get("headers", []),
                                                   (VERSION_HEADER.lower().encode(), str(note["version"]).encode()),
                                                   (FRAMES_HEADER.lower().encode(), str(note["frames"]).encode())]}
            await send(message)

        try:
            await self.app(scope, receive, send_noted)
        finally:
            _NOTE.reset(token)
