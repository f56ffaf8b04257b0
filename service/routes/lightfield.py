"""/lightfield/{id}: metadata and queries of a finished job's light field."""
from __future__ import annotations

import base64
import io
from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, Query, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, StreamingResponse

from core.conventions import CONVENTIONS_SUMMARY
from service import queries
from service.context import AppContext, Tenant, get_ctx, get_tenant, owned_job
from service.errors import Conflict, ErrorBody, InvalidInput
from service.fieldcache import CachedField
from service.models import (
    CubemapFace, CubemapResponse, DominantLight, EncodedEnvmap, EnvmapBatchRequest, EnvmapBatchResponse,
    EnvmapFormat, Flags, LightfieldInfo, Quality, SHLayout, SphericalHarmonics,
)

router = APIRouter(tags=["lightfield"])
_ERRORS = {s: {"model": ErrorBody} for s in (401, 404, 409, 413, 422)}
CONVENTIONS_HEADER = "X-Lightfield-Conventions"
EXTRAPOLATED_HEADER = "X-Lightfield-Extrapolated"
CUBE_FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
SH_BAND_ORDER = ("coefficient k = 0..8 is (l, m) = (0,0), (1,-1), (1,0), (1,1), (2,-2), (2,-1), (2,0), (2,1), "
                 "(2,2), i.e. 1, y, z, x, xy, yz, 3z^2-1, xz, x^2-y^2; 27 floats = 9 coefficients x RGB interleaved; "
                 "layout arcore: odd m negated (Condon-Shortley phase); layout threejs: SphericalHarmonics3.fromArray "
                 "(no phase) (docs/conventions.md, docs/integrations.md)")
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


def _encode(hdr: np.ndarray, fmt: str, ev: float, attributes: dict | None = None) -> tuple[bytes, str]:
    from core.io.envmap_io import encode_envmap

    return encode_envmap(hdr, fmt, ev, attributes=attributes)


def _attributes(point, t: float, job_id: str, flags: queries.EvalFlags) -> dict:
    from core.export.products import envmap_exr_attributes

    return envmap_exr_attributes(point, t, job_id, flags.header())


def _download(data: bytes, media_type: str, filename: str, flags: queries.EvalFlags) -> Response:
    return Response(data, media_type=media_type, headers={
        CONVENTIONS_HEADER: CONVENTIONS_SUMMARY, EXTRAPOLATED_HEADER: flags.header(),
        "Content-Disposition": f'attachment; filename="{filename}"'})


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
    data, media_type = await run_in_threadpool(_encode, hdr, format, ev, _attributes(point, t, job_id, flags))
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
            summary="ARCore-style lighting: main light + ambient SH (ARCore or three.js layout)")
