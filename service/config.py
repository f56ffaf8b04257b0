"""Service settings, read once from the environment (documented in docs/api.md).

One frozen object is passed around instead of scattered `os.environ` reads, so the API, the
worker and the tests agree on every limit and every path.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

ENV_PREFIX = "LIGHTFIELD_"


class SettingsError(ValueError):
    """An environment variable has an unusable value (the message names it)."""


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


class ServiceSettings(BaseModel):
    model_config = ConfigDict(frozen=True)

    data_dir: Path = Path("lightfield-data")
    broker_url: str | None = None  # None = embedded mode (lightfield serve starts Redis)
    api_keys: str | None = None  # "tenant:key,..." or a path to a file of such lines
    model_dirs: tuple[Path, ...] = ()  # where params.prior_weights may point
    visibility_timeout_s: float = Field(600.0, gt=0)  # broker re-delivery of unacked jobs
    lease_ttl_s: float = Field(60.0, gt=0)  # a job's run lease; heartbeat every ttl/3
    field_cache_size: int = Field(8, gt=0)  # loaded light fields per API process
    readiness_timeout_s: float = Field(2.0, gt=0)  # worker ping in /readyz
    # operator overrides of the engine's preset (e.g. {"iterations": 50} on a slow CPU box)
    distill_overrides: dict = Field(default_factory=dict)
    limits: ServiceLimits = ServiceLimits()

    @classmethod
    def from_env(cls, environ: dict[str, str] | None = None) -> "ServiceSettings":
        env = os.environ if environ is None else environ
        limits = {
            name: _number(env, ENV_PREFIX + name.upper(), int)
            for name in ServiceLimits.model_fields
            if ENV_PREFIX + name.upper() in env
        }
        try:
            values: dict = {"limits": ServiceLimits(**limits)}
        except ValueError as exc:
            raise SettingsError(f"invalid {ENV_PREFIX}MAX_* limit: {exc}") from None
        if env.get(ENV_PREFIX + "DATA_DIR"):
            values["data_dir"] = Path(env[ENV_PREFIX + "DATA_DIR"])
        if env.get(ENV_PREFIX + "BROKER_URL"):
            values["broker_url"] = env[ENV_PREFIX + "BROKER_URL"]
        if env.get(ENV_PREFIX + "API_KEYS"):
            values["api_keys"] = env[ENV_PREFIX + "API_KEYS"]
        if env.get(ENV_PREFIX + "MODEL_DIRS"):
            values["model_dirs"] = tuple(Path(p) for p in env[ENV_PREFIX + "MODEL_DIRS"].split(os.pathsep) if p)
        for name, key in (
            ("visibility_timeout_s", "VISIBILITY_TIMEOUT"),
            ("lease_ttl_s", "LEASE_TTL"),
            ("readiness_timeout_s", "READINESS_TIMEOUT"),
        ):
            if ENV_PREFIX + key in env:
                values[name] = _number(env, ENV_PREFIX + key, float)
        if env.get(ENV_PREFIX + "DISTILL_OVERRIDES"):
            try:
                values["distill_overrides"] = json.loads(env[ENV_PREFIX + "DISTILL_OVERRIDES"])
            except json.JSONDecodeError as exc:
                raise SettingsError(f"{ENV_PREFIX}DISTILL_OVERRIDES must be a JSON object: {exc}") from None
        if ENV_PREFIX + "FIELD_CACHE_SIZE" in env:
            values["field_cache_size"] = _number(env, ENV_PREFIX + "FIELD_CACHE_SIZE", int)
        try:
            return cls(**values)
        except ValueError as exc:  # pydantic: a value out of range
            raise SettingsError(f"invalid {ENV_PREFIX}* setting: {exc}") from None


def _number(env, key: str, kind: type):
    try:
        return kind(env[key])
    except ValueError:
        raise SettingsError(f"{key} must be a {kind.__name__}, got {env[key]!r}") from None
