"""Settings both the API and the workers read, once, from the environment (docs/api.md).

One frozen object is passed around instead of scattered `os.environ` reads, so the API, the
worker and the tests agree on every path and every timeout. The API's own settings (keys,
request limits) extend this in `service.config`.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Mapping

from pydantic import BaseModel, ConfigDict, Field

ENV_PREFIX = "LIGHTFIELD_"


class SettingsError(ValueError):
    """An environment variable has an unusable value (the message names it)."""


class JobSettings(BaseModel):
    model_config = ConfigDict(frozen=True)

    data_dir: Path = Path("lightfield-data")
    broker_url: str | None = None  # None = embedded mode (lightfield serve starts Redis)
    visibility_timeout_s: float = Field(600.0, gt=0)  # broker re-delivery of unacked jobs
    lease_ttl_s: float = Field(60.0, gt=0)  # a job's run lease; heartbeat every ttl/3
    # operator overrides of the engine preset's loop settings (e.g. {"iterations": 50} on a slow CPU box)
    distill_overrides: dict = Field(default_factory=dict)
    # a run that meets a storage fault (full, read-only, unreachable disk) is re-queued to resume
    # from its checkpoint after storage_retry_s, 2x, 4x, ... (capped at 5 min), at most
    # storage_retries times, then failed as storage_unavailable
    storage_retries: int = Field(8, ge=0)
    storage_retry_s: float = Field(5.0, gt=0)
    # where job files are kept (jobs.blobstore): None = the data directory; s3://bucket/prefix =
    # an S3-compatible store shared by hosts that share nothing else (AWS_* variables for access)
    storage_url: str | None = None
    cache_bytes: int = Field(4 << 30, gt=0)  # this host's cache of fetched light fields (LRU)
    # a live session's update (worker.sessions): distillation steps from the last version, the
    # engine's draft loop otherwise (a bounded cost per version, whatever the frames)
    session_steps: int = Field(40, gt=0)
    # the first version's steps: fewer, so a first answer lands soon, refined by the next versions
    session_first_steps: int = Field(10, gt=0)

    def storage_retry_delay_s(self, retry: int) -> float:
        """Seconds before storage retry number `retry` (1, 2, ...)."""
        return min(self.storage_retry_s * 2.0 ** max(retry - 1, 0), 300.0)

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None):
        env = os.environ if environ is None else environ
        try:
            return cls(**cls._values_from_env(env))
        except ValueError as exc:  # pydantic: a value out of range
            if isinstance(exc, SettingsError):
                raise
            raise SettingsError(f"invalid {ENV_PREFIX}* setting: {exc}") from None

    @classmethod
    def _values_from_env(cls, env: Mapping[str, str]) -> dict:
        """Constructor arguments from the variables that are set (subclasses add theirs)."""
        values: dict = {}
        if env.get(ENV_PREFIX + "DATA_DIR"):
            values["data_dir"] = Path(env[ENV_PREFIX + "DATA_DIR"])
        if env.get(ENV_PREFIX + "BROKER_URL"):
            values["broker_url"] = env[ENV_PREFIX + "BROKER_URL"]
        for name, key in (("visibility_timeout_s", "VISIBILITY_TIMEOUT"), ("lease_ttl_s", "LEASE_TTL"),
                          ("storage_retry_s", "STORAGE_RETRY_S")):
            if ENV_PREFIX + key in env:
                values[name] = env_number(env, ENV_PREFIX + key, float)
        if env.get(ENV_PREFIX + "STORAGE_URL"):
            values["storage_url"] = env[ENV_PREFIX + "STORAGE_URL"]
        if ENV_PREFIX + "CACHE_BYTES" in env:
            values["cache_bytes"] = env_number(env, ENV_PREFIX + "CACHE_BYTES", int)
        for name, key in (("session_steps", "SESSION_STEPS"), ("session_first_steps", "SESSION_FIRST_STEPS")):
            if ENV_PREFIX + key in env:
                values[name] = env_number(env, ENV_PREFIX + key, int)
        if ENV_PREFIX + "STORAGE_RETRIES" in env:
            values["storage_retries"] = env_number(env, ENV_PREFIX + "STORAGE_RETRIES", int)
        if env.get(ENV_PREFIX + "DISTILL_OVERRIDES"):
            try:
                values["distill_overrides"] = json.loads(env[ENV_PREFIX + "DISTILL_OVERRIDES"])
            except json.JSONDecodeError as exc:
                raise SettingsError(f"{ENV_PREFIX}DISTILL_OVERRIDES must be a JSON object: {exc}") from None
        return values


def env_number(env: Mapping[str, str], key: str, kind: type):
    try:
        return kind(env[key])
    except ValueError:
        raise SettingsError(f"{key} must be a {kind.__name__}, got {env[key]!r}") from None
