"""Issue 47: the storage layer (jobs.blobstore, jobs.jobfiles) against a real S3-API server (moto in
server mode on a loopback port), and the service on several "hosts" that share only Redis and
the object store: API and two workers with separate local directories, one worker `kill -9`'d
mid-job and the job finishing on the other from its checkpoint, the API answering for a field
it never had on disk, and a corrupted stored object answered 410."""
from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest

from conftest import ServiceStack, wait_until

MB = 1 << 20


@pytest.fixture
def s3_env(s3_server, monkeypatch):
    for k, v in s3_server.env.items():
        monkeypatch.setenv(k, v)
    return s3_server


@pytest.fixture
def store(s3_env, tmp_path):
    from jobs.blobstore import S3Store

    prefix = f"t{time.monotonic_ns()}"
    return S3Store(s3_env.bucket, prefix)


# -- the store -------------------------------------------------------------------------------------------
def test_s3_objects_round_trip_verified_and_listed(store, tmp_path):
    src = tmp_path / "a.bin"
    src.write_bytes(os.urandom(3 * MB + 17))
    store.put_file("x/y/a.bin", src)
    assert store.exists("x/y/a.bin") and not store.exists("x/y/b.bin")
    assert store.get_file("x/y/a.bin", tmp_path / "out" / "a.bin") is True
    assert (tmp_path / "out" / "a.bin").read_bytes() == src.read_bytes()
    assert store.get_file("x/y/missing", tmp_path / "out" / "m") is False and not (tmp_path / "out" / "m").exists()
    store.put_file("x/z.bin", src)
    assert store.list("x") == ["x/y/a.bin", "x/z.bin"] and store.list("x/y") == ["x/y/a.bin"]
    assert store.delete_prefix("x") and store.list("x") == []


def test_an_object_that_no_longer_matches_its_sha256_is_never_kept(store, s3_env, tmp_path):
    from jobs.blobstore import ObjectCorrupt

    src = tmp_path / "f.safetensors"
    src.write_bytes(b"abc" * 1000)
    store.put_file("k/f.safetensors", src)
    head = s3_env.client().head_object(Bucket=store.bucket, Key=f"{store.prefix}/k/f.safetensors")
    s3_env.client().put_object(Bucket=store.bucket, Key=f"{store.prefix}/k/f.safetensors", Body=b"abd" * 1000,
                               Metadata=head["Metadata"])  # bytes changed behind the service's back
    dest = tmp_path / "got" / "f.safetensors"
    with pytest.raises(ObjectCorrupt):
        store.get_file("k/f.safetensors", dest)
    assert not dest.exists() and not list(dest.parent.iterdir())  # no partial file either


def test_an_unreachable_store_is_an_oserror_the_service_waits_out(tmp_path, monkeypatch):
    from jobs.blobstore import S3Store, StorageUnavailable
    from jobs.storage import is_storage_error
    from service.processes import free_port

    monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{free_port()}")  # nothing listens
    for k in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
        monkeypatch.setenv(k, "x")
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    (tmp_path / "f").write_bytes(b"x")
    with pytest.raises(StorageUnavailable) as err:
        S3Store("b").put_file("k", tmp_path / "f")
    assert is_storage_error(err.value)


def test_the_default_store_is_the_data_directory_and_moves_nothing(tmp_path):
    from jobs.blobstore import LocalStore, store_for
    from jobs.jobfiles import JobFiles
    from jobs.storage import JobPaths, new_job_id

    store = store_for(None, tmp_path)
    assert isinstance(store, LocalStore)
    files = JobFiles(store, tmp_path)
    assert files.shared is False
    paths = JobPaths.for_job(tmp_path, "ab" * 8, new_job_id())
    paths.upload_dir.mkdir(parents=True)
    (paths.upload_dir / "input.png").write_bytes(b"x")
    files.push_uploads(paths)  # no copy, and the upload stays where the worker reads it
    assert (paths.upload_dir / "input.png").is_file()
    assert files.delete_job(paths) == [] and not paths.upload_dir.exists()


def test_checkpoints_move_through_the_store_pointer_last(store, tmp_path):
    from jobs.jobfiles import JobFiles
    from jobs.storage import JobPaths, new_job_id

    job = new_job_id()
    a = JobFiles(store, tmp_path / "host-a")
    b = JobFiles(store, tmp_path / "host-b")
    assert a.shared and b.shared
    pa, pb = (JobPaths.for_job(f.data_dir, "cd" * 8, job) for f in (a, b))
    pa.checkpoint_dir.mkdir(parents=True)
    for step in (4, 8):
        (pa.checkpoint_dir / "checkpoint.safetensors").write_bytes(f"state {step}".encode())
        (pa.checkpoint_dir / "checkpoint.json").write_text(json.dumps({"step": step, "fingerprint": "f"}))
        assert a.push_checkpoint(pa) == step
    prefix = a.key(pa.checkpoint_dir)
    assert sorted(store.list(prefix)) == [f"{prefix}/8.safetensors", f"{prefix}/checkpoint.json"]  # old state dropped
    assert b.pull_checkpoint(pb) == 8
    assert (pb.checkpoint_dir / "checkpoint.safetensors").read_bytes() == b"state 8"
    assert json.loads((pb.checkpoint_dir / "checkpoint.json").read_text())["step"] == 8


