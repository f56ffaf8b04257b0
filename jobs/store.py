"""Job records in Redis, shared by the API and every worker.

Why Redis: it is already the Celery broker in distributed mode, so API and workers reach it
with no extra service; with AOF persistence records survive restarts; and Lua scripts make
state transitions atomic (a cancel and a worker's "succeeded" can race, one of them wins).

Keys (prefix `lf:`):
    job:<id>                 hash: the record (see JobRecord)
    tenant:<thash>:jobs      sorted set of job ids by creation time (listing)
    tenant:<thash>:inflight  set of queued/running job ids (per-tenant limit)
    job:<id>:cancel          cancel flag read by the worker every step
    job:<id>:lease           run lease (SET NX PX token), so a job never runs twice at once
    stats:states             hash state -> count (metrics without scanning)
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, fields
from typing import Iterable, Literal, get_args

import redis

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
JOB_STATES: tuple[str, ...] = get_args(JobState)
ACTIVE_STATES = ("queued", "running")
TERMINAL_STATES = ("succeeded", "failed", "cancelled")
PREFIX = "lf:"


class JobLimitReached(RuntimeError):
    """The tenant already has the maximum number of queued + running jobs."""


@dataclass
class JobRecord:
    id: str
    tenant: str
    tenant_hash: str
    state: str = "queued"
    input_kind: str = ""  # image | video | capture (a nerfstudio zip)
    input_file: str = ""  # file name inside the upload dir (server-chosen)
    depth_file: str = ""
    params: str = "{}"  # JobParams JSON
    progress: float = 0.0
    stage: str = ""
    iteration: int = 0
    total: int = 0
    loss: float | None = None
    eta_s: float | None = None
    message: str = ""
    error_code: str = ""
    error_message: str = ""
    attempts: int = 0  # deliveries that started running
    resumed: bool = False  # a run started from an existing checkpoint
    storage_retries: int = 0  # runs re-queued after a storage fault (jobs.settings.storage_retries)
    artefact: str = ""  # artefact dir relative to the data dir, once succeeded
    created_at: float = 0.0
    started_at: float | None = None
    finished_at: float | None = None
    updated_at: float = 0.0
    version: int = 0

    def to_redis(self) -> dict[str, str]:
        return {f.name: _encode(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_redis(cls, raw: dict[str, str]) -> "JobRecord":
        kwargs = {}
        for f in fields(cls):
            if f.name in raw:
                kwargs[f.name] = _decode(raw[f.name], f.type)
        return cls(**kwargs)

    @property
    def is_terminal(self) -> bool:
        return self.state in TERMINAL_STATES

    def params_dict(self) -> dict:
        return json.loads(self.params or "{}")


def _encode(value) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "1" if value else "0"
    return str(value)


def _decode(raw: str, type_name: str):
    if "bool" in type_name:
        return raw == "1"
    if "float" in type_name:
        if raw == "":
            return None if "None" in type_name else 0.0
        return float(raw)
    if "int" in type_name:
        return int(raw or 0)
    return raw


# Atomic conditional update. KEYS: job, stats, inflight. ARGV: allowed states ("" = any),
# new state ("" = keep), then field/value pairs. Returns 1 if applied.
_UPDATE_LUA = """
local cur = redis.call('HGET', KEYS[1], 'state')
if not cur then return 0 end
if ARGV[1] ~= '' then
  local ok = false
  for s in string.gmatch(ARGV[1], '[^,]+') do if s == cur then ok = true end end
  if not ok then return 0 end
end
if ARGV[2] ~= '' and ARGV[2] ~= cur then
  redis.call('HSET', KEYS[1], 'state', ARGV[2])
  redis.call('HINCRBY', KEYS[2], cur, -1)
  redis.call('HINCRBY', KEYS[2], ARGV[2], 1)
  if ARGV[2] ~= 'queued' and ARGV[2] ~= 'running' then
    redis.call('SREM', KEYS[3], redis.call('HGET', KEYS[1], 'id'))
  end
