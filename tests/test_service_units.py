"""Service building blocks without HTTP: settings, keys, paths, query parsing, the streaming
form reader, and the Redis job store against a real redis-server."""
from __future__ import annotations

import asyncio
import math
import uuid

import pytest
from hypothesis import given, settings, strategies as st

from jobs.settings import SettingsError
from jobs.storage import JobPaths, is_job_id, new_job_id
from jobs.store import JobLimitReached, JobRecord, JobStore, connect
from service.auth import LOCAL_TENANT, AuthConfigError, KeyRing, is_loopback, require_loopback, tenant_hash
from service.config import ServiceLimits, ServiceSettings
from service.errors import BadRequest, InvalidInput, PayloadTooLarge, Unauthorized, UnsupportedMedia
from service.queries import check_t, parse_x
from service.upload import FormReader


# -- settings --------------------------------------------------------------------------------
def test_settings_read_limits_and_reject_garbage(tmp_path):
    s = ServiceSettings.from_env({"LIGHTFIELD_DATA_DIR": str(tmp_path), "LIGHTFIELD_MAX_ENVMAP_HEIGHT": "256",
                                  "LIGHTFIELD_VISIBILITY_TIMEOUT": "7.5"})
    assert s.data_dir == tmp_path and s.limits.max_envmap_height == 256 and s.visibility_timeout_s == 7.5
    with pytest.raises(SettingsError, match="LIGHTFIELD_MAX_BATCH"):
        ServiceSettings.from_env({"LIGHTFIELD_MAX_BATCH": "many"})
    with pytest.raises(SettingsError):
        ServiceSettings.from_env({"LIGHTFIELD_MAX_BATCH": "0"})
    with pytest.raises(SettingsError, match="DISTILL_OVERRIDES"):
        ServiceSettings.from_env({"LIGHTFIELD_DISTILL_OVERRIDES": "{not json"})


# -- auth ------------------------------------------------------------------------------------
def test_keyring_maps_keys_to_tenants_and_rejects_everything_else(tmp_path):
    ring = KeyRing.parse("alice:alice-secret-1, bob:bob-secret-22")
    assert ring.tenant_for("Bearer alice-secret-1") == "alice"
    assert ring.tenant_for("bearer bob-secret-22") == "bob"
    for bad in (None, "", "Bearer", "Bearer alice-secret-", "Basic alice-secret-1", "alice-secret-1"):
        with pytest.raises(Unauthorized):
            ring.tenant_for(bad)
    keyfile = tmp_path / "keys"
    keyfile.write_text("# tenants\ncarol:carol-secret-333\n")
    assert KeyRing.parse(str(keyfile)).tenant_for("Bearer carol-secret-333") == "carol"


def test_keyring_without_keys_is_the_local_tenant_and_loopback_only():
    ring = KeyRing.parse(None)
    assert ring.tenant_for(None) == LOCAL_TENANT
    require_loopback("127.0.0.1", ring)
    require_loopback("::1", ring)
    with pytest.raises(AuthConfigError, match="0.0.0.0"):
        require_loopback("0.0.0.0", ring)
    require_loopback("0.0.0.0", KeyRing.parse("a:long-enough-key"))
    assert is_loopback("localhost") and not is_loopback("example.com")


@pytest.mark.parametrize("spec", ["alice", "alice:short", "al ice:long-enough-key", "a:same-key-123,b:same-key-123"])
def test_keyring_rejects_malformed_specs(spec):
    with pytest.raises(AuthConfigError):
        KeyRing.parse(spec)


def test_tenant_hash_is_stable_hex_and_distinct():
    assert tenant_hash("alice") == tenant_hash("alice") != tenant_hash("bob")
    assert all(c in "0123456789abcdef" for c in tenant_hash("../../etc"))