def test_the_local_cache_is_bounded_least_recently_used_first(store, tmp_path):
    from jobs.jobfiles import JobFiles
    from jobs.storage import JobPaths, new_job_id

    worker = JobFiles(store, tmp_path / "worker")
    api = JobFiles(store, tmp_path / "api", cache_bytes=int(2.5 * MB))
    jobs = [new_job_id() for _ in range(3)]
    for job in jobs:
        paths = JobPaths.for_job(worker.data_dir, "ef" * 8, job)
        paths.artefact_dir.mkdir(parents=True)
        (paths.artefact_dir / "field.safetensors").write_bytes(os.urandom(MB))
        (paths.artefact_dir / "lightfield.json").write_text("{}")
        worker.push_results(paths)
    local = [JobPaths.for_job(api.data_dir, "ef" * 8, job) for job in jobs]
    for paths in local[:2]:
        assert api.fetch_artefact(paths)
        time.sleep(0.02)
    assert api.fetch_artefact(local[0])  # used again: now the most recent
    time.sleep(0.02)
    assert api.fetch_artefact(local[2])  # 3 MB > 2.5 MB: the least recently used (job 1) goes
    assert [p.job_dir.exists() for p in local] == [True, False, True]
    missing = JobPaths.for_job(api.data_dir, "ef" * 8, new_job_id())
    assert api.fetch_artefact(missing) is False


