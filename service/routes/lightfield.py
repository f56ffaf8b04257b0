"""/lightfield/{id}: metadata and queries of a finished job's light field."""
from __future__ import annotations

import asyncio
import base64
import io
from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, Query, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from core.conventions import CONVENTIONS_SUMMARY
from service import queries
from service.context import AppContext, Tenant, get_ctx, get_tenant
from service.errors import ErrorBody, PayloadTooLarge
from service.fieldcache import CachedField
from service.lightfields import job_field, recent_field
from service.models import (
    CubemapFace, CubemapResponse, DominantLight, EncodedEnvmap, EnvmapBatchRequest, EnvmapBatchResponse,
    EnvmapFormat, Flags, LightfieldInfo, Quality, SphericalHarmonics,
)
from service.queries import DEFAULT_QUALITY, MAX_ABS_EV, MAX_ABS_T_S, X_PATTERN

router = APIRouter(tags=["lightfield"])
_ERRORS = {s: {"model": ErrorBody} for s in (401, 404, 409, 410, 413, 422, 503)}
CONVENTIONS_HEADER = "X-Lightfield-Conventions"
EXTRAPOLATED_HEADER = "X-Lightfield-Extrapolated"
QUALITY_HEADER = "X-Lightfield-Quality"
CUBE_FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
SH_BAND_ORDER = ("ARCore order: coefficient k = 0..8 is (l, m) = (0,0), (1,-1), (1,0), (1,1), (2,-2), (2,-1), "
                 "(2,0), (2,1), (2,2); 27 floats = 9 coefficients x RGB interleaved; Condon-Shortley phase "
                 "(see docs/conventions.md)")
X_HELP = "world position 'X,Y,Z' in metres: three finite numbers, each within +-1e6"
T_HELP = "seconds from the first frame"
QUALITY_HELP = ("fast (default) = the worker's baked lattice of env maps, interpolated in x and t and upsampled "
                "to the requested height; exact = evaluate the field at every pixel (slower: see docs/api.md)")
MAX_BATCH_PIXELS = 1 << 23  # env map pixels per POST /envmaps (8 Mpx = 96 MB of float32)

XQuery = Query(..., description=X_HELP, examples=["0,1.2,-2"], pattern=X_PATTERN, max_length=200)
TQuery = Query(0.0, description=T_HELP, ge=-MAX_ABS_T_S, le=MAX_ABS_T_S)
QualityQuery = Query(DEFAULT_QUALITY, description=QUALITY_HELP)


async def _field(job_id: str, tenant: Tenant, ctx: AppContext) -> CachedField:
    return recent_field(job_id, tenant, ctx) or await run_in_threadpool(job_field, job_id, tenant, ctx)


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array, dtype=np.float32), allow_pickle=False)
    return buf.getvalue()


def _encoder(fmt: str, ev: float):
    from core.io.envmap_io import encode_envmap

    # uncompressed EXR: ZIP saves 2-11 % on float32 radiance for 5-15x the encoding time
    return lambda hdr: encode_envmap(hdr, fmt, ev, compress=False)


def _query_headers(flags: queries.EvalFlags, quality: str) -> dict[str, str]:
    return {CONVENTIONS_HEADER: CONVENTIONS_SUMMARY, EXTRAPOLATED_HEADER: flags.header(), QUALITY_HEADER: quality}


@router.get("/lightfield/{job_id}", response_model=LightfieldInfo, responses=_ERRORS,
            summary="Artefact metadata: bounds, time range, conventions, temporal decision, prior, training stats")
async def lightfield_info(job_id: str, tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    cf = await _field(job_id, tenant, ctx)
    return LightfieldInfo(id=job_id, conventions=CONVENTIONS_SUMMARY, metadata=dict(cf.artefact.meta),
                          fast_available=True)


@router.get("/lightfield/{job_id}/envmap", response_class=Response, responses={
    200: {"content": {t: {} for t in ("image/x-exr", "image/vnd.radiance", "image/png", "application/x-npy")},
          "description": "equirect H x 2H env map in the project's conventions"}, **_ERRORS},
    summary="Environment map at (x, t)")
async def get_envmap(
    job_id: str,
    x: str = XQuery,
    t: float = TQuery,
    height: int = Query(64, ge=1, description="rows; width = 2 x height (at most LIGHTFIELD_MAX_ENVMAP_HEIGHT)"),
    format: EnvmapFormat = Query("exr"),
    ev: float = Query(0.0, ge=-MAX_ABS_EV, le=MAX_ABS_EV,
                      description="exposure of the PNG preview (2^ev scale before the tone map)"),
    quality: Quality = QualityQuery,
    tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx),
):
    point, t, ev = queries.parse_x(x), queries.check_t(t), queries.check_ev(ev)
    limits = ctx.settings.limits
    queries.check_size(height, limits.max_envmap_height, "height")
    cf = await _field(job_id, tenant, ctx)
    answer = await queries.envmap_answer(ctx, cf, point, t, height, quality, finish=_encoder(format, ev))
    data, media_type = answer.value
    return Response(data, media_type=media_type, headers={
        **_query_headers(answer.flags, answer.quality), "Content-Disposition": f'inline; filename="envmap.{format}"'})