# -- paths -----------------------------------------------------------------------------------
def test_job_paths_only_from_uuid4_and_hex(tmp_path):
    job = new_job_id()
    assert is_job_id(job)
    paths = JobPaths.for_job(tmp_path, tenant_hash("t"), job)
    assert paths.upload_dir.parent.parent == tmp_path / "uploads"
    assert paths.artefact_dir.is_relative_to(tmp_path / "artefacts")
    for bad_job in ("../x", str(uuid.uuid1()), job.upper(), ""):
        with pytest.raises(ValueError):
            JobPaths.for_job(tmp_path, tenant_hash("t"), bad_job)
    with pytest.raises(ValueError):
        JobPaths.for_job(tmp_path, "../..", job)


# -- query parsing ---------------------------------------------------------------------------
@given(st.tuples(*[st.floats(min_value=-1e6, max_value=1e6, width=32)] * 3))
@settings(max_examples=50, deadline=None)
def test_parse_x_round_trips_finite_triples(xyz):
    assert parse_x(",".join(repr(v) for v in xyz)) == pytest.approx(xyz)


@pytest.mark.parametrize("text", ["", "1,2", "1,2,3,4", "a,b,c", "nan,0,0", "0,inf,0", "1;2;3", "1,,2",
                                  "1e300,0,0", "0,-1000001,0"])
def test_parse_x_rejects_anything_but_three_finite_numbers(text):
    with pytest.raises(InvalidInput) as err:
        parse_x(text)
    assert err.value.code == "invalid_x"


def test_check_t_rejects_non_finite():
    assert check_t(1.5) == 1.5
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(InvalidInput):
            check_t(bad)


# -- streaming form reader -------------------------------------------------------------------
BOUNDARY = "testboundary1234"


def _multipart(parts: list[tuple[str, bytes]], close: bool = True) -> bytes:
    out = b""
    for name, data in parts:
        out += (f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"{name}\"; filename=\"{name}\"\r\n"
                "Content-Type: application/octet-stream\r\n\r\n").encode() + data + b"\r\n"
    return out + (f"--{BOUNDARY}--\r\n".encode() if close else b"")


def _read(body: bytes, tmp_path, limits=ServiceLimits(), chunk=7):  # noqa: B008 — only read
    async def chunks():
        for i in range(0, len(body), chunk):
            yield body[i:i + chunk]

    reader = FormReader(tmp_path, limits)
    return asyncio.run(reader.read(f"multipart/form-data; boundary={BOUNDARY}", str(len(body)), chunks()))


def test_form_reader_streams_files_to_disk_in_small_chunks(tmp_path):
    payload = bytes(range(256)) * 40
    form = _read(_multipart([("file", payload), ("params", b'{"seed": 3}')]), tmp_path)
    assert form.files["file"].read_bytes() == payload
    assert form.texts["params"] == '{"seed": 3}'
    assert form.sizes["file"] == len(payload)


def test_form_reader_stops_at_the_size_limit(tmp_path):
    limits = ServiceLimits(max_upload_bytes=1000)
    with pytest.raises(PayloadTooLarge):
        _read(_multipart([("file", b"x" * 1001)]), tmp_path, limits)
    (tmp_path / "ok").mkdir()
    assert _read(_multipart([("file", b"x" * 1000)]), tmp_path / "ok", limits).sizes["file"] == 1000


@pytest.mark.parametrize("parts,close,error,code", [
    ([("file", b"abc"), ("bogus", b"1")], True, InvalidInput, "unknown_field"),
    ([("file", b"abc"), ("file", b"def")], True, InvalidInput, "duplicate_field"),
    ([("params", b"{}")], True, InvalidInput, "missing_file"),
    ([("file", b"abc")], False, BadRequest, "truncated_body"),
])
def test_form_reader_rejects_bad_forms(tmp_path, parts, close, error, code):
    with pytest.raises(error) as err:
        _read(_multipart(parts, close=close), tmp_path)
    assert err.value.code == code


def test_form_reader_requires_multipart(tmp_path):
    async def empty():
        yield b""

    with pytest.raises(UnsupportedMedia):
        asyncio.run(FormReader(tmp_path, ServiceLimits()).read("application/json", "2", empty()))


