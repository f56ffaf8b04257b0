"""Live sessions in Redis, shared by every API process and worker (docs/api.md, "Live sessions").

A session collects frames as a phone captures them; a worker turns the frames seen so far into
a new version of the light field, warm-started from the last one. Nothing of a session lives
in one process's memory: the record, the frames' metadata and the update flag are here, the
frames' files and the versions' artefacts in the blob store (jobs.blobstore), so any API
process answers and any worker updates.

Keys (prefix `lf:`):
    session:<id>                hash: the record (SessionRecord)
    session:<id>:frames         list: one JSON object per accepted frame (its file names, pose, exposure)
    session:<id>:scheduled      set while an update is queued (coalesces a burst of frame posts)
    session:<id>:rate:<second>  frames accepted in that second (the rate limit's window)
    tenant:<thash>:sessions     set of the tenant's live session ids (the per-tenant limit)

A session's id is a UUID4 like a job's: when it ends its last version becomes a normal stored
field under the same id (jobs.storage.JobPaths), answered as a succeeded job's.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, fields

import redis

from jobs.store import PREFIX, _decode, _encode

SESSION_STATES = ("live", "ended", "expired")


class SessionLimitReached(RuntimeError):
    """The tenant already has the maximum number of live sessions."""


class SessionFull(RuntimeError):
    """A frame limit (count, bytes or rate) refuses the batch; the message says which."""

    def __init__(self, message: str, code: str):
        super().__init__(message)
        self.code = code


@dataclass
class SessionRecord:
    id: str
    tenant: str
    tenant_hash: str
    state: str = "live"
    params: str = "{}"  # JobParams JSON, as a job's
    frames: int = 0  # frames accepted
    bytes: int = 0  # their stored size
    width: int = 0  # every frame's size, fixed by the first
    height: int = 0
    with_depth: bool = False  # fixed by the first frame: all frames have depth or none
    with_pose: bool = False  # fixed by the first frame: all frames have a pose or none
    latest: int = 0  # newest stored version (0: none yet)
    latest_frames: int = 0  # frames the newest version had seen
    latest_at: float | None = None
    tried_frames: int = 0  # frames the last update attempt had (a failed one is not retried on them)
    update_error: str = ""  # the last update's failure, in words (the session goes on)
    final: bool = False  # the ended session's field is stored as a job's (GET /lightfield/<id>)
    created_at: float = 0.0
    last_active: float = 0.0
    ended_at: float | None = None

    def to_redis(self) -> dict[str, str]:
        return {f.name: _encode(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_redis(cls, raw: dict[str, str]) -> "SessionRecord":
        return cls(**{f.name: _decode(raw[f.name], f.type) for f in fields(cls) if f.name in raw})

    @property
    def is_live(self) -> bool:
        return self.state == "live"


# Append frames unless a limit refuses them. KEYS: session, frames list, rate key.
# ARGV: now, max frames, max bytes, max per second, batch bytes, then one JSON per frame.
# Returns {0, reason} or {1, first index}.
_APPEND_LUA = """
if redis.call('HGET', KEYS[1], 'state') ~= 'live' then return {0, 'not_live'} end
local n = tonumber(redis.call('HGET', KEYS[1], 'frames'))
local b = tonumber(redis.call('HGET', KEYS[1], 'bytes'))
local k = #ARGV - 5
if n + k > tonumber(ARGV[2]) then return {0, 'too_many_frames'} end
if b + tonumber(ARGV[5]) > tonumber(ARGV[3]) then return {0, 'too_many_bytes'} end
local rate = tonumber(redis.call('GET', KEYS[3]) or '0')
if rate + k > tonumber(ARGV[4]) then return {0, 'rate_limited'} end
redis.call('INCRBY', KEYS[3], k)
redis.call('EXPIRE', KEYS[3], 2)
for i = 6, #ARGV do redis.call('RPUSH', KEYS[2], ARGV[i]) end
redis.call('HSET', KEYS[1], 'frames', n + k, 'bytes', b + tonumber(ARGV[5]), 'last_active', ARGV[1])
return {1, n}
"""

# Create unless the tenant is at its limit. KEYS: session, tenant set. ARGV: limit, id, pairs...
_CREATE_LUA = """
if redis.call('SCARD', KEYS[2]) >= tonumber(ARGV[1]) then return 0 end
for i = 3, #ARGV, 2 do redis.call('HSET', KEYS[1], ARGV[i], ARGV[i + 1]) end
redis.call('SADD', KEYS[2], ARGV[2])
return 1
"""

# End a live session. KEYS: session, tenant set. ARGV: new state, now. Returns 1 if it was live.
_END_LUA = """
if redis.call('HGET', KEYS[1], 'state') ~= 'live' then return 0 end
redis.call('HSET', KEYS[1], 'state', ARGV[1], 'ended_at', ARGV[2])
redis.call('SREM', KEYS[2], redis.call('HGET', KEYS[1], 'id'))
return 1
"""


@dataclass
class SessionStore:
    client: redis.Redis
    retention_s: float = 7 * 24 * 3600  # an ended session's record and frame list
    _scripts: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        for name, src in (("append", _APPEND_LUA), ("create", _CREATE_LUA), ("end", _END_LUA)):
            self._scripts[name] = self.client.register_script(src)

    @staticmethod
    def key(session_id: str) -> str:
        return f"{PREFIX}session:{session_id}"

    @staticmethod
    def _tenant_key(thash: str) -> str:
        return f"{PREFIX}tenant:{thash}:sessions"

    def create(self, record: SessionRecord, max_live: int) -> None:
        record.created_at = record.last_active = time.time()
        pairs = [x for kv in record.to_redis().items() for x in kv]
        if not self._scripts["create"](keys=[self.key(record.id), self._tenant_key(record.tenant_hash)],
                                       args=[max_live, record.id, *pairs]):
            raise SessionLimitReached(f"at most {max_live} live sessions per tenant")

    def get(self, session_id: str) -> SessionRecord | None:
        raw = self.client.hgetall(self.key(session_id))
        return SessionRecord.from_redis(raw) if raw else None

    def set(self, session_id: str, **values) -> None:
        """Set fields of an existing record (never re-creates a deleted one)."""
        if not self.client.exists(self.key(session_id)):
            return
        self.client.hset(self.key(session_id), mapping={k: _encode(v) for k, v in values.items()})

    def live_count(self, thash: str) -> int:
        return int(self.client.scard(self._tenant_key(thash)))

    def live_ids(self, thash: str) -> list[str]:
        """The tenant's live session ids; one whose record is gone (its keys expired) is dropped."""
        ids = sorted(self.client.smembers(self._tenant_key(thash)))
        gone = [sid for sid in ids if not self.client.exists(self.key(sid))]
        if gone:
            self.client.srem(self._tenant_key(thash), *gone)
        return [sid for sid in ids if sid not in gone]

    def append_frames(self, session_id: str, frames: list[dict], nbytes: int, *, max_frames: int,
                      max_bytes: int, max_per_s: int) -> int:
        """Record accepted frames atomically under the limits; returns the first one's index.
        SessionFull (its .code: too_many_frames, too_many_bytes, rate_limited, not_live) else."""
        now = time.time()
        ok, detail = self._scripts["append"](
            keys=[self.key(session_id), self.key(session_id) + ":frames",
                  f"{self.key(session_id)}:rate:{int(now)}"],
            args=[now, max_frames, max_bytes, max_per_s, nbytes, *(json.dumps(f) for f in frames)])
        if not ok:
            message = {"too_many_frames": f"a session holds at most {max_frames} frames",
                       "too_many_bytes": f"a session's frames may take at most {max_bytes} bytes",
                       "rate_limited": f"at most {max_per_s} frames per second per session",
                       "not_live": "the session has ended"}[detail]
            raise SessionFull(message, detail)
        return int(detail)

    def frames(self, session_id: str, count: int | None = None) -> list[dict]:
        end = -1 if count is None else count - 1
        return [json.loads(x) for x in self.client.lrange(self.key(session_id) + ":frames", 0, end)]

    def end(self, record: SessionRecord, state: str = "ended") -> bool:
        """live -> ended/expired; the record and frames are kept retention_s for the final update."""
        done = bool(self._scripts["end"](keys=[self.key(record.id), self._tenant_key(record.tenant_hash)],
                                         args=[state, time.time()]))
        if done:
            for suffix in ("", ":frames"):
                self.client.expire(self.key(record.id) + suffix, int(self.retention_s))
        return done

    def delete(self, record: SessionRecord) -> None:
        self.client.srem(self._tenant_key(record.tenant_hash), record.id)
        self.client.delete(self.key(record.id), self.key(record.id) + ":frames", self.key(record.id) + ":scheduled")

    # -- update scheduling: one queued update per session at a time --------------------------
    def schedule(self, session_id: str, ttl_s: float) -> bool:
        """True when no update was queued (the caller enqueues one). Expires after ttl_s so a
        message lost with its worker never blocks the session's updates for good."""
        return bool(self.client.set(self.key(session_id) + ":scheduled", "1", nx=True, px=int(ttl_s * 1000)))

    def unschedule(self, session_id: str) -> None:
        self.client.delete(self.key(session_id) + ":scheduled")