@router.post("/lightfield/{job_id}/envmaps", response_model=EnvmapBatchResponse, responses=_ERRORS,
             summary="Environment maps at many (x, t) at once")
async def post_envmaps(job_id: str, body: EnvmapBatchRequest, response: Response,
                       tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    limits = ctx.settings.limits
    queries.check_size(len(body.queries), limits.max_batch, "batch")
    queries.check_size(body.height, limits.max_envmap_height, "height")
    pixels = len(body.queries) * 2 * body.height ** 2
    if pixels > MAX_BATCH_PIXELS:
        raise PayloadTooLarge(f"{len(body.queries)} maps of height {body.height} are {pixels} pixels; at most "
                              f"{MAX_BATCH_PIXELS} per request", code="batch_too_large")
    cf = await _field(job_id, tenant, ctx)
    encode = _encoder(body.format, body.ev)
    answers = await asyncio.gather(*(
        queries.envmap_answer(ctx, cf, q.x, q.t, body.height, body.quality, finish=encode)
        for q in body.queries))
    response.headers[CONVENTIONS_HEADER] = CONVENTIONS_SUMMARY
    response.headers[QUALITY_HEADER] = body.quality
    return EnvmapBatchResponse(height=body.height, width=2 * body.height, format=body.format, items=[
        EncodedEnvmap(x=q.x, t=q.t, extrapolated=Flags(x=a.flags.x, t=a.flags.t), media_type=a.value[1],
                      data_base64=base64.b64encode(a.value[0]).decode())
        for q, a in zip(body.queries, answers)
    ])


@router.get("/lightfield/{job_id}/sh", response_model=SphericalHarmonics, responses=_ERRORS,
            summary="ARCore-style lighting: ambient SH (27 floats) + dominant light")
async def get_sh(job_id: str, response: Response, x: str = XQuery, t: float = TQuery,
                 quality: Quality = QualityQuery,
                 tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    point, t = queries.parse_x(x), queries.check_t(t)
    cf = await _field(job_id, tenant, ctx)
    answer = await queries.envmap_answer(ctx, cf, point, t, queries.SH_ENVMAP_HEIGHT, quality,
                                         finish=queries.sh_from_envmap)
    coeffs, light = answer.value
    response.headers.update(_query_headers(answer.flags, answer.quality))
    flags = answer.flags
    return SphericalHarmonics(
        x=point, t=t, extrapolated=Flags(x=flags.x, t=flags.t), arcore_27=coeffs, band_order=SH_BAND_ORDER,
        dominant_light=DominantLight(
            direction=tuple(float(v) for v in light.direction), intensity=tuple(float(v) for v in light.intensity_rgb),
            solid_angle=float(light.solid_angle), found=bool(light.found)),
    )


@router.get("/lightfield/{job_id}/cubemap", responses={
    200: {"model": CubemapResponse, "content": {"application/x-npy": {}},
          "description": "format=json: one EXR per face, base64; format=npy: float32 array [6, size, size, 3]"},
    **_ERRORS}, summary="Cube map faces +X, -X, +Y, -Y, +Z, -Z at (x, t)")
async def get_cubemap(job_id: str, x: str = XQuery, t: float = TQuery,
                      size: int = Query(64, ge=1, description="face edge in texels (at most LIGHTFIELD_MAX_CUBEMAP_SIZE)"),
                      format: Literal["json", "npy"] = "json", quality: Quality = QualityQuery,
                      tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    point, t = queries.parse_x(x), queries.check_t(t)
    limits = ctx.settings.limits
    queries.check_size(size, limits.max_cubemap_size, "size")
    cf = await _field(job_id, tenant, ctx)

    def finish(hdr: np.ndarray):
        faces = queries.cube_faces(hdr, size)
        if format == "npy":
            return _npy(faces)
        from core.io.exr import encode_exr

        return [base64.b64encode(encode_exr(face, compress=False)).decode() for face in faces]

    answer = await queries.envmap_answer(ctx, cf, point, t, queries.cubemap_height(size), quality, finish=finish)
    headers = _query_headers(answer.flags, answer.quality)
    if format == "npy":
        return Response(answer.value, media_type="application/x-npy", headers=headers)
    flags = answer.flags
    body = CubemapResponse(x=point, t=t, size=size, extrapolated=Flags(x=flags.x, t=flags.t), faces=[
        CubemapFace(name=name, media_type="image/x-exr", data_base64=data) for name, data in zip(CUBE_FACES, answer.value)
    ])
    return JSONResponse(body.model_dump(mode="json"), headers=headers)
