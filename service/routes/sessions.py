"""/sessions: live AR sessions. Open one, stream frames in (HTTP or WebSocket), follow the
versions of its field (SSE or the WebSocket), end it; docs/api.md, "Live sessions"."""
from __future__ import annotations

import asyncio
import json
import logging

from fastapi import APIRouter, Depends, Query, Request, WebSocket, WebSocketDisconnect
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, StreamingResponse

from jobs.sessions import SessionLimitReached, SessionRecord
from jobs.storage import new_job_id
from service.context import AppContext, Tenant, get_ctx, get_tenant
from service.errors import ApiError, ErrorBody, InvalidInput, PayloadTooLarge, TooManyJobs, broker_errors
from service.lightfields import job_field
from service.routes.jobs import parse_params
from service.session_frames import batch_from_message, read_multipart
from service.session_push import check_layout, parse_probes, version_event
from service.session_versions import owned_session
from service.sessions import accept_frames, end_session, expire_idle_of_tenant, expire_if_idle, session_view

log = logging.getLogger("lightfield.service")
router = APIRouter(tags=["sessions"])
_ERRORS = {s: {"model": ErrorBody} for s in (400, 401, 404, 409, 413, 415, 422, 429, 503)}
POLL_S = 0.25  # how often a subscription looks for a new version (versions land at ~1 Hz at best)
KEEPALIVE_S = 15.0
PER_FRAME_KEYS = ("poses", "frame_ev", "max_frames")  # a session's frames carry these themselves

_FRAMES_SCHEMA = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
    "type": "object",
    "properties": {
        "frame": {"type": "array", "items": {"type": "string", "format": "binary"},
                  "description": "images (PNG, JPEG, WebP, BMP, TIFF), one part per frame, in capture order"},
        "depth": {"type": "array", "items": {"type": "string", "format": "binary"},
                  "description": "one depth map per frame (.npy/.npz/EXR/16-bit PNG mm), same order"},
        "video": {"type": "string", "format": "binary", "description": "instead of frames: a short video chunk"},
        "meta": {"type": "string", "contentMediaType": "application/json",
                 "description": '{"poses": [[16 floats row-major camera-to-world], ...], "ev": [stops, ...]}'},
    }}}}}}


def _view(record: SessionRecord, ctx: AppContext) -> dict:
    return session_view(record, ctx.settings.limits.session_idle_s)


