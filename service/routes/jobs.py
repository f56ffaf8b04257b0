"""/jobs: submit, inspect, stream, list and cancel/delete distillation jobs."""
from __future__ import annotations

import asyncio
import json
import logging
import os
import time
from pathlib import Path

from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, StreamingResponse
from pydantic import ValidationError

from core.priors.base import PriorError
from core.priors.registry import prior_class, require_weights
from jobs.queue import TASK_NAME
from jobs.storage import JobPaths, new_job_id
from jobs.store import JobLimitReached, JobRecord
from service.context import AppContext, Tenant, get_ctx, get_tenant, owned_job
from service.errors import (
    BROKER_DOWN,
    RETRY_AFTER_STORAGE_S,
    ErrorBody,
    InvalidInput,
    ServiceUnavailable,
    TooManyJobs,
    broker_errors,
    describe_validation_errors,
    storage_errors,
)
from service.lightfields import forget
from service.models import JobList, JobView
from service.upload import FormReader
from service.validation import check_capture, classify_depth, classify_input

log = logging.getLogger("lightfield.service")
router = APIRouter(tags=["jobs"])

SSE_POLL_S = 0.25
SSE_KEEPALIVE_S = 15.0

_ERRORS = {s: {"model": ErrorBody} for s in (400, 401, 403, 404, 408, 409, 413, 415, 422, 429, 503)}
MAX_OFFSET = 10**9  # GET /jobs offset (Redis ranges are 64-bit: offset + limit must stay far inside)

_MULTIPART_SCHEMA = {
    "requestBody": {
        "required": True,
        "content": {"multipart/form-data": {"schema": {
            "type": "object",
            "required": ["file"],
            "properties": {
                "file": {"type": "string", "format": "binary",
                         "description": "image or video; the type is sniffed from the content"},
                "depth": {"type": "string", "format": "binary",
                          "description": "planar depth in metres: .npz/.npy (array 'depth' [T,H,W] or [H,W]), "
                                         "OpenEXR, or 16-bit PNG in millimetres"},
                "params": {"type": "string", "contentMediaType": "application/json",
                           "description": "JSON object following JobParams (intrinsics, poses, fps, preset, prior, "
                                          "prior_weights, temporal, seed, max_frames, field); see docs/api.md"},
            },
        }}},
    }
}


def parse_params(text: str | None, ctx: AppContext):
    from core.engine.params import JobParams  # noqa: PLC0415 — core.engine.params pulls in av, cv2, OpenEXR, PIL, safetensors, scipy: imported when used

    try:
        params = JobParams.model_validate_json(text or "{}")
    except ValidationError as exc:
        raise InvalidInput("params: " + describe_validation_errors(exc.errors()), code="invalid_params") from None
    if params.prior_weights is not None:
        weights = Path(params.prior_weights).resolve()
        if not any(weights.is_relative_to(Path(d).resolve()) for d in ctx.settings.model_dirs):
            raise InvalidInput("params.prior_weights must name a directory inside LIGHTFIELD_MODEL_DIRS",
                               code="invalid_params")
    check_prior(params)
    return params


def check_prior(params) -> None:
    """What the worker would refuse about the job's prior, refused now: its settings, and the
    weights of a prior that loads weights (the registry's rule, require_weights)."""
    from core.engine.params import resolve_job  # noqa: PLC0415 — core.engine.params pulls in av, cv2, OpenEXR, PIL, safetensors, scipy: imported when used

    try:
        cls = prior_class(params.prior)
        settings = resolve_job(params).prior_settings
        cls.Config.model_validate(settings)
    except PriorError as exc:
        raise InvalidInput(f"params.prior: {exc}", code="prior_unavailable") from None
    except ValidationError as exc:
        raise InvalidInput(f"params.prior: settings of the {params.prior!r} prior: "
                           + describe_validation_errors(exc.errors()), code="invalid_params") from None
    try:
        require_weights(params.prior, settings, where="a directory inside LIGHTFIELD_MODEL_DIRS")
    except PriorError as exc:
        raise InvalidInput(f"params.prior_weights: {exc}", code="prior_unavailable") from None