def test_a_burst_of_first_queries_fetches_a_field_once(store, tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    from jobs.jobfiles import JobFiles
    from jobs.storage import JobPaths, new_job_id

    job = new_job_id()
    worker = JobFiles(store, tmp_path / "worker")
    paths = JobPaths.for_job(worker.data_dir, "ab" * 8, job)
    paths.artefact_dir.mkdir(parents=True)
    (paths.artefact_dir / "field.safetensors").write_bytes(os.urandom(MB))
    (paths.artefact_dir / "lightfield.json").write_text("{}")
    worker.push_results(paths)
    api = JobFiles(store, tmp_path / "api")
    fetched = []
    real = api.pull_dir
    api.pull_dir = lambda *a, **k: fetched.append(1) or real(*a, **k)
    local = JobPaths.for_job(api.data_dir, "ab" * 8, job)
    with ThreadPoolExecutor(8) as pool:
        assert all(pool.map(lambda _: api.fetch_artefact(local), range(16)))
    assert len(fetched) == 2  # lightfield/ and preview/, once
    assert (local.artefact_dir / "field.safetensors").read_bytes() == (
        paths.artefact_dir / "field.safetensors"
    ).read_bytes()


# -- several hosts: the service sharing only Redis and the object store -----------------------------------
class MultiHostStack(ServiceStack):
    """The API and each worker with a data directory of its own (their "hosts"), sharing only
    Redis and the S3 store."""

    def host_dir(self, name: str) -> Path:
        return self.root / f"host-{name}"

    def env(self, host: str = "api") -> dict[str, str]:
        env = super().env()
        env["LIGHTFIELD_DATA_DIR"] = str(self.host_dir(host))
        return env

    @property
    def data_dir(self) -> Path:
        return self.host_dir("api")

    def start_worker(self):
        from service.processes import spawn, worker_command

        n = len(self.workers)
        proc = spawn(worker_command(f"w{n}", loglevel="INFO"), env=self.env(f"w{n}"),
                     log_path=self.root / f"worker{n}.log")
        self.workers.append(proc)
        return proc


@pytest.fixture
def multi_host(tmp_path, s3_server):
    prefix = f"multi{time.monotonic_ns()}"
    env = {**s3_server.env, "LIGHTFIELD_STORAGE_URL": f"s3://{s3_server.bucket}/{prefix}",
           "LIGHTFIELD_DISTILL_OVERRIDES": json.dumps({"iterations": 60, "checkpoint_every": 2, "work_height": 24,
                                                       "warmup_steps": 2})}
    stack = MultiHostStack(tmp_path / "stack", extra_env=env)
    try:
        stack.start(workers=2)
        stack.wait_ready()
        yield stack, prefix
    finally:
        stack.stop()


@pytest.mark.slow
def test_a_job_survives_its_worker_on_another_host_and_is_served_by_an_api_that_never_had_it(
        multi_host, s3_server, tiny_image):
    stack, prefix = multi_host
    with stack.client("alice") as c:
        resp = c.post("/jobs", files={"file": ("room.png", tiny_image.read_bytes())})
        assert resp.status_code == 202, resp.text
        job = resp.json()["id"]
        assert not list(stack.host_dir("api").glob(f"uploads/*/{job}/*"))  # the API keeps no upload
        assert any(k.startswith(f"{prefix}/uploads/") for k in s3_server.keys(prefix))
        pointer = wait_until(
            lambda: [k for k in s3_server.keys(prefix) if k.endswith(f"{job}/checkpoint/checkpoint.json")],
            120,
            interval_s=0.05,
            what="a checkpoint in the store",
        )
        assert pointer
        runner = next(i for i in range(2) if list(stack.host_dir(f"w{i}").glob(f"artefacts/*/{job}")))
        stack.workers[runner].send_signal(signal.SIGKILL)  # the host running it dies
        stack.workers[runner].wait(timeout=10)
        final = wait_until(lambda: (lambda b: b if b["state"] in ("succeeded", "failed", "cancelled") else None)(
            c.get(f"/jobs/{job}").json()), 240, interval_s=0.25, what="the job to end on the other host")
        assert final["state"] == "succeeded", (final, stack.log(f"worker{1 - runner}"))
        assert final["resumed"] is True and final["attempts"] == 2
        other = stack.host_dir(f"w{1 - runner}")
        assert "resuming" in stack.log(f"worker{1 - runner}") or final["resumed"]
        # the worker keeps nothing afterwards, here or in the store (it cleans up just after it has
        # published the success)
        wait_until(lambda: not list(other.glob(f"artefacts/*/{job}/lightfield/*")) and not any(
            "/uploads/" in k or "/checkpoint/" in k for k in s3_server.keys(prefix) if job in k), 30, interval_s=0.1,
            what="the worker to delete its local copy, the upload and the checkpoint")
        keys = s3_server.keys(prefix)
        assert any(k.endswith(f"{job}/lightfield/lightfield.json") for k in keys)

        api_copy = list(stack.host_dir("api").glob(f"artefacts/*/{job}"))
        assert not api_copy  # the API never had the field on disk...
        resp = c.get(f"/lightfield/{job}/envmap", params={"x": "0,0,-1", "format": "npy", "height": 32})
        assert resp.status_code == 200, resp.text  # ...and answers for it, fetched from the store
        assert list(stack.host_dir("api").glob(f"artefacts/*/{job}/lightfield/field.safetensors"))
        assert c.get(f"/lightfield/{job}/frame").status_code == 200  # the preview came along

        assert c.delete(f"/jobs/{job}").status_code == 204
        assert not [k for k in s3_server.keys(prefix) if job in k]  # DELETE removes it from the store too


@pytest.mark.slow
def test_a_stored_object_that_fails_its_checksum_is_410(multi_host, s3_server, tiny_image):
    stack, prefix = multi_host
    from jobs.store import JobStore, connect

    with stack.client("alice") as c:
        job = c.post("/jobs", files={"file": ("room.png", tiny_image.read_bytes())}).json()["id"]
        final = wait_until(lambda: (lambda b: b if b["state"] in ("succeeded", "failed") else None)(
            c.get(f"/jobs/{job}").json()), 240, interval_s=0.25, what="the job")
        assert final["state"] == "succeeded", final
        s3 = s3_server.client()
        key = next(k for k in s3_server.keys(prefix) if k.endswith(f"{job}/lightfield/field.safetensors"))
        head = s3.head_object(Bucket=s3_server.bucket, Key=key)
        data = bytearray(s3.get_object(Bucket=s3_server.bucket, Key=key)["Body"].read())
        data[-5] ^= 1
        s3.put_object(Bucket=s3_server.bucket, Key=key, Body=bytes(data), Metadata=head["Metadata"])
        resp = c.get(f"/lightfield/{job}/envmap", params={"x": "0,0,-1"})
        assert resp.status_code == 410 and resp.json()["error"]["code"] == "artefact_corrupt", resp.text
        assert "SHA-256" in resp.json()["error"]["message"]
        assert JobStore(connect(stack.redis.url)).get(job).error_code == "artefact_corrupt"


@pytest.mark.slow
def test_an_unreachable_store_is_503_at_submission_and_nothing_is_kept(tmp_path, tiny_image):
    from service.processes import free_port

    dead = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    env = {"AWS_ACCESS_KEY_ID": "x", "AWS_SECRET_ACCESS_KEY": "x", "AWS_DEFAULT_REGION": "us-east-1",
           "AWS_ENDPOINT_URL": dead, "LIGHTFIELD_STORAGE_URL": "s3://nowhere/jobs"}
    stack = MultiHostStack(tmp_path / "stack", extra_env=env)
    try:
        stack.start(workers=0)
        with stack.client("alice") as c:
            resp = c.post("/jobs", files={"file": ("room.png", tiny_image.read_bytes())})
            assert resp.status_code == 503, resp.text
            assert resp.json()["error"]["code"] == "storage_unavailable" and int(resp.headers["retry-after"]) > 0
            assert dead not in resp.text
            assert c.get("/jobs").json()["total"] == 0  # no record
        assert not list(stack.host_dir("api").glob("uploads/*/*"))  # no upload left on the API's disk
    finally:
        stack.stop()
