"""/lightfield/{id}: metadata and queries of a finished job's light field."""
from __future__ import annotations

import base64
import io
from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, Query, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from core.conventions import CONVENTIONS_SUMMARY
from service import queries
from service.context import AppContext, Tenant, get_ctx, get_tenant, owned_job
from service.errors import Conflict, ErrorBody, InvalidInput
from service.fieldcache import CachedField
from service.models import (
    CubemapFace, CubemapResponse, DominantLight, EncodedEnvmap, EnvmapBatchRequest, EnvmapBatchResponse,
    EnvmapFormat, Flags, LightfieldInfo, Quality, SphericalHarmonics,
)

router = APIRouter(tags=["lightfield"])
_ERRORS = {s: {"model": ErrorBody} for s in (401, 404, 409, 413, 422)}
CONVENTIONS_HEADER = "X-Lightfield-Conventions"
EXTRAPOLATED_HEADER = "X-Lightfield-Extrapolated"
CUBE_FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
SH_BAND_ORDER = ("ARCore order: coefficient k = 0..8 is (l, m) = (0,0), (1,-1), (1,0), (1,1), (2,-2), (2,-1), "
                 "(2,0), (2,1), (2,2); 27 floats = 9 coefficients x RGB interleaved; Condon-Shortley phase "
                 "(see docs/conventions.md)")
X_HELP = "world position 'X,Y,Z' in metres (three finite numbers)"


def _field(job_id: str, tenant: Tenant, ctx: AppContext) -> CachedField:
    record = owned_job(job_id, tenant, ctx)
    if record.state != "succeeded":
        raise Conflict(f"job {job_id} is {record.state}; its light field exists once it has succeeded",
                       code="not_ready")
    return ctx.fields.get(record.id, ctx.settings.data_dir / record.artefact)


async def _field_async(job_id: str, tenant: Tenant, ctx: AppContext) -> CachedField:
    return await run_in_threadpool(_field, job_id, tenant, ctx)


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array, dtype=np.float32), allow_pickle=False)
    return buf.getvalue()


def _encode(hdr: np.ndarray, fmt: str, ev: float) -> tuple[bytes, str]:
    from core.io.envmap_io import encode_envmap

    return encode_envmap(hdr, fmt, ev)


@router.get("/lightfield/{job_id}", response_model=LightfieldInfo, responses=_ERRORS,
            summary="Artefact metadata: bounds, time range, conventions, temporal decision, prior, training stats")
async def lightfield_info(job_id: str, tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    cf = await _field_async(job_id, tenant, ctx)
    return LightfieldInfo(id=job_id, conventions=CONVENTIONS_SUMMARY, metadata=dict(cf.artefact.meta),
                          fast_available=True)


@router.get("/lightfield/{job_id}/envmap", response_class=Response, responses={
    200: {"content": {t: {} for t in ("image/x-exr", "image/vnd.radiance", "image/png", "application/x-npy")},
          "description": "equirect H x 2H env map in the project's conventions"}, **_ERRORS},
    summary="Environment map at (x, t)")
async def get_envmap(
    job_id: str,
    x: str = Query(..., description=X_HELP, examples=["0,1.2,-2"]),
    t: float = Query(0.0, description="seconds from the first frame"),
    height: int = Query(64, ge=1, description="rows; width = 2 x height"),
    format: EnvmapFormat = Query("exr"),
    ev: float = Query(0.0, description="exposure of the PNG preview (2^ev scale before the tone map)"),
    quality: Quality = Query("exact", description="exact = evaluate the field; fast = baked grid when available"),
    tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx),
):
    point, t, ev = queries.parse_x(x), queries.check_t(t), queries.check_ev(ev)
    queries.check_size(height, ctx.settings.limits.max_envmap_height, "height")
    cf = await _field_async(job_id, tenant, ctx)
    hdr, flags, used = await run_in_threadpool(queries.envmap_with_quality, cf, point, t, height, quality)
    data, media_type = await run_in_threadpool(_encode, hdr, format, ev)
    return Response(data, media_type=media_type, headers={
        CONVENTIONS_HEADER: CONVENTIONS_SUMMARY, EXTRAPOLATED_HEADER: flags.header(),
        "X-Lightfield-Quality": used, "Content-Disposition": f'inline; filename="envmap.{format}"',
    })


