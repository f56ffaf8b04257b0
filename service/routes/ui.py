"""What the web page needs beyond the public query API: the frames it clicks on, probe
placement along a pixel's ray, and chrome/diffuse balls composited into a frame.

All four read the capture preview the worker stores beside a succeeded job's artefact
(service.stored_preview) and use the same auth, ownership and `not_ready` rules as
/lightfield/{id}. Geometry lives in service.ui_probes and core; rendering in
core.insertion. Included by service.app.create_app.
"""
from __future__ import annotations

import logging
import tempfile
import threading
from pathlib import Path

import numpy as np
import torch
from fastapi import APIRouter, Depends, Query, Response
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, Field

from core.capture.base import Capture
from core.chrome_ball import BallPlacementError
from core.conventions import CONVENTIONS_SUMMARY
from core.export.schema import AnswerGrade
from core.insertion import InsertionError, insert_objects, parse_points
from core.sim.room_scan import write_sample_scan
from jobs.storage import JobPaths
from service.context import AppContext, Tenant, get_ctx, get_tenant
from service.errors import ErrorBody, Gone, InvalidInput, NotFound, storage_errors
from service.fieldcache import CachedField
from service.lightfields import load_field, succeeded_job
from service.models import Flags
from service.queries import check_t, parse_x
from service.query_rules import MAX_ABS_T_S, X_PATTERN
from service.stored_preview import PreviewCorrupt, PreviewError, StoredPreview, load_preview
from service.ui_probes import ProbeError, locate, place

log = logging.getLogger("lightfield.service")
router = APIRouter(tags=["ui"])
_ERRORS = {s: {"model": ErrorBody} for s in (401, 404, 409, 410, 413, 422, 503)}
CONVENTIONS_HEADER = "X-Lightfield-Conventions"
MAX_INSERTED_PROBES = 16
MAX_INSERTION_ENV_HEIGHT = 128
# Balls are rendered into a frame of at most this many rows: the perspective-exact ball
# rendering costs ~2 s for 4 probes at 360 rows on 2 CPU cores, and the browser scales the
# picture to the card anyway (see bench/ui_latency.py).
INSERTION_MAX_HEIGHT = 240
T_HELP = "seconds from the first frame; the stored frame nearest in time is used"
X_HELP = "world position 'X,Y,Z' in metres (each within +-1e6)"
TQuery = Query(0.0, description=T_HELP, ge=-MAX_ABS_T_S, le=MAX_ABS_T_S)


class CaptureView(BaseModel):
    id: str
    width: int = Field(description="width of the stored preview frames (pixels)")
    height: int
    frames: int = Field(description="stored preview frames (evenly spaced over the capture)")
    source_frames: int = Field(description="frames the estimation used")
    times: list[float] = Field(description="time of each stored frame, seconds from the first frame")
    fps: float
    intrinsics: dict = Field(description="fx, fy, cx, cy, width, height of the preview frames")
    depth_source: str
    uses_time: bool = Field(description="whether the light field varies over time")
    bounds: dict = Field(description="scene box lo/hi (metres) and time range t0/t1 of the field")
    static_camera: bool = Field(description="the estimate used one camera pose for every frame")
    intrinsics_source: str | None = Field(None, description="where the intrinsics came from: params, the capture file, "
                                                            "EXIF, refined by tracking, or assumed")
    poses_source: str | None = Field(None, description="where given poses came from (null: none were given)")
    tracking: dict | None = Field(None, description="camera tracking: method, reprojection error, frames dropped, "
                                                    "scale source (null: not run)")
    exposure_source: str | None = Field(None, description="where each frame's exposure came from: params, the capture "
                                                          "file, or estimated (asked for, or a moving camera "
                                                          "taken to auto-expose); null: one locked exposure")
    frame_ev: list[float] | None = Field(None, description="the stored frames' exposures in stops (null: none)")
    transfer: dict | None = Field(None, description="the camera's transfer function the frames were decoded with: "
                                                    "curve, where it came from (params, the file, or the sRGB "
                                                    "default), bit depth, primaries (null: an older artefact)")
    response: dict | None = Field(None, description="the camera response estimated from frames at different "
                                                    "exposures: whether it was used, and how well each curve "
                                                    "explains held-out frames (null: not estimated)")
    notes: list[str] = Field(default_factory=list, description="what was taken from the file's metadata and applied")
    warnings: list[str] = Field(default_factory=list, description="the capture's warnings (assumptions, fallbacks)")
    grade: AnswerGrade = Field(description="the job's self-check and the share of the sphere seen vs filled")


