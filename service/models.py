"""Pydantic request/response models: they are the OpenAPI schema clients see."""
from __future__ import annotations

from datetime import datetime, timezone
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from jobs.store import JobRecord, JobState
from service.errors import ErrorDetail

EnvmapFormat = Literal["exr", "hdr", "png", "npy"]
Quality = Literal["exact", "fast"]


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
            cancel_requested=cancel_requested, attempts=r.attempts, resumed=r.resumed, input_kind=r.input_kind,
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
    fast_available: bool = Field(description="whether quality=fast (a baked grid) can answer queries")


class Flags(BaseModel):
    x: bool = Field(description="x lies outside the scene bounds the field was trained on")
    t: bool = Field(description="t lies outside the capture's time range")


class EnvmapQuery(BaseModel):
    model_config = ConfigDict(extra="forbid")
    x: tuple[float, float, float] = Field(description="world position in metres")
    t: float = Field(0.0, description="seconds from the first frame")


class EnvmapBatchRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    queries: list[EnvmapQuery] = Field(min_length=1)
    height: int = Field(64, ge=1)
    format: EnvmapFormat = "npy"
    ev: float = 0.0
    quality: Quality = "exact"


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
    items: list[EncodedEnvmap]


SHLayout = Literal["arcore", "threejs"]


class DominantLight(BaseModel):
    direction: tuple[float, float, float] = Field(description="unit vector the light arrives from (world); "
                                                  "the best guess even when found is false")
    intensity: tuple[float, float, float] = Field(description="RGB intensity of a directional light (radiance x sr, "
                                                  "relative units): ambient SH + this light reproduce the map's irradiance")
    solid_angle: float = Field(description="effective steradians of the light's lobe")
    found: bool = Field(description="confidence >= 0.05: the light is real; when false, use the ambient SH alone "
                        "or the light at your own risk")
    confidence: float = Field(description="0..1: share of the irradiance facing the light that it gives x (1 - 1/contrast)")
    reason: str = Field(description="why it was or was not found, in words")


class SphericalHarmonics(BaseModel):
    x: tuple[float, float, float]
    t: float
    extrapolated: Flags
    layout: SHLayout = Field(description="layout of `coefficients` and `coefficients_with_light`")
    coefficients: list[float] = Field(description="ambient SH (the map without the main light), 27 floats in `layout`")
    coefficients_with_light: list[float] = Field(description="SH of the whole map (for clients without a "
                                                 "directional light), 27 floats in `layout`")
    arcore_27: list[float] = Field(description="ambient SH in ARCore's 27-float layout (9 coefficients x RGB "
                                   "interleaved, Condon-Shortley signs), whatever the layout")
    band_order: str
    dominant_light: DominantLight


class CubemapFace(BaseModel):
    name: Literal["+X", "-X", "+Y", "-Y", "+Z", "-Z"]
    media_type: str
    data_base64: str


class CubemapResponse(BaseModel):
    x: tuple[float, float, float]
    t: float
    size: int
    extrapolated: Flags
    faces: list[CubemapFace] = Field(description="in the order +X, -X, +Y, -Y, +Z, -Z")


class Health(BaseModel):
    status: Literal["ok"]


class Readiness(BaseModel):
    status: Literal["ready", "not_ready"]
    broker: bool
    workers: int
    detail: str = ""
