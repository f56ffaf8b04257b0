"""/lightfield/{id}: metadata and queries of a finished job's light field."""
from __future__ import annotations

import asyncio
import base64
import io
from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, StreamingResponse

from core.conventions import CONVENTIONS_SUMMARY
from core.export.arkit import arkit_probe
from core.export.probe_queries import (
    SH_ENVMAP_HEIGHT,
    UNITY_GRID_AXIS_MAX,
    UNITY_GRID_DEFAULT,
    UNITY_SH_HEIGHT,
    parse_grid,
)
from core.export.products import cube_for, cube_ktx2, cube_source_height, envmap_exr_attributes, probe_glb, probe_usdz
from core.export.schema import AnswerGrade
from core.export.sequence import sequence_fps, sequence_members, sequence_times, zip_stream
from core.export.sh_layouts import LAYOUTS
from core.export.unity import unity_probe_grid
from core.export.usd import USDUnavailable
from service import queries
from service.context import AppContext, Tenant, get_ctx, get_tenant
from service.errors import ErrorBody, InvalidInput, PayloadTooLarge, ServiceUnavailable
from service.exports import Cancellation, run_export, stream_export
from service.fieldcache import CachedField
from service.lightfields import job_field, recent_field
from service.models import (
    ArkitProbe,
    CubemapFace,
    CubemapResponse,
    EncodedEnvmap,
    EnvmapBatchRequest,
    EnvmapBatchResponse,
    EnvmapFormat,
    Flags,
    LightfieldInfo,
    Quality,
    SHLayout,
    SphericalHarmonics,
    UnityProbeGrid,
)
from service.queries import DEFAULT_QUALITY
from service.query_rules import MAX_ABS_EV, MAX_ABS_T_S, X_PATTERN

router = APIRouter(tags=["lightfield"])
_ERRORS = {s: {"model": ErrorBody} for s in (401, 404, 409, 410, 413, 422, 503)}
CONVENTIONS_HEADER = "X-Lightfield-Conventions"
EXTRAPOLATED_HEADER = "X-Lightfield-Extrapolated"
QUALITY_HEADER = "X-Lightfield-Quality"
GRADE_HEADER = "X-Lightfield-Grade"  # the self-check (core.engine.self_check): how well the field explains its frames
CUBE_FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
X_HELP = "world position 'X,Y,Z' in metres: three finite numbers, each within +-1e6"
T_HELP = "seconds from the first frame"
QUALITY_HELP = ("fast (default) = the field evaluated at (x, t) at a quarter of the rows (at least 16) and "
                "upsampled; exact = the field at every pixel; baked = the worker's lattice of maps interpolated "
                "in x and t (cheapest, least accurate near lights); costs and errors in docs/api.md")
MAX_BATCH_PIXELS = 1 << 23  # env map pixels per POST /envmaps (8 Mpx = 96 MB of float32)

XQuery = Query(..., description=X_HELP, examples=["0,1.2,-2"], pattern=X_PATTERN, max_length=200)
TQuery = Query(0.0, description=T_HELP, ge=-MAX_ABS_T_S, le=MAX_ABS_T_S)
QualityQuery = Query(DEFAULT_QUALITY, description=QUALITY_HELP)


async def _field_async(job_id: str, tenant: Tenant, ctx: AppContext) -> CachedField:
    """The job's loaded field: from memory when it was found succeeded a moment ago (no Redis
    round trip, no thread hop: the hot path), else checked and loaded in the threadpool."""
    return recent_field(job_id, tenant, ctx) or await run_in_threadpool(job_field, job_id, tenant, ctx)


def _grade(cf: CachedField) -> str:
    """'GRADE; residual_ratio=R; frames_explained=K/N; seen=S; filled=F[; fallback=constant map]' from the
    artefact's self-check ('unchecked' for an artefact made before the check)."""
    q = cf.artefact.meta.get("quality") or {}
    if not q.get("grade"):
        return "unchecked"
    answer = _answer_grade(cf)
    return (f"{q['grade']}; residual_ratio={q.get('residual_ratio')}; "
            f"frames_explained={q.get('frames_explained')}/{q.get('frames_checked')}; "
            f"seen={answer.seen_share}; filled={answer.filled_share}" + ("; fallback=constant map" if answer.fallback
                                                                          else ""))


