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


class ServiceSettings(JobSettings):
    api_keys: str | None = None  # "tenant:key,..." or a path to a file of such lines
    model_dirs: tuple[Path, ...] = ()  # where params.prior_weights may point
    field_cache_size: int = Field(8, gt=0)  # loaded light fields per API process
    readiness_timeout_s: float = Field(2.0, gt=0)  # worker ping in /readyz
    limits: ServiceLimits = ServiceLimits()

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
        if env.get(ENV_PREFIX + "API_KEYS"):
            values["api_keys"] = env[ENV_PREFIX + "API_KEYS"]
        if env.get(ENV_PREFIX + "MODEL_DIRS"):
            values["model_dirs"] = tuple(Path(p) for p in env[ENV_PREFIX + "MODEL_DIRS"].split(os.pathsep) if p)
        if ENV_PREFIX + "READINESS_TIMEOUT" in env:
            values["readiness_timeout_s"] = env_number(env, ENV_PREFIX + "READINESS_TIMEOUT", float)
        if ENV_PREFIX + "FIELD_CACHE_SIZE" in env:
            values["field_cache_size"] = env_number(env, ENV_PREFIX + "FIELD_CACHE_SIZE", int)
        return values
