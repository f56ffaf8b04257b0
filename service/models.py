"""Pydantic request/response models: they are the OpenAPI schema clients see."""
from __future__ import annotations

from datetime import datetime, timezone
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictFloat, StrictInt

from core.export.schema import (  # noqa: F401  (the hand-off products: one model each, shared with the CLI)
    AnswerGrade,
    ArkitProbe,
    DominantLight,
    Flags,
    SHLayoutName as SHLayout,
    SphericalHarmonics,
    UnityProbeGrid,
)
from jobs.store import JobRecord, JobState
from service.errors import ErrorDetail

EnvmapFormat = Literal["exr", "hdr", "png", "npy"]
Quality = Literal["fast", "exact", "baked"]


def _ts(value: float | None) -> datetime | None:
    return datetime.fromtimestamp(value, tz=timezone.utc) if value else None


class JobLinks(BaseModel):
    self: str
    events: str
    lightfield: str | None = Field(None, description="artefact metadata, once the job succeeded")
    envmap: str | None = Field(None, description="env map query endpoint, once the job succeeded")


class JobView(BaseModel):
    id: str
    state: JobState
    progress: float = Field(description="0..1 over the whole job")
    stage: str
    iteration: int
    total: int = Field(description="distillation steps in this job (0 before the loop starts)")
    loss: float | None
    eta_s: float | None = Field(description="estimated seconds to completion")
    message: str
    error: ErrorDetail | None = Field(None, description="set when state = failed")
    cancel_requested: bool = False
    attempts: int = Field(description="deliveries that started running (> 1 after a worker died)")
    resumed: bool = Field(description="a run started from a checkpoint of an earlier run")
    storage_retries: int = Field(0, description="runs given back to the queue after a storage fault (stage "
                                                "waiting_for_storage while the next one waits)")
    input_kind: str
    params: dict[str, Any]
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime
    links: JobLinks

    @classmethod
    def of(cls, r: JobRecord, cancel_requested: bool = False) -> "JobView":
        done = r.state == "succeeded"
        return cls(
            id=r.id, state=r.state, progress=r.progress, stage=r.stage, iteration=r.iteration, total=r.total,
            loss=r.loss, eta_s=r.eta_s, message=r.message,
            error=ErrorDetail(code=r.error_code, message=r.error_message) if r.state == "failed" else None,
            cancel_requested=cancel_requested, attempts=r.attempts, resumed=r.resumed,
            storage_retries=r.storage_retries, input_kind=r.input_kind,
            params=r.params_dict(), created_at=_ts(r.created_at), started_at=_ts(r.started_at),
            finished_at=_ts(r.finished_at), updated_at=_ts(r.updated_at),
            links=JobLinks(
                self=f"/jobs/{r.id}", events=f"/jobs/{r.id}/events",
                lightfield=f"/lightfield/{r.id}" if done else None,
                envmap=f"/lightfield/{r.id}/envmap" if done else None,
            ),
        )


class JobList(BaseModel):
    jobs: list[JobView]
    total: int
    offset: int
    limit: int
    next_offset: int | None = Field(description="pass as ?offset= for the next page; null on the last page")


class LightfieldInfo(BaseModel):
    id: str
    conventions: str = Field(description="the project's conventions (same as header X-Lightfield-Conventions)")
    metadata: dict[str, Any] = Field(description="the artefact's lightfield.json: bounds, time range, "
                                     "temporal decision, prior, training statistics")
    fast_available: bool = Field(description="whether quality=baked (the worker's lattice) can answer queries")
    grade: AnswerGrade = Field(description="the job's self-check and the share of the sphere seen vs filled")


# JSON numbers only (strict: `true` is not 1, "2" is not 2), within what the queries accept
Coordinate = Annotated[StrictFloat, Field(ge=-1e6, le=1e6, description="metres")]
Seconds = Annotated[StrictFloat, Field(ge=-1e9, le=1e9)]


class EnvmapQuery(BaseModel):
    model_config = ConfigDict(extra="forbid")
    x: tuple[Coordinate, Coordinate, Coordinate] = Field(description="world position in metres")
    t: Seconds = Field(0.0, description="seconds from the first frame")


class EnvmapBatchRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    queries: list[EnvmapQuery] = Field(min_length=1, description="at most LIGHTFIELD_MAX_BATCH queries")
    height: StrictInt = Field(64, ge=1, description="rows (at most LIGHTFIELD_MAX_ENVMAP_HEIGHT); "
                              "queries x 2 height^2 <= 8388608 pixels")
    format: EnvmapFormat = "npy"
    ev: StrictFloat = Field(0.0, ge=-64, le=64, description="exposure of PNG previews")
    quality: Quality = Field("fast", description="fast = the field at 1/4 of the rows, upsampled; exact = the field "
                             "at every pixel; baked = the worker's lattice, interpolated (docs/api.md)")


class EncodedEnvmap(BaseModel):
    x: tuple[float, float, float]
    t: float
    extrapolated: Flags
    media_type: str
    data_base64: str


class EnvmapBatchResponse(BaseModel):
    height: int
    width: int
    format: EnvmapFormat
    grade: AnswerGrade | None = None
    items: list[EncodedEnvmap]


class CubemapFace(BaseModel):
    name: Literal["+X", "-X", "+Y", "-Y", "+Z", "-Z"]
    media_type: str
    data_base64: str


class CubemapResponse(BaseModel):
    x: tuple[float, float, float]
    t: float
    size: int
    extrapolated: Flags
    grade: AnswerGrade | None = None
    faces: list[CubemapFace] = Field(description="in the order +X, -X, +Y, -Y, +Z, -Z")


class Health(BaseModel):
    status: Literal["ok"]
    dependencies: dict[str, str] = Field(default_factory=dict, description="embedded mode: state of the "
                                         "supervised Redis and worker processes ('running')")


class Readiness(BaseModel):
    status: Literal["ready", "not_ready"]
    broker: bool
    workers: int
    detail: str = ""