def _answer_grade(cf: CachedField) -> AnswerGrade:
    """The grade and the share seen vs filled every JSON answer carries (core.export.schema.AnswerGrade)."""
    return AnswerGrade.of(cf.artefact.meta)


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array, dtype=np.float32), allow_pickle=False)
    return buf.getvalue()


def _encode(hdr: np.ndarray, fmt: str, ev: float, attributes: dict | None = None) -> tuple[bytes, str]:
    from core.io.envmap_io import encode_envmap  # noqa: PLC0415 — core.io.envmap_io pulls in av, cv2, OpenEXR, PIL: imported when used

    # uncompressed EXR: ZIP saves 2-11 % on float32 radiance for 5-15x the encoding time
    return encode_envmap(hdr, fmt, ev, attributes=attributes, compress=False)


def _attributes(point, t: float, job_id: str, flags: queries.EvalFlags) -> dict:
    return envmap_exr_attributes(point, t, job_id, flags.header())


def _download(data: bytes, media_type: str, filename: str, flags: queries.EvalFlags, grade: str) -> Response:
    return Response(data, media_type=media_type, headers={
        CONVENTIONS_HEADER: CONVENTIONS_SUMMARY, EXTRAPOLATED_HEADER: flags.header(), GRADE_HEADER: grade,
        "Content-Disposition": f'attachment; filename="{filename}"'})


@router.get("/lightfield/{job_id}", response_model=LightfieldInfo, responses=_ERRORS,
            summary="Artefact metadata: bounds, time range, conventions, temporal decision, prior, training stats")
