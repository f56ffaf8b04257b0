"""The API's settings: the shared job settings (jobs.settings) plus what only HTTP needs
(API keys, model directories, request limits, caches), read once from the environment
(documented in docs/api.md)."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

from pydantic import BaseModel, ConfigDict, Field

from jobs.settings import ENV_PREFIX, JobSettings, SettingsError, env_number


class ServiceLimits(BaseModel):
    """Per-request and per-tenant bounds. Media pixel/frame limits live in core.io.limits."""

    model_config = ConfigDict(frozen=True)

    # 200 MiB = core.io's MediaLimits.max_bytes default: a larger upload could not be decoded
    max_upload_bytes: int = Field(200 * 1024**2, gt=0, description="input file size")
    max_depth_bytes: int = Field(200 * 1024**2, gt=0, description="depth file size")
    max_params_bytes: int = Field(1024**2, gt=0, description="params JSON size")
    max_envmap_height: int = Field(1024, gt=0, description="env map height (width = 2 x height)")
    max_cubemap_size: int = Field(1024, gt=0, description="cube map face edge")
    max_batch: int = Field(64, gt=0, description="queries per POST /lightfield/{id}/envmaps")
    max_sequence_frames: int = Field(240, gt=0, description="frames per GET /lightfield/{id}/sequence")
    max_jobs_in_flight: int = Field(4, gt=0, description="queued + running jobs per tenant")
    max_page_size: int = Field(100, gt=0, description="GET /jobs page size")
    # a batch of 64 queries is ~4 KB of JSON; 256 KiB bounds what the event loop parses
    max_json_bytes: int = Field(256 * 1024, gt=0, description="JSON request body size")
    # queued field evaluations per light field, in env map pixels (an exact 1024-row map is 2 Mpx)
    max_pending_pixels: int = Field(1 << 25, gt=0, description="env map pixels queued per light field")
    # upload checks (service.uploadcheck): threads of their own, and a time budget per upload
    upload_checks: int = Field(2, gt=0, description="upload checks run at once per API process")
    upload_check_s: int = Field(30, gt=0, description="seconds one upload's check may take (413 beyond)")
    # live sessions (service.routes.sessions): 20 held at once is the target per service
    max_live_sessions: int = Field(20, gt=0, description="live sessions per tenant")
    max_session_frames: int = Field(240, gt=0, description="frames one session may hold")
    max_session_bytes: int = Field(256 * 1024**2, gt=0, description="stored bytes of one session's frames")
    max_session_fps: int = Field(30, gt=0, description="frames per second one session may receive")
    max_frames_request_bytes: int = Field(16 * 1024**2, gt=0, description="one POST /sessions/{id}/frames or "
                                          "WebSocket message")
    max_session_probes: int = Field(16, gt=0, description="probe points one subscription names")
    session_idle_s: int = Field(300, gt=0, description="a session without frames for this long expires")


class HttpTimeouts(BaseModel):
    """Bounds on every wait a client can impose on the server (slowloris, dripped bodies)."""

    model_config = ConfigDict(frozen=True)

    header_s: float = Field(10.0, gt=0, description="a request's line and headers must arrive within this")
    body_idle_s: float = Field(15.0, gt=0, description="longest pause between two body chunks")
    body_grace_s: float = Field(10.0, ge=0, description="body time allowed before the minimum rate applies")
    body_min_rate: float = Field(4096.0, gt=0, description="bytes/s a body must average after the grace time")
    keep_alive_s: float = Field(5.0, gt=0, description="idle keep-alive connections are closed after this")
    max_connections: int = Field(512, gt=0, description="open connections + requests in progress (503 beyond)")


# env var suffix -> HttpTimeouts field
_TIMEOUT_ENV = {"HEADER_TIMEOUT": "header_s", "BODY_TIMEOUT": "body_idle_s", "BODY_GRACE": "body_grace_s",
                "MIN_BODY_RATE": "body_min_rate", "KEEP_ALIVE": "keep_alive_s", "MAX_CONNECTIONS": "max_connections"}


class ServiceSettings(JobSettings):
    api_keys: str | None = None  # "tenant:key,..." or a path to a file of such lines
    model_dirs: tuple[Path, ...] = ()  # where params.prior_weights may point
    field_cache_size: int = Field(8, gt=0)  # loaded light fields per API process
    readiness_timeout_s: float = Field(2.0, gt=0)  # worker ping in /readyz
    limits: ServiceLimits = ServiceLimits()
    timeouts: HttpTimeouts = HttpTimeouts()
    # with no API keys: Host names (besides loopback) and Origins (besides the server's own)
    # a browser may use; see service.origin
    allowed_hosts: tuple[str, ...] = ()
    allowed_origins: tuple[str, ...] = ()

    @classmethod
    def _values_from_env(cls, env: Mapping[str, str]) -> dict:
        values = super()._values_from_env(env)
        limits = {
            name: env_number(env, ENV_PREFIX + name.upper(), int)
            for name in ServiceLimits.model_fields
            if ENV_PREFIX + name.upper() in env
        }
        try:
            values["limits"] = ServiceLimits(**limits)
        except ValueError as exc:
            raise SettingsError(f"invalid {ENV_PREFIX}MAX_* limit: {exc}") from None
        timeouts = {field: env_number(env, ENV_PREFIX + key, int if field == "max_connections" else float)
                    for key, field in _TIMEOUT_ENV.items() if ENV_PREFIX + key in env}
        try:
            values["timeouts"] = HttpTimeouts(**timeouts)
        except ValueError as exc:
            raise SettingsError(f"invalid {ENV_PREFIX}* timeout: {exc}") from None
        for name in ("allowed_hosts", "allowed_origins"):
            if env.get(ENV_PREFIX + name.upper()):
                values[name] = tuple(v.strip().lower() for v in env[ENV_PREFIX + name.upper()].split(",") if v.strip())
        if env.get(ENV_PREFIX + "API_KEYS"):
            values["api_keys"] = env[ENV_PREFIX + "API_KEYS"]
        if env.get(ENV_PREFIX + "MODEL_DIRS"):
            values["model_dirs"] = tuple(Path(p) for p in env[ENV_PREFIX + "MODEL_DIRS"].split(os.pathsep) if p)
        if ENV_PREFIX + "READINESS_TIMEOUT" in env:
            values["readiness_timeout_s"] = env_number(env, ENV_PREFIX + "READINESS_TIMEOUT", float)
        if ENV_PREFIX + "FIELD_CACHE_SIZE" in env:
            values["field_cache_size"] = env_number(env, ENV_PREFIX + "FIELD_CACHE_SIZE", int)
        return values