def _finalise_upload(path: Path, suffix: str, stem: str) -> str:
    name = stem + suffix
    os.replace(path, path.with_name(name))
    return name


async def _accept_upload(request: Request, ctx: AppContext, tenant: Tenant, job_id: str, paths: JobPaths) -> JobRecord:
    """Stream the form to the job's upload dir, validate it as the worker will load it, and
    return the record to create. Raises a 4xx ApiError for any bad part, 503
    storage_unavailable when the storage root refuses the upload."""
    with storage_errors("storing the upload"):
        form = await FormReader(paths.upload_dir, ctx.settings.limits).read(
            request.headers.get("content-type"), request.headers.get("content-length"), request.stream())
    params = parse_params(form.texts.get("params"), ctx)
    with storage_errors("storing the upload"):
        kind, suffix = classify_input(form.files["file"])
        input_name = _finalise_upload(form.files["file"], suffix, "input")
        depth_name = ""
        if "depth" in form.files:
            depth_name = _finalise_upload(form.files["depth"], classify_depth(form.files["depth"]), "depth")
    await ctx.upload_checks.run(check_capture, paths.upload_dir / input_name,
                                paths.upload_dir / depth_name if depth_name else None, params)
    return JobRecord(id=job_id, tenant=tenant.name, tenant_hash=tenant.hash, input_kind=kind,
                     input_file=input_name, depth_file=depth_name, params=params.model_dump_json())


@router.post("/jobs", status_code=202, response_model=JobView, responses=_ERRORS, openapi_extra=_MULTIPART_SCHEMA,
             summary="Submit an image or video for light-field estimation")