async def lightfield_info(job_id: str, tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    cf = await _field_async(job_id, tenant, ctx)
    return LightfieldInfo(id=job_id, conventions=CONVENTIONS_SUMMARY, metadata=dict(cf.artefact.meta),
                          fast_available=True, grade=_answer_grade(cf))


@router.get("/lightfield/{job_id}/envmap", response_class=Response, responses={
    200: {"content": {t: {} for t in ("image/x-exr", "image/vnd.radiance", "image/png", "application/x-npy")},
          "description": "equirect H x 2H env map in the project's conventions"}, **_ERRORS},
    summary="Environment map at (x, t)")
async def get_envmap(
    job_id: str,
    request: Request,
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
    queries.check_size(height, ctx.settings.limits.max_envmap_height, "height")
    cf = await _field_async(job_id, tenant, ctx)

    def finish(hdr: np.ndarray, flags: queries.EvalFlags):  # in the batch's thread
        return _encode(hdr, format, ev, _attributes(point, t, job_id, flags) if format == "exr" else None)

    if queries.is_large(height, quality):  # an export: its own field copy, cancelled if the client leaves
        hdr, flags, used = await _export(request, ctx, queries.envmap_with_quality, cf, point, t, height, quality)
        data, media_type = await run_in_threadpool(finish, hdr, flags)
    else:
        answer = await queries.envmap_answer(ctx, cf, point, t, height, quality, finish=finish)
        (data, media_type), flags, used = answer.value, answer.flags, answer.quality
    return Response(data, media_type=media_type, headers={
        CONVENTIONS_HEADER: CONVENTIONS_SUMMARY, EXTRAPOLATED_HEADER: flags.header(),
        QUALITY_HEADER: used, GRADE_HEADER: _grade(cf), "Content-Disposition": f'inline; filename="envmap.{format}"',
    })


async def _export(request: Request, ctx: AppContext, fn, *args):
    """fn(*args, on_map) as a cancellable export (service.exports), counted in the metrics."""
    metrics = ctx.metrics
    on_map = (lambda quality: metrics.export_maps.labels(quality).inc()) if metrics is not None else None
    on_cancel = metrics.exports_cancelled.inc if metrics is not None else None
    return await run_export(request, fn, *args, on_map, on_cancel=on_cancel)


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
    cf = await _field_async(job_id, tenant, ctx)
    answers = await asyncio.gather(*(  # queued together: evaluated in one field call
        queries.envmap_answer(ctx, cf, q.x, q.t, body.height, body.quality,
                              finish=lambda hdr, _flags: _encode(hdr, body.format, body.ev))
        for q in body.queries))
    response.headers[CONVENTIONS_HEADER] = CONVENTIONS_SUMMARY
    response.headers[QUALITY_HEADER] = body.quality
    response.headers[GRADE_HEADER] = _grade(cf)
    return EnvmapBatchResponse(height=body.height, width=2 * body.height, format=body.format, grade=_answer_grade(cf),
                               items=[
        EncodedEnvmap(x=q.x, t=q.t, extrapolated=Flags(x=a.flags.x, t=a.flags.t), media_type=a.value[1],
                      data_base64=base64.b64encode(a.value[0]).decode())
        for q, a in zip(body.queries, answers)
    ])


def _layout_help() -> str:
    return "; ".join(layout.describe() for layout in LAYOUTS.values())


@router.get("/lightfield/{job_id}/sh", response_model=SphericalHarmonics, responses=_ERRORS,
            summary="ARCore-style lighting: main light + ambient SH, in a consumer's SH layout")
async def get_sh(job_id: str, response: Response, x: str = XQuery, t: float = TQuery,
                 layout: SHLayout = Query("arcore", description=_layout_help()),  # noqa: B008 — a help string
                 quality: Quality = QualityQuery,
                 tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    point, t = queries.parse_x(x), queries.check_t(t)
    cf = await _field_async(job_id, tenant, ctx)
    answer = await queries.envmap_answer(ctx, cf, point, t, SH_ENVMAP_HEIGHT, quality,
                                         finish=lambda hdr, _flags: queries.sh_from_envmap(hdr))
    light, full_sh = answer.value
    flags = answer.flags
    response.headers[CONVENTIONS_HEADER] = CONVENTIONS_SUMMARY
    response.headers[EXTRAPOLATED_HEADER] = flags.header()
    response.headers[QUALITY_HEADER] = answer.quality
    response.headers[GRADE_HEADER] = _grade(cf)
    doc = SphericalHarmonics.of(point, t, Flags(x=flags.x, t=flags.t), layout, light, full_sh)
    doc.grade = _answer_grade(cf)
    return doc


MAX_UNITY_PROBES = 512


def _counts(text: str) -> tuple[int, int, int]:
    try:
        values = parse_grid(text)
    except ValueError as exc:
        raise InvalidInput(str(exc), code="invalid_query") from None
    if values[0] * values[1] * values[2] > MAX_UNITY_PROBES:
        raise PayloadTooLarge(f"grid {text} has {values[0] * values[1] * values[2]} probes; at most {MAX_UNITY_PROBES}",
                              code="grid_too_large")
    return values


@router.get(
    "/lightfield/{job_id}/unity",
    response_model=UnityProbeGrid,
    responses=_ERRORS,
    summary="Unity light-probe grid: positions (ours and Unity's) + SphericalHarmonicsL2, extrapolated probes flagged",
)
async def get_unity(
    job_id: str,
    response: Response,
    grid: str = Query(
        ",".join(map(str, UNITY_GRID_DEFAULT)),
        description=f"probes per axis 'NX,NY,NZ' (each 1..{UNITY_GRID_AXIS_MAX}, at most {MAX_UNITY_PROBES} in all)",
        max_length=40,
    ),
    lo: str | None = Query(
        None,
        description="grid corner 'X,Y,Z' (our metres); default: the probes "
        "sit at the cell centres of the region the captures cover",
        pattern=X_PATTERN,
        max_length=200,
    ),
    hi: str | None = Query(
        None, description="opposite corner; default: that region's", pattern=X_PATTERN, max_length=200
    ),
    t: float | None = Query(
        None, description=T_HELP + " (required when the field varies over time)", ge=-MAX_ABS_T_S, le=MAX_ABS_T_S
    ),
    tenant: Tenant = Depends(get_tenant),
    ctx: AppContext = Depends(get_ctx),
):
    counts = _counts(grid)
    corner_lo, corner_hi = (None if v is None else queries.parse_x(v) for v in (lo, hi))
    t = None if t is None else queries.check_t(t)
    cf = await _field_async(job_id, tenant, ctx)

    def evaluate(point):
        hdr, flags = queries.envmap(cf, point, t, UNITY_SH_HEIGHT)
        return hdr, {"x": flags.x, "t": flags.t}

    doc = await run_in_threadpool(
        unity_probe_grid, evaluate, cf.artefact.bounds, counts, t, job_id, corner_lo, corner_hi, _answer_grade(cf)
    )
    response.headers[GRADE_HEADER] = _grade(cf)
    response.headers[CONVENTIONS_HEADER] = CONVENTIONS_SUMMARY
    response.headers[EXTRAPOLATED_HEADER] = "x" if doc.extrapolated_probes else "none"
    return doc


@router.get("/lightfield/{job_id}/arkit", response_model=ArkitProbe, responses=_ERRORS,
            summary="ARKit / RealityKit / SceneKit: Metal cube slices + SH planes + main light at (x, t)")
async def get_arkit(
    job_id: str,
    response: Response,
    x: str = XQuery,
    t: float = TQuery,
    size: int = Query(64, ge=1, description="cube face edge in texels (at most LIGHTFIELD_MAX_CUBEMAP_SIZE)"),
    pixel_format: Literal["rgba16Float", "rgba8Unorm_srgb"] = Query(
        "rgba16Float",
        description="rgba16Float: linear HDR (EnvironmentResource, lightingEnvironment); "
        "rgba8Unorm_srgb: what AREnvironmentProbeAnchor.environmentTexture holds (tone-mapped at ev)",
    ),
    ev: float = Query(0.0, ge=-MAX_ABS_EV, le=MAX_ABS_EV, description="exposure of the sRGB slices"),
    tenant: Tenant = Depends(get_tenant),
    ctx: AppContext = Depends(get_ctx),
):
    point, t, ev = queries.parse_x(x), queries.check_t(t), queries.check_ev(ev)
    queries.check_size(size, ctx.settings.limits.max_cubemap_size, "size")
    cf = await _field_async(job_id, tenant, ctx)
    hdr, flags = await run_in_threadpool(queries.envmap, cf, point, t, cube_source_height(size))
    doc = await run_in_threadpool(arkit_probe, hdr, point, t, Flags(x=flags.x, t=flags.t), size, pixel_format, ev)
    doc.grade = _answer_grade(cf)
    response.headers[GRADE_HEADER] = _grade(cf)
    response.headers[CONVENTIONS_HEADER] = CONVENTIONS_SUMMARY
    response.headers[EXTRAPOLATED_HEADER] = flags.header()
    return doc


@router.get("/lightfield/{job_id}/cubemap", responses={
    200: {"model": CubemapResponse, "content": {"application/x-npy": {}, "image/ktx2": {}},
          "description": "format=ktx2: one KTX2 file (RGBA16F cube, GGX roughness mips); format=npy: float32 array "
                         "[6, size, size, 3]; format=json: one EXR per face, base64 (kept for compatibility)"},
    **_ERRORS}, summary="Cube map faces +X, -X, +Y, -Y, +Z, -Z at (x, t); prefiltered mips as KTX2")
async def get_cubemap(
    job_id: str,
    request: Request,
    x: str = XQuery,
    t: float = TQuery,
    size: int = Query(
        64, ge=1, description="face edge in texels (a power of two for ktx2; at most LIGHTFIELD_MAX_CUBEMAP_SIZE)"
    ),
    format: Literal["json", "npy", "ktx2"] = "json",
    quality: Quality = QualityQuery,
    levels: int | None = Query(
        None,
        ge=1,
        le=16,
        description="ktx2 only: mip levels, roughness "
        "i / (levels - 1); default: down to size/32 (6 for 128); 1 = mirror only",
    ),
    layout: Literal["gl", "threejs"] = Query(
        "gl",
        description="gl: the OpenGL/Vulkan/Metal face table (Babylon, Filament, ARCore, "
        "engines reading KTX2 cubes); threejs: mirrored in x for a three.js CubeTexture, which "
        "three samples at (-x, y, z) (docs/integrations.md has the recipe)",
    ),
    tenant: Tenant = Depends(get_tenant),
    ctx: AppContext = Depends(get_ctx),
):
    point, t = queries.parse_x(x), queries.check_t(t)
    queries.check_size(size, ctx.settings.limits.max_cubemap_size, "size")
    if format == "ktx2":
        _check_cube_size(size, levels)
    cf = await _field_async(job_id, tenant, ctx)
    if format == "ktx2":
        hdr, flags, used = await _export(request, ctx, queries.envmap_with_quality, cf, point, t,
                                         cube_source_height(size), quality)
        data = await run_in_threadpool(cube_ktx2, hdr, size, levels, layout)
        return _download(data, "image/ktx2", "cubemap.ktx2", flags, _grade(cf))

    def finish(hdr: np.ndarray, _flags):  # in the batch's thread
        faces = queries.cube_faces(cube_for(hdr, layout).numpy(), size)
        if format == "npy":
            return _npy(faces)
        from core.io.exr import encode_exr  # noqa: PLC0415 — core.io.exr pulls in av, cv2, OpenEXR, PIL: imported when used

        return [base64.b64encode(encode_exr(face, compress=False)).decode() for face in faces]

    answer = await queries.envmap_answer(ctx, cf, point, t, queries.cubemap_height(size), quality, finish=finish)
    flags = answer.flags
    headers = {CONVENTIONS_HEADER: CONVENTIONS_SUMMARY, EXTRAPOLATED_HEADER: flags.header(),
               QUALITY_HEADER: answer.quality, GRADE_HEADER: _grade(cf)}
    if format == "npy":
        return Response(answer.value, media_type="application/x-npy", headers=headers)
    body = CubemapResponse(x=point, t=t, size=size, extrapolated=Flags(x=flags.x, t=flags.t), grade=_answer_grade(cf),
                           faces=[
        CubemapFace(name=name, media_type="image/x-exr", data_base64=data)
        for name, data in zip(CUBE_FACES, answer.value)
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
    **_ERRORS}, summary="glTF (.glb) image-based light at (x, t): irradiance SH + prefiltered specular cube mips "
                         "(+ the main light as KHR_lights_punctual)")
async def get_gltf(
    job_id: str,
    request: Request,
    x: str = XQuery,
    t: float = TQuery,
    size: int = Query(64, ge=1, description="specular cube face edge (a power of two)"),
    levels: int | None = Query(None, ge=1, le=16, description="specular mips (roughness 0..1)"),
    main_light: bool = Query(
        True,
        description="add the main light (when found) as a KHR_lights_punctual "
        "directional light, with the ambient SH as irradiance; false: the whole "
        "map's SH and no punctual light",
    ),
    tenant: Tenant = Depends(get_tenant),
    ctx: AppContext = Depends(get_ctx),
):
    point, t = queries.parse_x(x), queries.check_t(t)
    queries.check_size(size, ctx.settings.limits.max_cubemap_size, "size")
    _check_cube_size(size, levels)
    cf = await _field_async(job_id, tenant, ctx)
    hdr, flags, _ = await _export(request, ctx, queries.envmap_with_quality, cf, point, t, cube_source_height(size),
                                  "exact")
    data = await run_in_threadpool(probe_glb, hdr, point, t, size, levels, job_id, main_light,
                                   _answer_grade(cf).model_dump())
    return _download(data, "model/gltf-binary", "probe.glb", flags, _grade(cf))


@router.get("/lightfield/{job_id}/usdz", response_class=Response, responses={
    200: {"content": {"model/vnd.usdz+zip": {}}, "description": "USD package: DomeLight + its EXR (OpenEXR latlong)"},
    **_ERRORS}, summary="USD (.usdz) dome light at (x, t)")
async def get_usdz(job_id: str, request: Request, x: str = XQuery, t: float = TQuery,
                   height: int = Query(256, ge=1, description="rows of the dome's latlong EXR (width = 2 x height)"),
                                  tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    point, t = queries.parse_x(x), queries.check_t(t)
    queries.check_size(height, ctx.settings.limits.max_envmap_height, "height")
    cf = await _field_async(job_id, tenant, ctx)
    hdr, flags, _ = await _export(request, ctx, queries.envmap_with_quality, cf, point, t, height, "exact")
    try:
        data = await run_in_threadpool(probe_usdz, hdr, point, t, job_id, _answer_grade(cf).model_dump())
    except USDUnavailable as exc:
        raise ServiceUnavailable(str(exc), code="usd_unavailable") from exc
    return _download(data, "model/vnd.usdz+zip", "probe.usdz", flags, _grade(cf))


@router.get("/lightfield/{job_id}/sequence", response_class=StreamingResponse, responses={
    200: {"content": {"application/zip": {}}, "description": "envmap.0001.exr ... + sequence.json, streamed"},
    **_ERRORS}, summary="EXR sequence of env maps at one probe over a time range (a zip, streamed)")
async def get_sequence(job_id: str, x: str = XQuery,
                       t0: float = Query(..., description="first time, seconds", ge=-MAX_ABS_T_S, le=MAX_ABS_T_S),
                       t1: float = Query(..., description="last time, seconds (inclusive)", ge=-MAX_ABS_T_S,
                                         le=MAX_ABS_T_S),
                       frames: int = Query(..., ge=1, description="evenly spaced frames from t0 to t1"),
                       height: int = Query(64, ge=1, description="rows (width = 2 x height)"),
                       first_frame: int = Query(1, ge=0, description="number of the first file (envmap.0001.exr)"),
                       quality: Quality = Query("exact", description=QUALITY_HELP.replace(" (default)", "") +  # noqa: B008 — a help string
                                                "; this route's default is exact"),
                       colour: Literal["rec709", "acescg"] = Query(
                           "rec709", description="pixel colour space: linear Rec. 709 (as estimated) or ACEScg (AP1 "
                           "primaries, ACES white, Bradford-adapted; the EXR chromaticities say which)"),
                       tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    point, t0, t1 = queries.parse_x(x), queries.check_t(t0), queries.check_t(t1)
    queries.check_size(height, ctx.settings.limits.max_envmap_height, "height")
    queries.check_size(frames, ctx.settings.limits.max_sequence_frames, "frames")
    if t1 < t0:
        raise InvalidInput(f"t1 ({t1}) must not be before t0 ({t0})", code="invalid_t")
    cf = await _field_async(job_id, tenant, ctx)
    times = sequence_times(t0, t1, frames)
    for probe_t in {times[0], times[-1]}:  # refuse a bad query now, not after the 200 is sent
        await run_in_threadpool(queries.envmap, cf, point, probe_t, 1)
    # frame by frame on the exports' copy of the field; the frame in flight is cancelled when the
    # client leaves (service.exports)
    metrics = ctx.metrics
    cancellation = Cancellation()
    on_map = (lambda q: metrics.export_maps.labels(q).inc()) if metrics is not None else None
    maps = ((t, hdr) for t, hdr, _ in queries.envmap_sequence(cf, point, times, height, quality, cancellation, on_map))
    members = sequence_members(
        maps,
        point,
        job_id,
        first_frame=first_frame,
        extra={"height": height, "quality": quality},
        fps=sequence_fps(times),
        colour=colour,
    )
    stream = stream_export(zip_stream(members), cancellation,
                           on_cancel=metrics.exports_cancelled.inc if metrics is not None else None)
    return StreamingResponse(stream, media_type="application/zip", headers={
        CONVENTIONS_HEADER: CONVENTIONS_SUMMARY, "Content-Disposition": 'attachment; filename="envmaps.zip"'})