@router.post("/sessions", status_code=201, responses=_ERRORS, summary="Open a live session (body: a job's params)")
async def create_session(request: Request, tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    body = (await request.body()).decode("utf-8", "replace").strip()
    params = parse_params(body or "{}", ctx)
    given = [k for k in PER_FRAME_KEYS if getattr(params, k) is not None and not isinstance(getattr(params, k), str)]
    if given:
        raise InvalidInput(f"params.{given[0]}: a session's frames carry their own poses and exposures "
                           "(POST /sessions/{id}/frames)", code="invalid_params")
    limit = ctx.settings.limits.max_live_sessions
    await run_in_threadpool(expire_idle_of_tenant, ctx, tenant.hash)
    record = SessionRecord(id=new_job_id(), tenant=tenant.name, tenant_hash=tenant.hash,
                           params=params.model_dump_json(exclude_none=True))
    try:
        await run_in_threadpool(ctx.sessions.create, record, limit)
    except SessionLimitReached as exc:
        raise TooManyJobs(str(exc), retry_after_s=5) from None
    return JSONResponse(_view(record, ctx), status_code=201, headers={"Location": f"/sessions/{record.id}"})


@router.get("/sessions/{session_id}", responses=_ERRORS, summary="A session: frames, latest version, state")
def get_session(session_id: str, tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    return _view(expire_if_idle(ctx, owned_session(session_id, tenant, ctx)), ctx)


@router.post("/sessions/{session_id}/frames", status_code=202, responses=_ERRORS, openapi_extra=_FRAMES_SCHEMA,
             summary="Send one or a few frames (images with pose, depth, exposure; or a short video chunk)")
async def post_frames(session_id: str, request: Request, tenant: Tenant = Depends(get_tenant),
                      ctx: AppContext = Depends(get_ctx)):
    record = await run_in_threadpool(owned_session, session_id, tenant, ctx)
    limit = ctx.settings.limits.max_frames_request_bytes
    length = request.headers.get("content-length")
    if length and length.isdigit() and int(length) > limit + 64 * 1024:
        raise PayloadTooLarge(f"a frames request may carry at most {limit} bytes", code="too_large")
    batch = await read_multipart(request.headers.get("content-type"), request.stream(), limit)
    result = await accept_frames(ctx, record, batch)
    return JSONResponse({**result, "session": _view(ctx.sessions.get(session_id) or record, ctx)}, status_code=202)


@router.delete("/sessions/{session_id}", status_code=202, responses=_ERRORS,
               summary="End a session: its last version becomes a stored field at /lightfield/{id}")
def delete_session(session_id: str, tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    record = owned_session(session_id, tenant, ctx)
    return JSONResponse(_view(end_session(ctx, record), ctx), status_code=202)


@router.get("/sessions/{session_id}/events", responses={200: {"content": {"text/event-stream": {}}}, **_ERRORS},
            summary="Server-Sent Events: per probe point, the lighting of each new version (XRLightProbe-like)")
async def session_events(session_id: str, request: Request,
                         x: list[str] = Query(..., description="probe points 'X,Y,Z' (repeat x=)"),  # noqa: B008 — FastAPI's idiom
                         t: float | None = Query(None, description="seconds; default: each version's last frame"),
                         layout: str = Query("arcore", description="SH layout of sphericalHarmonicsCoefficients "
                                             "(arcore: ARCore/WebXR's 27 floats; threejs: LightProbe.sh.fromArray)"),
                         tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    probes = parse_probes(x, ctx.settings.limits.max_session_probes)
    t = _time(t)
    await run_in_threadpool(owned_session, session_id, tenant, ctx)
    follower = _Follower(ctx, tenant, session_id)
    follower.subscribe(probes, t, check_layout(layout))

    async def stream():
        idle = 0.0
        while True:
            try:
                events = await follower.poll()
            except broker_errors():
                yield 'event: error\ndata: {"code": "broker_unavailable"}\n\n'
                return
            for name, data in events:
                idle = 0.0
                yield f"event: {name}\ndata: {json.dumps(data)}\n\n"
            if follower.done:
                return
            if idle >= KEEPALIVE_S:
                idle = 0.0
                yield ": keep-alive\n\n"
            if await request.is_disconnected():
                return
            await asyncio.sleep(POLL_S)
            idle += POLL_S

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


class _Follower:
    """What a subscriber has been sent: the events due since the last poll."""

    def __init__(self, ctx: AppContext, tenant: Tenant, session_id: str):
        self.ctx, self.tenant, self.session_id = ctx, tenant, session_id
        self.probes: list | None = None
        self.t: float | None = None
        self.layout = "arcore"
        self.sent_version, self.sent_state, self.done = 0, None, False

    def subscribe(self, probes: list, t: float | None, layout: str = "arcore") -> None:
        self.probes, self.t, self.layout, self.sent_version = probes, t, layout, 0  # the current version again

    async def poll(self) -> list[tuple[str, dict]]:
        events = []
        record = await run_in_threadpool(self.ctx.sessions.get, self.session_id)
        if record is None:
            self.done = True
            return [("deleted", {"session": self.session_id})]
        record = await run_in_threadpool(expire_if_idle, self.ctx, record)
        if record.state != self.sent_state:
            self.sent_state = record.state
            events.append(("session", session_view(record, self.ctx.settings.limits.session_idle_s)))
        if self.probes and record.latest and record.latest != self.sent_version and not record.final:
            try:
                cf = await run_in_threadpool(job_field, self.session_id, self.tenant, self.ctx)
                events.append(("version", await version_event(self.ctx, cf, self.session_id, record.latest,
                                                              record.latest_frames, self.probes, self.t,
                                                              self.layout)))
                self.sent_version = record.latest
            except ApiError as exc:  # e.g. the version is being replaced: try again at the next poll
                events.append(("error", {"status": exc.status, "code": exc.code, "message": exc.message}))
        if record.final:
            self.done = True
            events.append(("ended", {"session": self.session_id, "version": record.latest,
                                     "lightfield": f"/lightfield/{self.session_id}" if record.latest else None}))
        return events


@router.websocket("/sessions/{session_id}/stream")
async def session_stream(websocket: WebSocket, session_id: str):
    """Frames in, versions out, on one connection. Client messages (JSON text):
    {"type": "frames", ...} (service.session_frames), {"type": "subscribe", "probes": [[x, y, z]], "t": null,
    "layout": "arcore"},
    {"type": "end"}. Server messages: accepted, error (the session goes on), session, version, ended."""
    ctx: AppContext = websocket.app.state.ctx
    await websocket.accept()
    try:
        tenant = Tenant(ctx.keyring.tenant_for(websocket.headers.get("authorization")))
        record = await run_in_threadpool(owned_session, session_id, tenant, ctx)
    except ApiError as exc:
        await websocket.send_json({"type": "error", "status": exc.status, "code": exc.code, "message": exc.message})
        await websocket.close(code=4000 + exc.status)
        return
    follower = _Follower(ctx, tenant, session_id)
    lock = asyncio.Lock()

    async def send(message: dict) -> None:
        async with lock:
            await websocket.send_json(message)

    async def push() -> None:
        while not follower.done:
            for name, data in await follower.poll():  # a status is wrapped: its "id" is the session's
                await send({"type": "session", "session": data} if name == "session"
                           else data if name == "version" else {"type": name, **data})
            await asyncio.sleep(POLL_S)
        await websocket.close(code=1000)

    pusher = asyncio.create_task(push())
    try:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                break
            reply = await _handle(ctx, follower, session_id, record, message)
            await send(reply)
    except (WebSocketDisconnect, RuntimeError):  # the client left (RuntimeError: receive after close)
        pass
    finally:
        pusher.cancel()


async def _handle(ctx: AppContext, follower: _Follower, session_id: str, record: SessionRecord, message: dict) -> dict:
    """One client message's reply: accepted / subscribed / error (never raises: the session goes on)."""
    request_id = None
    try:
        text = message.get("text")
        if text is None:
            raise InvalidInput("messages are JSON text", code="invalid_message")
        limit = ctx.settings.limits.max_frames_request_bytes * 4 // 3 + 4096  # base64
        if len(text) > limit:
            raise PayloadTooLarge(f"a message may carry at most {limit} characters", code="too_large")
        try:
            body = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InvalidInput(f"message is not JSON: {exc}", code="invalid_message") from None
        if not isinstance(body, dict):
            raise InvalidInput("a message is a JSON object with 'type'", code="invalid_message")
        request_id = body.get("id")
        kind = body.get("type")
        if kind == "frames":
            current = await run_in_threadpool(ctx.sessions.get, session_id) or record
            result = await accept_frames(ctx, current, batch_from_message(body))
            return {"type": "accepted", "id": request_id, **result}
        if kind == "subscribe":
            follower.subscribe(parse_probes(body.get("probes"), ctx.settings.limits.max_session_probes),
                               _time(body.get("t")), check_layout(body.get("layout", "arcore")))
            return {"type": "subscribed", "id": request_id, "probes": len(follower.probes)}
        if kind == "end":
            current = await run_in_threadpool(ctx.sessions.get, session_id) or record
            view = await run_in_threadpool(end_session, ctx, current)
            return {"type": "session", "id": request_id,
                    "session": session_view(view, ctx.settings.limits.session_idle_s)}
        raise InvalidInput(f"unknown message type {kind!r}; expected frames, subscribe, end", code="invalid_message")
    except ApiError as exc:
        return {"type": "error", "id": request_id, "status": exc.status, "code": exc.code, "message": exc.message}


def _time(value) -> float | None:
    if value is None:
        return None
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        raise InvalidInput("t must be a number of seconds or null", code="invalid_t")
    from service.queries import check_t  # noqa: PLC0415 — service.queries pulls in torch: imported when used

    return check_t(float(value))
