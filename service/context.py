"""Per-process state of the API, built once by `create_app` and reached through dependencies."""
from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

from celery import Celery
from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

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
    # upload checks hold a file (up to its byte limit) and one decoded video frame: one at a
    # time per process keeps memory bounded
    validation_slots: asyncio.Semaphore = field(default_factory=lambda: asyncio.Semaphore(1))


@dataclass(frozen=True)
class Tenant:
    name: str

    @property
    def hash(self) -> str:
        return tenant_hash(self.name)


_bearer = HTTPBearer(auto_error=False, description="API key of a tenant (LIGHTFIELD_API_KEYS)")


def get_ctx(request: Request) -> AppContext:
    return request.app.state.ctx


def get_tenant(request: Request, credentials: HTTPAuthorizationCredentials | None = Depends(_bearer)) -> Tenant:
    ctx = get_ctx(request)
    header = f"{credentials.scheme} {credentials.credentials}" if credentials else None
    return Tenant(ctx.keyring.tenant_for(header))


def owned_job(job_id: str, tenant: Tenant, ctx: AppContext) -> JobRecord:
    """The caller's job or 404: another tenant's job is indistinguishable from a missing one."""
    record = ctx.store.get(job_id) if is_job_id(job_id) else None
    if record is None or record.tenant != tenant.name:
        raise NotFound(f"no job {job_id!r}", code="job_not_found")
    return record
