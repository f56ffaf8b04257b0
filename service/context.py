"""Per-process state of the API, built once by `create_app` and reached through dependencies."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from celery import Celery
from fastapi import Request

from jobs.storage import is_job_id
from jobs.store import JobRecord, JobStore
from service.auth import KeyRing, tenant_hash
from service.config import ServiceSettings
from service.errors import NotFound
from service.fieldcache import FieldCache


@dataclass
class AppContext:
    settings: ServiceSettings
    keyring: KeyRing
    store: JobStore
    celery: Celery
    fields: FieldCache
    metrics: Any = None  # service.metrics.Metrics
    recent_jobs: dict = field(default_factory=dict)  # job id -> (tenant, expiry): service.lightfields
    upload_checks: Any = None  # service.uploadcheck.UploadChecks: the upload checks' own threads and budget
    files: Any = None  # jobs.jobfiles.JobFiles: this host's directory and the shared store
    sessions: Any = None  # jobs.sessions.SessionStore: live sessions (service.sessions)


@dataclass(frozen=True)
class Tenant:
    name: str

    @property
    def hash(self) -> str:
        return tenant_hash(self.name)


# async: FastAPI runs a plain `def` dependency in the threadpool, two thread hops per request
# for what is a dictionary lookup and a constant-time key comparison
async def get_ctx(request: Request) -> AppContext:
    return request.app.state.ctx


async def get_tenant(request: Request) -> Tenant:
    """The caller's tenant from `Authorization: Bearer KEY` (declared in the OpenAPI document
    by service.openapi; no nested security dependency: this runs on every request)."""
    return Tenant(request.app.state.ctx.keyring.tenant_for(request.headers.get("authorization")))


def owned_job(job_id: str, tenant: Tenant, ctx: AppContext) -> JobRecord:
    """The caller's job or 404: another tenant's job is indistinguishable from a missing one."""
    record = ctx.store.get(job_id) if is_job_id(job_id) else None
    if record is None or record.tenant != tenant.name:
        raise NotFound(f"no job {job_id!r}", code="job_not_found")
    return record