# -- job store (real Redis) ------------------------------------------------------------------
@pytest.fixture(scope="module")
def store(tmp_path_factory):
    from service.processes import start_redis

    proc = start_redis(tmp_path_factory.mktemp("redis"))
    try:
        yield JobStore(connect(proc.url))
    finally:
        proc.stop()


def _record(tenant="alice") -> JobRecord:
    return JobRecord(id=new_job_id(), tenant=tenant, tenant_hash=tenant_hash(tenant))


def test_store_transitions_are_conditional_and_counted(store):
    rec = _record()
    store.create(rec, max_in_flight=10)
    assert store.update(rec.id, allowed=("queued",), state="running", progress=0.25)
    assert not store.update(rec.id, allowed=("queued",), state="cancelled")  # lost the race
    assert store.update(rec.id, allowed=("running",), state="succeeded", loss=None)
    got = store.get(rec.id)
    assert (got.state, got.progress, got.loss) == ("succeeded", 0.25, None)
    assert got.version == 3 - 1  # two applied updates
    assert not store.update(rec.id, allowed=("running",), progress=0.5)  # terminal records are frozen
    counts = store.state_counts()
    assert counts["succeeded"] >= 1 and all(v >= 0 for v in counts.values())


def test_store_enforces_in_flight_limit_per_tenant(store):
    recs = [_record("limited") for _ in range(2)]
    for r in recs:
        store.create(r, max_in_flight=2)
    with pytest.raises(JobLimitReached):
        store.create(_record("limited"), max_in_flight=2)
    store.create(_record("other"), max_in_flight=2)  # other tenants are unaffected
    store.update(recs[0].id, allowed=("queued",), state="failed")
    store.create(_record("limited"), max_in_flight=2)  # a finished job frees its slot


def test_store_lists_newest_first_and_deletes(store):
    recs = [_record("lister") for _ in range(3)]
    for r in recs:
        store.create(r, max_in_flight=10)
    page, total = store.list(tenant_hash("lister"), 0, 2)
    assert total == 3 and [r.id for r in page] == [recs[2].id, recs[1].id]
    assert store.delete(store.get(recs[0].id))
    assert store.get(recs[0].id) is None and store.list(tenant_hash("lister"), 0, 10)[1] == 2


def test_store_lease_is_exclusive_and_expires(store):
    job = new_job_id()
    assert store.acquire_lease(job, "a", ttl_s=0.3)
    assert not store.acquire_lease(job, "b", ttl_s=0.3)
    assert not store.renew_lease(job, "b", ttl_s=0.3)  # only the holder renews
    assert store.renew_lease(job, "a", ttl_s=0.3)
    store.release_lease(job, "b")  # not the holder: no effect
    assert store.lease_held(job)
    import time

    time.sleep(0.45)
    assert store.acquire_lease(job, "b", ttl_s=0.3)


# -- field cache -----------------------------------------------------------------------------
def test_field_cache_loads_each_key_once_under_concurrent_misses_and_evicts_least_recent(tmp_path):
    import threading
    import time

    from service.fieldcache import FieldCache

    loads: list = []

    def slow_loader(directory):
        loads.append(directory)
        time.sleep(0.05)  # keep the first load in flight while the other threads miss
        return object()

    cache = FieldCache(capacity=2, loader=slow_loader)
    got: list = []
    threads = [threading.Thread(target=lambda: got.append(cache.get("a", tmp_path / "a"))) for _ in range(6)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert len(loads) == 1 and all(item is got[0] for item in got)
    cache.get("b", tmp_path / "b")
    cache.get("a", tmp_path / "a")  # a is now the most recent; c pushes b out
    cache.get("c", tmp_path / "c")
    assert len(cache) == 2 and len(loads) == 3
    assert cache.get("a", tmp_path / "a") is got[0]
    cache.get("b", tmp_path / "b")
    assert len(loads) == 4 and loads[-1] == tmp_path / "b"