end
for i = 3, #ARGV, 2 do redis.call('HSET', KEYS[1], ARGV[i], ARGV[i + 1]) end
redis.call('HINCRBY', KEYS[1], 'version', 1)
return 1
"""

# Create a job unless the tenant is at its in-flight limit. KEYS: job, index, inflight, stats.
# ARGV: limit, job id, created_at, then field/value pairs.
_CREATE_LUA = """
if redis.call('SCARD', KEYS[3]) >= tonumber(ARGV[1]) then return 0 end
for i = 4, #ARGV, 2 do redis.call('HSET', KEYS[1], ARGV[i], ARGV[i + 1]) end
redis.call('ZADD', KEYS[2], ARGV[3], ARGV[2])
redis.call('SADD', KEYS[3], ARGV[2])
redis.call('HINCRBY', KEYS[4], 'queued', 1)
return 1
"""

# Delete a record and its index entries. KEYS: job, index, inflight, stats, cancel, lease.
_DELETE_LUA = """
local cur = redis.call('HGET', KEYS[1], 'state')
if not cur then return 0 end
local id = redis.call('HGET', KEYS[1], 'id')
redis.call('DEL', KEYS[1], KEYS[5], KEYS[6])
redis.call('ZREM', KEYS[2], id)
redis.call('SREM', KEYS[3], id)
redis.call('HINCRBY', KEYS[4], cur, -1)
return 1
"""

_LEASE_RENEW_LUA = """
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('PEXPIRE', KEYS[1], ARGV[2]) end
return 0
"""

_LEASE_RELEASE_LUA = """
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0
"""


def connect(url: str) -> redis.Redis:
    """A thread-safe client (connection pool) with bounded socket waits."""
    return redis.Redis.from_url(
        url, decode_responses=True, socket_timeout=10, socket_connect_timeout=5, health_check_interval=30
    )


@dataclass
class JobStore:
    client: redis.Redis
    _scripts: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        for name, src in (
            ("update", _UPDATE_LUA),
            ("create", _CREATE_LUA),
            ("delete", _DELETE_LUA),
            ("renew", _LEASE_RENEW_LUA),
            ("release", _LEASE_RELEASE_LUA),
        ):
            self._scripts[name] = self.client.register_script(src)

    # -- keys ---------------------------------------------------------------------------
    @staticmethod
    def _job_key(job_id: str) -> str:
        return f"{PREFIX}job:{job_id}"

    @staticmethod
    def _index_key(thash: str) -> str:
        return f"{PREFIX}tenant:{thash}:jobs"

    @staticmethod
    def _inflight_key(thash: str) -> str:
        return f"{PREFIX}tenant:{thash}:inflight"

    _STATS = PREFIX + "stats:states"

    # -- records --------------------------------------------------------------------------
    def create(self, record: JobRecord, max_in_flight: int) -> None:
        now = time.time()
        record.created_at = record.updated_at = now
        pairs = [x for kv in record.to_redis().items() for x in kv]
        ok = self._scripts["create"](
            keys=[self._job_key(record.id), self._index_key(record.tenant_hash),
                  self._inflight_key(record.tenant_hash), self._STATS],
            args=[max_in_flight, record.id, now, *pairs],
        )
        if not ok:
            raise JobLimitReached(f"at most {max_in_flight} jobs may be queued or running per tenant")

    def in_flight(self, thash: str) -> int:
        return int(self.client.scard(self._inflight_key(thash)))

    def get(self, job_id: str) -> JobRecord | None:
        raw = self.client.hgetall(self._job_key(job_id))
        return JobRecord.from_redis(raw) if raw else None

    def update(self, record_or_id, *, allowed: Iterable[str] = (), state: str = "", **values) -> bool:
        """Set fields (and optionally move to `state`) iff the current state is in `allowed`
        (any state when empty). Returns whether the update was applied."""
        job_id = record_or_id if isinstance(record_or_id, str) else record_or_id.id
        raw = self.client.hget(self._job_key(job_id), "tenant_hash")
        if raw is None:
            return False
        values["updated_at"] = time.time()
        pairs = [x for k, v in values.items() for x in (k, _encode(v))]
        return bool(self._scripts["update"](
            keys=[self._job_key(job_id), self._STATS, self._inflight_key(raw)],
            args=[",".join(allowed), state, *pairs],
        ))

    def delete(self, record: JobRecord) -> bool:
        return bool(self._scripts["delete"](
            keys=[self._job_key(record.id), self._index_key(record.tenant_hash),
                  self._inflight_key(record.tenant_hash), self._STATS,
                  self._cancel_key(record.id), self._lease_key(record.id)],
        ))

    def list(self, thash: str, offset: int, limit: int) -> tuple[list[JobRecord], int]:
        """Newest first. Returns (records, total count for the tenant)."""
        key = self._index_key(thash)
        ids = self.client.zrevrange(key, offset, offset + limit - 1)
        pipe = self.client.pipeline(transaction=False)
        for job_id in ids:
            pipe.hgetall(self._job_key(job_id))
        records = [JobRecord.from_redis(raw) for raw in pipe.execute() if raw]
        return records, int(self.client.zcard(key))

    def state_counts(self) -> dict[str, int]:
        raw = self.client.hgetall(self._STATS)
        return {s: max(int(raw.get(s, 0)), 0) for s in JOB_STATES}

    # -- cancel flag ------------------------------------------------------------------------
    @staticmethod
    def _cancel_key(job_id: str) -> str:
        return f"{PREFIX}job:{job_id}:cancel"

    def request_cancel(self, job_id: str) -> None:
        self.client.set(self._cancel_key(job_id), "1", ex=7 * 24 * 3600)

    def cancel_requested(self, job_id: str) -> bool:
        return bool(self.client.exists(self._cancel_key(job_id)))

    # -- run lease ----------------------------------------------------------------------------
    @staticmethod
    def _lease_key(job_id: str) -> str:
        return f"{PREFIX}job:{job_id}:lease"

    def acquire_lease(self, job_id: str, token: str, ttl_s: float) -> bool:
        return bool(self.client.set(self._lease_key(job_id), token, nx=True, px=max(int(ttl_s * 1000), 1)))

    def renew_lease(self, job_id: str, token: str, ttl_s: float) -> bool:
        return bool(self._scripts["renew"](keys=[self._lease_key(job_id)], args=[token, max(int(ttl_s * 1000), 1)]))

    def release_lease(self, job_id: str, token: str) -> None:
        self._scripts["release"](keys=[self._lease_key(job_id)], args=[token])

    def lease_held(self, job_id: str) -> bool:
        return bool(self.client.exists(self._lease_key(job_id)))

    def clear_leases(self) -> int:
        """Drop every run lease; returns how many. Only correct when no worker is alive (the
        embedded mode's restart of its one worker): their holders are gone."""
        keys = list(self.client.scan_iter(match=f"{PREFIX}job:*:lease", count=500))
        return int(self.client.delete(*keys)) if keys else 0
