"""Liveness, readiness and metrics."""
from __future__ import annotations

import json
from typing import Callable

from fastapi import APIRouter, Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from service.context import AppContext, get_ctx
from service.errors import ErrorBody, ServiceUnavailable
from service.models import Health, Readiness

router = APIRouter(tags=["health"])


def health_answer(states_of: Callable[[], dict[str, str]] | None) -> tuple[int, dict]:
    """(status, body) of /healthz from the supervised dependencies' states (memory only)."""
    states = states_of() if states_of is not None else {}
    down = {name: state for name, state in states.items() if state != "running"}
    if down:
        message = "embedded " + ", ".join(f"{n} is {s}" for n, s in sorted(down.items()))
        return 503, ErrorBody(error={"code": "dependency_down", "message": message}).model_dump()
    return 200, Health(status="ok", dependencies=states).model_dump()


def health_probe(states_of: Callable[[], dict[str, str]] | None, metrics=None) -> Callable[[], tuple[int, bytes]]:
    """health_answer as (status, JSON bytes), for service.server's protocol-level answer
    (counted in `metrics` like a routed request)."""

    def probe() -> tuple[int, bytes]:
        status, body = health_answer(states_of)
        if metrics is not None:
            metrics.requests.labels("GET", "/healthz", str(status)).inc()
        return status, json.dumps(body).encode()

    return probe


@router.get("/healthz", response_model=Health, responses={503: {"model": ErrorBody}},
            summary="The API process is up (embedded mode: and its Redis and worker processes are running)")
async def healthz(request: Request):
    # async and I/O-free: answered on the event loop, never queued behind the threadpool
    # (`lightfield serve` answers it before routing, in service.server, with the same body)
    status, body = health_answer(getattr(request.app.state, "dependency_states", None))
    if status != 200:
        return JSONResponse(body, status_code=status, headers={"Retry-After": "5"})
    return body


def _check_ready(ctx: AppContext) -> Readiness:
    try:
        ctx.store.client.ping()
    except Exception:
        return Readiness(status="not_ready", broker=False, workers=0, detail="Redis (broker and job store) unreachable")
    try:
        replies = ctx.celery.control.ping(timeout=ctx.settings.readiness_timeout_s, limit=1) or []
    except Exception:
        replies = []
    if not replies:
        return Readiness(status="not_ready", broker=True, workers=0,
                         detail=f"no worker answered a ping within {ctx.settings.readiness_timeout_s:g} s")
    return Readiness(status="ready", broker=True, workers=len(replies))


@router.get("/readyz", response_model=Readiness, responses={503: {"model": ErrorBody}},
            summary="Broker reachable and at least one worker answering")
async def readyz(ctx: AppContext = Depends(get_ctx)):
    ready = await run_in_threadpool(_check_ready, ctx)
    if ready.status != "ready":
        raise ServiceUnavailable(f"not ready: {ready.detail}", code="not_ready")
    return ready


@router.get("/metrics", response_class=Response, summary="Prometheus metrics",
            responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}})
async def metrics(request: Request):
    registry = request.app.state.metrics.registry
    data = await run_in_threadpool(generate_latest, registry)
    return Response(data, media_type=CONTENT_TYPE_LATEST)