class ProbeView(BaseModel):
    u: float | None = Field(
        description="fraction of the frame width (outside [0, 1]: off the frame; null: behind the camera)"
    )
    v: float | None = Field(description="fraction of the frame height")
    t: float
    frame_index: int
    frame_time: float
    visible: bool = Field(description="the probe is in front of the camera and inside the frame")
    surface_depth: float | None = Field(description="planar depth (m) of the surface at the pixel; null when unknown")
    default_depth: float = Field(description="planar depth (m) that puts the drawn ball just in front of the surface")
    depth: float = Field(description="planar depth (m) of the probe (<= 0: behind the camera)")
    x: tuple[float, float, float] = Field(description="world position of the probe (metres): pass as x to the queries")
    radius: float = Field(description="radius (m) of the ball drawn at the probe by /insertion")
    extrapolated: Flags


def _succeeded(job_id: str, tenant: Tenant, ctx: AppContext):
    return succeeded_job(job_id, tenant, ctx, what="its frames and light field")


def _stored_preview(record, ctx: AppContext) -> StoredPreview:
    paths = JobPaths.for_job(ctx.settings.data_dir, record.tenant_hash, record.id)
    try:
        with storage_errors("fetching the stored frames"):
            ctx.files.fetch_artefact(paths)  # this host's cache (a no-op with the local store)
        return load_preview(paths.job_dir)
    except FileNotFoundError:
        raise NotFound(f"job {record.id} has no stored frames (it finished before the page's previews existed)",
                       code="frames_unavailable") from None
    except PreviewCorrupt as exc:  # never served; the light field itself is unaffected
        log.error("job %s: stored preview failed verification: %s", record.id, exc)
        raise Gone(f"job {record.id}: the stored frames failed verification and will not be served ({exc})",
                   code="preview_corrupt") from None
    except PreviewError as exc:
        raise NotFound(f"job {record.id}: stored frames are unreadable ({exc})", code="frames_unavailable") from None


def _preview(job_id: str, tenant: Tenant, ctx: AppContext) -> StoredPreview:
    return _stored_preview(_succeeded(job_id, tenant, ctx), ctx)


def _load(job_id: str, tenant: Tenant, ctx: AppContext) -> tuple[StoredPreview, CachedField]:
    """The preview and the (cached) light field of a succeeded job."""
    record = _succeeded(job_id, tenant, ctx)
    return _stored_preview(record, ctx), load_field(record, ctx)


def _field_time(cf: CachedField, preview: StoredPreview, index: int) -> float | None:
    """The field's time input for stored frame `index` (None for a field without time)."""
    return float(preview.times[index]) if cf.artefact.uses_time else None


def _flags(cf: CachedField, x, t: float | None) -> Flags:
    ts = None if t is None else torch.tensor([t], dtype=torch.float32)
    flags = cf.artefact.flags(torch.tensor([x], dtype=torch.float32), ts)[0]
    return Flags(x=bool(flags["extrapolated_x"]), t=bool(flags["extrapolated_t"]))


@router.get("/lightfield/{job_id}/capture", response_model=CaptureView, responses=_ERRORS,
            summary="The stored preview of the capture: frame size, times, intrinsics (for the web page)")