async def get_sh(job_id: str, response: Response, x: str = Query(..., description=X_HELP), t: float = 0.0,
                 layout: SHLayout = Query("arcore", description="arcore: ARCore's signs; threejs: "
                                          "SphericalHarmonics3.fromArray / LightProbe"),
                 tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    from core.export.products import sh_in_layout
    from core.sh import to_arcore_27

    point, t = queries.parse_x(x), queries.check_t(t)
    cf = await _field_async(job_id, tenant, ctx)
    light, full_sh, flags = await run_in_threadpool(queries.spherical_harmonics, cf, point, t)
    response.headers[CONVENTIONS_HEADER] = CONVENTIONS_SUMMARY
    response.headers[EXTRAPOLATED_HEADER] = flags.header()
    return SphericalHarmonics(
        x=point, t=t, extrapolated=Flags(x=flags.x, t=flags.t), layout=layout,
        coefficients=sh_in_layout(light.ambient_sh, layout), coefficients_with_light=sh_in_layout(full_sh, layout),
        arcore_27=to_arcore_27(light.ambient_sh), band_order=SH_BAND_ORDER,
        dominant_light=DominantLight(
            direction=tuple(float(v) for v in light.direction), intensity=tuple(float(v) for v in light.intensity_rgb),
            solid_angle=float(light.solid_angle), found=bool(light.found), confidence=float(light.confidence),
            reason=light.reason),
    )


@router.get("/lightfield/{job_id}/cubemap", responses={
    200: {"model": CubemapResponse, "content": {"application/x-npy": {}},
          "description": "format=ktx2: one KTX2 file (RGBA16F cube, GGX roughness mips); format=npy: float32 array "
                         "[6, size, size, 3]; format=json: one EXR per face, base64 (kept for compatibility)"},
    **_ERRORS}, summary="Cube map faces +X, -X, +Y, -Y, +Z, -Z at (x, t); prefiltered mips as KTX2")
async def get_cubemap(job_id: str, x: str = Query(..., description=X_HELP), t: float = 0.0,
                      size: int = Query(64, ge=1, description="face edge in texels (a power of two for ktx2)"),
                      format: Literal["json", "npy", "ktx2"] = "json",
                      levels: int | None = Query(None, ge=1, le=16, description="ktx2 only: mip levels, roughness "
                                                 "i / (levels - 1); default: down to size/32 (6 for 128); 1 = mirror only"),
                      tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    point, t = queries.parse_x(x), queries.check_t(t)
    queries.check_size(size, ctx.settings.limits.max_cubemap_size, "size")
    if format == "ktx2":
        _check_cube_size(size, levels)
    cf = await _field_async(job_id, tenant, ctx)
    if format == "ktx2":
        from core.export.products import cube_ktx2, cube_source_height

        hdr, flags = await run_in_threadpool(queries.envmap, cf, point, t, cube_source_height(size))
        data = await run_in_threadpool(cube_ktx2, hdr, size, levels)
        return _download(data, "image/ktx2", "cubemap.ktx2", flags)
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


def _check_cube_size(size: int, levels: int | None) -> None:
    if size & (size - 1):
        raise InvalidInput(f"size must be a power of two for prefiltered cube maps, got {size}", code="invalid_query")
    if levels is not None and levels > size.bit_length():
        raise InvalidInput(f"levels={levels} exceeds the {size.bit_length()} mips of a {size}-texel face",
                           code="invalid_query")


@router.get("/lightfield/{job_id}/gltf", response_class=Response, responses={
    200: {"content": {"model/gltf-binary": {}}, "description": "glTF 2.0 binary with EXT_lights_image_based"},
    **_ERRORS}, summary="glTF (.glb) image-based light at (x, t): irradiance SH + prefiltered specular cube mips")
async def get_gltf(job_id: str, x: str = Query(..., description=X_HELP), t: float = 0.0,
                   size: int = Query(64, ge=1, description="specular cube face edge (a power of two)"),
                   levels: int | None = Query(None, ge=1, le=16, description="specular mips (roughness 0..1)"),
                   tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    from core.export.products import cube_source_height, probe_glb

    point, t = queries.parse_x(x), queries.check_t(t)
    queries.check_size(size, ctx.settings.limits.max_cubemap_size, "size")
    _check_cube_size(size, levels)
    cf = await _field_async(job_id, tenant, ctx)
    hdr, flags = await run_in_threadpool(queries.envmap, cf, point, t, cube_source_height(size))
    data = await run_in_threadpool(probe_glb, hdr, point, t, size, levels, job_id)
    return _download(data, "model/gltf-binary", "probe.glb", flags)


@router.get("/lightfield/{job_id}/usdz", response_class=Response, responses={
    200: {"content": {"model/vnd.usdz+zip": {}}, "description": "USD package: DomeLight + its EXR (OpenEXR latlong)"},
    **_ERRORS}, summary="USD (.usdz) dome light at (x, t)")
async def get_usdz(job_id: str, x: str = Query(..., description=X_HELP), t: float = 0.0,
                   height: int = Query(256, ge=1, description="rows of the dome's latlong EXR (width = 2 x height)"),
                   tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    from core.export.products import probe_usdz

    point, t = queries.parse_x(x), queries.check_t(t)
    queries.check_size(height, ctx.settings.limits.max_envmap_height, "height")
    cf = await _field_async(job_id, tenant, ctx)
    hdr, flags = await run_in_threadpool(queries.envmap, cf, point, t, height)
    data = await run_in_threadpool(probe_usdz, hdr, point, t, job_id)
    return _download(data, "model/vnd.usdz+zip", "probe.usdz", flags)


@router.get("/lightfield/{job_id}/sequence", response_class=StreamingResponse, responses={
    200: {"content": {"application/zip": {}}, "description": "envmap.0001.exr ... + sequence.json, streamed"},
    **_ERRORS}, summary="EXR sequence of env maps at one probe over a time range (a zip, streamed)")
async def get_sequence(job_id: str, x: str = Query(..., description=X_HELP),
                       t0: float = Query(..., description="first time, seconds"),
                       t1: float = Query(..., description="last time, seconds (inclusive)"),
                       frames: int = Query(..., ge=1, description="evenly spaced frames from t0 to t1"),
                       height: int = Query(64, ge=1, description="rows (width = 2 x height)"),
                       first_frame: int = Query(1, ge=0, description="number of the first file (envmap.0001.exr)"),
                       quality: Quality = Query("exact", description="fast = the baked lattice (large maps, long shots)"),
                       tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    from core.export.sequence import sequence_members, sequence_times, zip_stream

    point, t0, t1 = queries.parse_x(x), queries.check_t(t0), queries.check_t(t1)
    queries.check_size(height, ctx.settings.limits.max_envmap_height, "height")
    queries.check_size(frames, ctx.settings.limits.max_sequence_frames, "frames")
    if t1 < t0:
        raise InvalidInput(f"t1 ({t1}) must not be before t0 ({t0})", code="invalid_t")
    cf = await _field_async(job_id, tenant, ctx)
    times = sequence_times(t0, t1, frames)
    for probe_t in {times[0], times[-1]}:  # refuse a bad query now, not after the 200 is sent
        await run_in_threadpool(queries.envmap, cf, point, probe_t, 1)
    maps = ((t, hdr) for t, hdr, _ in queries.envmap_sequence(cf, point, times, height, quality))
    members = sequence_members(maps, point, job_id, first_frame=first_frame, extra={"height": height, "quality": quality})
    return StreamingResponse(zip_stream(members), media_type="application/zip", headers={
        CONVENTIONS_HEADER: CONVENTIONS_SUMMARY, "Content-Disposition": 'attachment; filename="envmaps.zip"'})