async def create_job(request: Request, tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    limit = ctx.settings.limits.max_jobs_in_flight
    if await run_in_threadpool(ctx.store.in_flight, tenant.hash) >= limit:  # before reading the body
        raise TooManyJobs(f"at most {limit} jobs may be queued or running per tenant")
    job_id = new_job_id()
    paths = JobPaths.for_job(ctx.settings.data_dir, tenant.hash, job_id)
    with storage_errors("storing the upload"):
        paths.upload_dir.mkdir(parents=True, exist_ok=False)
    try:
        record = await _accept_upload(request, ctx, tenant, job_id, paths)
        with storage_errors("storing the upload"):  # to the shared store (a no-op on the local one)
            await run_in_threadpool(ctx.files.push_uploads, paths)
        await run_in_threadpool(ctx.store.create, record, limit)  # atomic re-check of the limit
    except JobLimitReached as exc:
        await run_in_threadpool(ctx.files.delete_job, paths)
        raise TooManyJobs(str(exc)) from None
    except BaseException:  # including a client that disconnects mid-upload
        ctx.files.delete_job(paths)
        raise
    try:
        await run_in_threadpool(ctx.celery.send_task, TASK_NAME, args=[job_id])
    except Exception:
        log.exception("job %s: could not enqueue", job_id)
        await _fail_unqueued(ctx, job_id)
        await run_in_threadpool(ctx.files.delete_job, paths)
        raise ServiceUnavailable("the job queue is unreachable; try again later", code="broker_unavailable") from None
    view = JobView.of(await run_in_threadpool(ctx.store.get, job_id))
    return JSONResponse(view.model_dump(mode="json"), status_code=202, headers={"Location": f"/jobs/{job_id}"})


async def _fail_unqueued(ctx: AppContext, job_id: str, attempts: int = 6, pause_s: float = 0.5) -> None:
    """Mark a job whose message never reached the queue as failed, so it does not sit queued
    (and count against the tenant's limit) forever. Redis may be restarting: retry for ~3 s."""
    for _ in range(attempts):
        try:
            await run_in_threadpool(ctx.store.update, job_id, allowed=("queued",), state="failed",
                                    error_code="broker_unavailable", error_message="the job queue was unreachable",
                                    finished_at=time.time())
            return
        except broker_errors():
            await asyncio.sleep(pause_s)
    log.error("job %s: accepted but neither queued nor marked failed (Redis unreachable)", job_id)


@router.get("/jobs/{job_id}", response_model=JobView, responses=_ERRORS, summary="Status of a job")
def get_job(job_id: str, tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    record = owned_job(job_id, tenant, ctx)
    return JobView.of(record, ctx.store.cancel_requested(job_id) and not record.is_terminal)


@router.get("/jobs", response_model=JobList, responses=_ERRORS, summary="The caller's jobs, newest first")
def list_jobs(offset: int = Query(0, ge=0, le=MAX_OFFSET, description="jobs to skip (newest first)"),
              limit: int = Query(20, ge=1, description="page size (at most LIGHTFIELD_MAX_PAGE_SIZE)"),
              tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    if limit > ctx.settings.limits.max_page_size:
        raise InvalidInput(f"limit must be <= {ctx.settings.limits.max_page_size}", code="invalid_limit")
    records, total = ctx.store.list(tenant.hash, offset, limit)
    nxt = offset + limit if offset + limit < total else None
    return JobList(jobs=[JobView.of(r) for r in records], total=total, offset=offset, limit=limit, next_offset=nxt)


@router.delete("/jobs/{job_id}", status_code=204, responses={202: {"model": JobView}, **_ERRORS},
               summary="Cancel an active job (202), or delete a finished one and its artefacts (204)")
def delete_job(job_id: str, tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    record = owned_job(job_id, tenant, ctx)
    paths = JobPaths.for_job(ctx.settings.data_dir, record.tenant_hash, record.id)
    if record.is_terminal:
        # files first: a record is deleted only once nothing it owns is left, so a storage
        # fault never orphans files (the client is told, and DELETE can be retried)
        forget(record.id, ctx)
        left = ctx.files.delete_job(paths)
        if left:
            raise ServiceUnavailable(
                f"job {job_id}: its {' and '.join(left)} could not be deleted (storage unavailable); the job is "
                "kept so that DELETE can be retried", code="storage_unavailable", retry_after_s=RETRY_AFTER_STORAGE_S)
        ctx.store.delete(record)
        return Response(status_code=204)
    ctx.store.request_cancel(job_id)
    # Nobody runs it (still queued, or its worker died): cancel now rather than at the
    # next delivery. A worker holding the lease sees the flag within one step instead.
    if not ctx.store.lease_held(job_id):
        if ctx.store.update(job_id, allowed=("queued", "running"), state="cancelled", stage="cancelled",
                            finished_at=time.time(), eta_s=None):
            left = ctx.files.delete_job(paths)
            if left:
                ctx.store.update(job_id, message=f"its {' and '.join(left)} could not be deleted yet (storage "
                                                 "unavailable); DELETE again to retry")
    record = ctx.store.get(job_id) or record
    return JSONResponse(JobView.of(record, cancel_requested=not record.is_terminal).model_dump(mode="json"),
                        status_code=202)


@router.get("/jobs/{job_id}/events", responses={200: {"content": {"text/event-stream": {}}}, **_ERRORS},
            summary="Server-Sent Events: the job record each time it changes; ends when the job ends")
async def job_events(job_id: str, request: Request, tenant: Tenant = Depends(get_tenant),
                     ctx: AppContext = Depends(get_ctx)):
    await run_in_threadpool(owned_job, job_id, tenant, ctx)

    async def stream():
        version, idle = -1, 0.0
        while True:
            try:
                record = await run_in_threadpool(ctx.store.get, job_id)
            except broker_errors():  # the stream has started: say so in-band, and end it
                yield f"event: error\ndata: {json.dumps({'code': 'broker_unavailable', 'message': BROKER_DOWN})}\n\n"
                return
            if record is None:
                yield "event: deleted\ndata: {}\n\n"
                return
            if record.version != version:
                version, idle = record.version, 0.0
                data = json.dumps(JobView.of(record).model_dump(mode="json"))
                yield f"id: {version}\nevent: job\ndata: {data}\n\n"
                if record.is_terminal:
                    return
            elif idle >= SSE_KEEPALIVE_S:
                idle = 0.0
                yield ": keep-alive\n\n"
            if await request.is_disconnected():
                return
            await asyncio.sleep(SSE_POLL_S)
            idle += SSE_POLL_S

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