@router.post("/lightfield/{job_id}/envmaps", response_model=EnvmapBatchResponse, responses=_ERRORS,
             summary="Environment maps at many (x, t) at once")
async def post_envmaps(job_id: str, body: EnvmapBatchRequest, response: Response,
                       tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    limits = ctx.settings.limits
    queries.check_size(len(body.queries), limits.max_batch, "batch")
    queries.check_size(body.height, limits.max_envmap_height, "height")
    ev = queries.check_ev(body.ev)
    for i, q in enumerate(body.queries):
        if not all(np.isfinite(q.x)) or not np.isfinite(q.t):
            raise InvalidInput(f"queries[{i}]: x and t must be finite", code="invalid_x")
    cf = await _field_async(job_id, tenant, ctx)
    xs = [q.x for q in body.queries]
    ts = [q.t for q in body.queries]
    hdrs, flags = await run_in_threadpool(queries.envmaps, cf, xs, ts, body.height)

    def encode_all():
        return [_encode(h, body.format, ev) for h in hdrs]

    encoded = await run_in_threadpool(encode_all)
    response.headers[CONVENTIONS_HEADER] = CONVENTIONS_SUMMARY
    return EnvmapBatchResponse(height=body.height, width=2 * body.height, format=body.format, items=[
        EncodedEnvmap(x=q.x, t=q.t, extrapolated=Flags(x=f.x, t=f.t), media_type=mt,
                      data_base64=base64.b64encode(data).decode())
        for q, f, (data, mt) in zip(body.queries, flags, encoded)
    ])


@router.get("/lightfield/{job_id}/sh", response_model=SphericalHarmonics, responses=_ERRORS,
            summary="ARCore-style lighting: ambient SH (27 floats) + dominant light")
async def get_sh(job_id: str, response: Response, x: str = Query(..., description=X_HELP), t: float = 0.0,
                 tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    point, t = queries.parse_x(x), queries.check_t(t)
    cf = await _field_async(job_id, tenant, ctx)
    coeffs, light, flags = await run_in_threadpool(queries.spherical_harmonics, cf, point, t)
    response.headers[CONVENTIONS_HEADER] = CONVENTIONS_SUMMARY
    response.headers[EXTRAPOLATED_HEADER] = flags.header()
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
async def get_cubemap(job_id: str, x: str = Query(..., description=X_HELP), t: float = 0.0,
                      size: int = Query(64, ge=1, description="face edge in texels"),
                      format: Literal["json", "npy"] = "json",
                      tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    point, t = queries.parse_x(x), queries.check_t(t)
    queries.check_size(size, ctx.settings.limits.max_cubemap_size, "size")
    cf = await _field_async(job_id, tenant, ctx)
    faces, flags = await run_in_threadpool(queries.cubemap, cf, point, t, size)
    headers = {CONVENTIONS_HEADER: CONVENTIONS_SUMMARY, EXTRAPOLATED_HEADER: flags.header()}
    if format == "npy":
        return Response(_npy(faces), media_type="application/x-npy", headers=headers)

    def encode_faces():
        from core.io.exr import encode_exr

        return [base64.b64encode(encode_exr(face)).decode() for face in faces]

    encoded = await run_in_threadpool(encode_faces)
    body = CubemapResponse(x=point, t=t, size=size, extrapolated=Flags(x=flags.x, t=flags.t), faces=[
        CubemapFace(name=name, media_type="image/x-exr", data_base64=data) for name, data in zip(CUBE_FACES, encoded)
    ])
    return JSONResponse(body.model_dump(mode="json"), headers=headers)