def get_capture(job_id: str, tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    preview, cf = _load(job_id, tenant, ctx)
    summary = cf.artefact.meta.get("capture", {})
    meta = summary.get("metadata", {})
    tracking = meta.get("tracking")
    notes = list(meta.get("applied", [])) + list((meta.get("nerfstudio") or {}).get("notes", []))
    return CaptureView(
        id=job_id,
        grade=AnswerGrade.of(cf.artefact.meta),
        width=preview.width,
        height=preview.height,
        frames=preview.num_frames,
        source_frames=preview.source_frames,
        times=[round(float(t), 6) for t in preview.times],
        fps=preview.fps,
        intrinsics=preview.intrinsics,
        depth_source=preview.depth_source,
        uses_time=bool(cf.artefact.uses_time),
        bounds=cf.artefact.bounds.to_dict(),
        static_camera=bool(summary.get("static_camera", True)),
        intrinsics_source=meta.get("intrinsics_source"),
        poses_source=meta.get("poses_source"),
        tracking={
            k: tracking.get(k)
            for k in ("method", "reprojection_error_px", "frames_dropped", "scale_source", "camera_moves", "reason")
        }
        if tracking
        else None,
        exposure_source=meta.get("exposure_source"),
        frame_ev=None if preview.stated_ev is None else [round(float(e), 4) for e in preview.stated_ev],
        transfer=meta.get("transfer"),
        response={k: v for k, v in meta["response"].items() if k not in ("codes", "log_linear")}
        if meta.get("response")
        else None,
        notes=notes,
        warnings=list(summary.get("warnings", [])),
    )


@router.get("/lightfield/{job_id}/frame", response_class=Response, responses={
    200: {"content": {"image/png": {}}, "description": "the stored frame nearest in time to t"}, **_ERRORS},
    summary="A frame of the capture as PNG (preview resolution)")
def get_frame(job_id: str, t: float = TQuery,
              tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    from core.io.images import encode_png  # noqa: PLC0415 — core.io.images pulls in av, cv2, OpenEXR, PIL: imported when used

    preview = _preview(job_id, tenant, ctx)
    index = preview.nearest_frame(check_t(t))
    return Response(encode_png(preview.frame(index)), media_type="image/png", headers={
        "X-Lightfield-Frame-Index": str(index), "X-Lightfield-Frame-Time": f"{float(preview.times[index]):.6g}",
        "Cache-Control": "private, max-age=3600"})


@router.get("/lightfield/{job_id}/probe", response_model=ProbeView, responses=_ERRORS,
            summary="Place a probe on the ray through a pixel (default depth: just in front of the surface), "
                    "or find where a world point x appears in the frame at t")
def get_probe(job_id: str,
              u: float | None = Query(None, description="fraction of the frame width, 0 = left edge"),
              v: float | None = Query(None, description="fraction of the frame height, 0 = top edge"),
              t: float = TQuery,
              depth: float | None = Query(None, description="planar depth in metres along the pixel's ray"),
              x: str | None = Query(None, description="instead of u, v, depth: " + X_HELP, pattern=X_PATTERN,
                                    max_length=200),
              tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    if (x is None) == (u is None or v is None):
        raise InvalidInput("give either u and v (a pixel, with an optional depth) or x (a world point)",
                           code="invalid_probe")
    point = parse_x(x) if x is not None else None
    preview, cf = _load(job_id, tenant, ctx)
    try:
        p = locate(preview, point, check_t(t)) if point is not None else place(preview, u, v, check_t(t), depth)
    except ProbeError as exc:
        raise InvalidInput(str(exc), code="invalid_probe") from None
    frame_time = float(preview.times[p.frame_index])
    return ProbeView(u=p.u, v=p.v, t=t, frame_index=p.frame_index, frame_time=frame_time, visible=p.visible,
                     surface_depth=p.surface_depth, default_depth=p.default_depth, depth=p.depth, x=p.x,
                     radius=p.radius, extrapolated=_flags(cf, p.x, _field_time(cf, preview, p.frame_index)))


def _insertion_frame(preview: StoredPreview, index: int):
    """Frame [h,w,3] float in [0,1], depth [h,w] and camera of stored frame `index`, at most
    INSERTION_MAX_HEIGHT rows (the engine's own resize: area-averaged colour, nearest depth)."""
    capture = Capture(frames=torch.from_numpy(preview.frame(index).astype(np.float32) / 255.0)[None],
                      depth=torch.from_numpy(preview.depth_map(index))[None],
                      intrinsics=preview.camera(index).intrinsics,
                      poses=torch.from_numpy(preview.poses[index : index + 1]),
                      times=torch.from_numpy(preview.times[index : index + 1]), fps=preview.fps,
                      depth_source=preview.depth_source).resized(INSERTION_MAX_HEIGHT)
    return capture.frames[0], capture.depth[0], capture.camera(0)


def _render_insertion(preview: StoredPreview, cf: CachedField, index: int, points_text: str, env_height: int) -> bytes:
    from core.io.images import encode_png  # noqa: PLC0415 — core.io.images pulls in av, cv2, OpenEXR, PIL: imported when used

    try:
        points = parse_points(points_text)
    except InsertionError as exc:
        raise InvalidInput(str(exc), code="invalid_points") from None
    if len(points) > MAX_INSERTED_PROBES:
        raise InvalidInput(f"points: at most {MAX_INSERTED_PROBES} probes, got {len(points)}", code="invalid_points")
    t = _field_time(cf, preview, index)

    def envmaps_at(xs: torch.Tensor, t_: float | None) -> torch.Tensor:
        ts = None if t_ is None else torch.full((xs.shape[0],), float(t_))
        with cf.lock:
            return cf.artefact.envmaps(xs, ts, env_height)[0]

    frame, depth, camera = _insertion_frame(preview, index)
    try:
        out = insert_objects(frame, depth, camera, envmaps_at, t, points, ev=preview.frame_ev(index))
    except (InsertionError, BallPlacementError) as exc:
        raise InvalidInput(f"points: {exc}", code="invalid_points") from None
    return encode_png(out.numpy())


@router.get("/lightfield/{job_id}/insertion", response_class=Response, responses={
    200: {"content": {"image/png": {}}, "description": "the frame with the balls composited"}, **_ERRORS},
    summary="A chrome ball and a diffuse sphere at each point, lit by the field and composited into the frame")
async def get_insertion(job_id: str, t: float = TQuery,
                        points: str = Query(..., description="'u,v,depth;...': u, v fractions of width/height, "
                                                             "depth planar metres (as `lightfield preview --points`)"),
                        env_height: int = Query(32, ge=4, le=MAX_INSERTION_ENV_HEIGHT,
                                                description="env map rows used to light the balls"),
                        tenant: Tenant = Depends(get_tenant), ctx: AppContext = Depends(get_ctx)):
    preview, cf = await run_in_threadpool(_load, job_id, tenant, ctx)
    index = preview.nearest_frame(check_t(t))
    data = await run_in_threadpool(_render_insertion, preview, cf, index, points, env_height)
    return Response(data, media_type="image/png", headers={
        CONVENTIONS_HEADER: CONVENTIONS_SUMMARY, "X-Lightfield-Frame-Index": str(index)})


_sample_scan: bytes | None = None
_sample_lock = threading.Lock()


def _render_sample_scan() -> bytes:
    """The bundled panorama's room scan as an MP4 (core.sim.room_scan.write_sample_scan),
    rendered once per process (about a second) and kept: the same bytes for every caller."""
    global _sample_scan
    with _sample_lock:
        if _sample_scan is None:
            with tempfile.TemporaryDirectory() as tmp:
                video, _, _ = write_sample_scan(Path(tmp))
                _sample_scan = video.read_bytes()
        return _sample_scan


@router.get("/samples/room_scan.mp4", response_class=Response, include_in_schema=False)
async def get_sample_scan():
    """The web page's sample: a phone turned around a room (46 frames, auto-exposure on, no
    poses), simulated from the bundled CC0 panorama; not tenant data, so no key is needed."""
    return Response(await run_in_threadpool(_render_sample_scan), media_type="video/mp4",
                    headers={"Cache-Control": "public, max-age=86400"})
