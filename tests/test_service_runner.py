"""worker.runner.JobRunner's decisions against a real Redis, with scripted engines standing in
for core.engine (passed to the runner as its engine): skip, re-queue, resume-free finish,
failure codes, cancel and a lost lease."""
from __future__ import annotations

import threading
import time

import pytest

from jobs.settings import JobSettings
from jobs.storage import JobPaths, new_job_id
from jobs.store import JobRecord, JobStore, connect
from service.auth import tenant_hash
from worker.runner import JobRunner, Outcome

CALLS: list[str] = []


def engine_ok(input_path, depth_path, params, out_dir, on_capture=None, **kw):
    """A tiny real artefact, and the engine's hand-over of the decoded capture."""
    import torch

    from core.capture.load import capture_from_arrays
    from core.engine import JobResult
    from core.fields import FieldConfig, SceneBounds, build_field
    from core.fields.stored.artefact import save_artefact

    CALLS.append("ok")
    on_capture(capture_from_arrays(torch.full((2, 12, 16, 3), 0.5)))
    field = build_field(FieldConfig(kind="grid", uses_time=False, grid={"resolution": (2, 2, 2), "env_height": 4}),
                        SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 0.0, 0.0))
    return JobResult(save_artefact(out_dir, field))


def engine_bad_depth(*a, **kw):
    from core.capture.base import CaptureError

    raise CaptureError("depth", "no valid pixels")


def engine_crash(*a, **kw):
    raise RuntimeError("/secret/path/model.bin exploded")


def engine_until_cancelled(input_path, depth_path, params, out_dir, should_cancel=None, **kw):
    from core.engine.progress import Cancelled

    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        if should_cancel():
            raise Cancelled("job cancelled")
        time.sleep(0.02)
    raise AssertionError("never cancelled")


@pytest.fixture(scope="module")
def redis_url(tmp_path_factory):
    from service.processes import start_redis

    proc = start_redis(tmp_path_factory.mktemp("redis"))
    try:
        yield proc.url
    finally:
        proc.stop()


@pytest.fixture
def runner(redis_url, tmp_path):
    settings = JobSettings(data_dir=tmp_path, broker_url=redis_url, lease_ttl_s=2.0)
    CALLS.clear()

    def make(engine) -> JobRunner:
        return JobRunner(JobStore(connect(redis_url)), settings, engine=engine)

    return make


def _job(r: JobRunner) -> tuple[str, JobPaths]:
    rec = JobRecord(id=new_job_id(), tenant="t", tenant_hash=tenant_hash("t"), input_kind="image",
                    input_file="input.png")
    r.store.create(rec, max_in_flight=100)
    paths = JobPaths.for_job(r.settings.data_dir, rec.tenant_hash, rec.id)
    paths.upload_dir.mkdir(parents=True)
    (paths.upload_dir / "input.png").write_bytes(b"\x89PNG")
    return rec.id, paths


def test_success_records_a_relative_artefact_and_removes_uploads(runner, monkeypatch):
    from core.fields.stored.artefact import LightFieldArtefact
    from jobs.capture_preview import META_FILE, preview_dir

    r = runner(engine_ok)
    job, paths = _job(r)
    monkeypatch.setattr(LightFieldArtefact, "load", lambda *a, **k: pytest.fail("the artefact was read back"))
    assert r.run(job) is Outcome.SUCCEEDED
    rec = r.store.get(job)
    assert (rec.state, rec.attempts, rec.progress) == ("succeeded", 1, 1.0)
    assert r.settings.data_dir / rec.artefact == paths.artefact_dir
    assert not paths.upload_dir.exists()
    assert (paths.artefact_dir / "baked.safetensors").is_file()  # baked from the field in memory
    assert (preview_dir(paths.job_dir) / META_FILE).is_file()  # from the capture the engine decoded
    assert r.run(job) is Outcome.SKIPPED and CALLS == ["ok"]  # a late duplicate does nothing


def test_a_saved_artefact_is_not_recomputed_on_redelivery(runner):
    r = runner(engine_ok)
    job, paths = _job(r)
    engine_ok(None, None, None, paths.artefact_dir, on_capture=lambda c: None)  # a run died after saving
    CALLS.clear()
    r.engine = engine_crash  # would fail if called
    assert r.run(job) is Outcome.SUCCEEDED
    assert (paths.artefact_dir / "baked.safetensors").is_file()


def test_a_saved_artefact_that_fails_verification_is_estimated_again(runner):
    """Never served, never retried forever: removed, and the engine runs once more."""
    from core.fields.stored.artefact import LightFieldArtefact

    r = runner(engine_ok)
    job, paths = _job(r)
    paths.artefact_dir.mkdir(parents=True)
    (paths.artefact_dir / "lightfield.json").write_text('{"truncated": ')
    assert r.run(job) is Outcome.SUCCEEDED and CALLS == ["ok"]
    LightFieldArtefact.load(paths.artefact_dir)  # the new one verifies


def test_losing_redis_mid_run_is_retried_not_failed(runner, monkeypatch):
    """A progress write or cancel check that meets a Redis outage does not fail the job; an
    error the runner cannot record propagates, so the Celery task retries the delivery."""
    import redis as redis_lib

    r = runner(engine_ok)
    job, _ = _job(r)
    real_update = r.store.update

    def flaky_update(job_id, **kw):
        if kw.get("stage") == "baking":
            raise redis_lib.exceptions.ConnectionError("Redis went away")
        return real_update(job_id, **kw)

    monkeypatch.setattr(r.store, "update", flaky_update)
    assert r.run(job) is Outcome.SUCCEEDED  # the bake's stage update is best effort

    def engine_progress_during_outage(input_path, depth_path, params, out_dir, progress=None, should_cancel=None, **kw):
        monkeypatch.setattr(r.store, "cancel_requested", lambda _: (_ for _ in ()).throw(
            redis_lib.exceptions.ConnectionError("Redis went away")))
        assert should_cancel() is False
        return engine_ok(input_path, depth_path, params, out_dir, **kw)

    job2, _ = _job(r)
    r.engine = engine_progress_during_outage
    monkeypatch.setattr(r.store, "update", real_update)
    assert r.run(job2) is Outcome.SUCCEEDED


def test_a_held_lease_requeues_instead_of_running(runner):
    r = runner(engine_ok)
    job, _ = _job(r)
    assert r.store.acquire_lease(job, "someone-else", ttl_s=5)
    assert r.run(job) is Outcome.REQUEUE
    assert r.store.get(job).state == "queued" and CALLS == []


def test_cancel_before_start_skips_the_engine(runner):
    r = runner(engine_ok)
    job, _ = _job(r)
    r.store.request_cancel(job)
    assert r.run(job) is Outcome.SKIPPED
    assert r.store.get(job).state == "cancelled" and CALLS == []
    assert r.store.get(job).state == "cancelled" and CALLS == []


def test_input_errors_fail_with_the_field_named(runner):
    r = runner(engine_bad_depth)
    job, paths = _job(r)
    assert r.run(job) is Outcome.FAILED
    rec = r.store.get(job)
    assert (rec.state, rec.error_code) == ("failed", "invalid_depth") and "no valid pixels" in rec.error_message
    assert not paths.upload_dir.exists()


def test_engine_crashes_fail_without_leaking_internals(runner):
    r = runner(engine_crash)
    job, _ = _job(r)
    assert r.run(job) is Outcome.FAILED
    rec = r.store.get(job)
    assert rec.error_code == "engine_error" and "/secret" not in rec.error_message


def test_cancel_while_running_stops_at_the_next_check(runner):
    r = runner(engine_until_cancelled)
    job, paths = _job(r)
    threading.Timer(0.3, r.store.request_cancel, args=[job]).start()
    t0 = time.monotonic()
    assert r.run(job) is Outcome.CANCELLED
    assert time.monotonic() - t0 < 2.0
    assert r.store.get(job).state == "cancelled" and not paths.job_dir.exists()
    assert not r.store.lease_held(job)  # released on the way out


def test_a_lost_lease_abandons_the_run_without_touching_the_record(runner):
    r = runner(engine_until_cancelled)
    job, _ = _job(r)
    # another party takes over the lease (as if ours had expired): the heartbeat notices
    threading.Timer(0.3, lambda: (r.store.client.delete(f"lf:job:{job}:lease"),
                                  r.store.acquire_lease(job, "new-owner", 5))).start()
    assert r.run(job) is Outcome.ABANDONED
    rec = r.store.get(job)
    assert rec.state == "running"  # the new owner decides the outcome
    assert r.store.client.get(f"lf:job:{job}:lease") == "new-owner"


def test_input_errors_get_the_codes_the_api_documents():
    from core.camera import CameraError
    from core.capture.base import CaptureError
    from jobs.errors import error_code_of

    assert error_code_of(CaptureError("poses", "not 4x4")) == "invalid_poses"
    assert error_code_of(CameraError("fx must be positive")) == "invalid_intrinsics"  # as docs/api.md lists it
    assert error_code_of(RuntimeError("boom")) == "invalid_input"


def test_a_real_celery_worker_runs_the_runner_with_an_injected_engine(redis_url, tmp_path):
    """The worker process path (Celery app -> task -> JobRunner -> engine) with the engine
    passed in by a test-only app module (tests/scripted_worker.py)."""
    import signal

    from conftest import REPO, wait_until
    from jobs.queue import TASK_NAME, make_celery
    from service.processes import child_env, spawn, stop, worker_command

    settings = JobSettings(data_dir=tmp_path, broker_url=redis_url, lease_ttl_s=2.0)
    store = JobStore(connect(redis_url))
    rec = JobRecord(
        id=new_job_id(), tenant="t", tenant_hash=tenant_hash("t"), input_kind="image", input_file="input.png"
    )
    store.create(rec, max_in_flight=100)
    paths = JobPaths.for_job(tmp_path, rec.tenant_hash, rec.id)
    paths.upload_dir.mkdir(parents=True)
    (paths.upload_dir / "input.png").write_bytes(b"\x89PNG")
    env = child_env(LIGHTFIELD_DATA_DIR=str(tmp_path), LIGHTFIELD_BROKER_URL=redis_url,
                    PYTHONPATH=f"{REPO / 'tests'}:{REPO}")
    proc = spawn(worker_command("scripted", loglevel="WARNING", app="scripted_worker"), env=env,
                 log_path=tmp_path / "worker.log")
    try:
        make_celery(settings).send_task(TASK_NAME, args=[rec.id])
        done = wait_until(lambda: (r := store.get(rec.id)) is not None and r.is_terminal and r, 60,
                          what=f"the job to end (worker log: {tmp_path / 'worker.log'})")
    finally:
        stop(proc, signal.SIGQUIT, grace_s=5)
    assert (done.state, done.error_code) == ("failed", "invalid_depth")
    assert not paths.upload_dir.exists()


def test_one_job_decodes_its_upload_once(redis_url, tmp_path, tiny_video, monkeypatch):
    """The real engine through the runner: the video is decoded once (the UI preview reuses
    the engine's capture) and the artefact is baked from memory."""
    import core.io
    from core.engine import run_job
    from core.fields.stored.artefact import LightFieldArtefact

    decodes = []
    real_read_video = core.io.read_video
    monkeypatch.setattr(core.io, "read_video", lambda *a, **k: decodes.append(1) or real_read_video(*a, **k))
    monkeypatch.setattr(LightFieldArtefact, "load", lambda *a, **k: pytest.fail("the artefact was read back"))
    settings = JobSettings(data_dir=tmp_path, broker_url=redis_url, lease_ttl_s=5.0,
                           distill_overrides={"iterations": 2, "work_height": 24, "warmup_steps": 1})
    r = JobRunner(JobStore(connect(redis_url)), settings, engine=run_job)
    rec = JobRecord(
        id=new_job_id(), tenant="t", tenant_hash=tenant_hash("t"), input_kind="video", input_file="input.mp4"
    )
    r.store.create(rec, max_in_flight=100)
    paths = JobPaths.for_job(tmp_path, rec.tenant_hash, rec.id)
    paths.upload_dir.mkdir(parents=True)
    (paths.upload_dir / "input.mp4").write_bytes(tiny_video.read_bytes())
    with pytest.warns(UserWarning):  # no depth, no intrinsics given
        assert r.run(rec.id) is Outcome.SUCCEEDED
    assert len(decodes) == 1
    assert (paths.artefact_dir / "baked.safetensors").is_file() and (paths.job_dir / "preview").is_dir()


# -- issue 45: storage faults are the storage's, not the job's --------------------------------------------
def engine_disk_full(*a, **kw):
    """What safetensors raises when the checkpoint's directory cannot be written."""
    from safetensors import SafetensorError

    raise SafetensorError('Error while serializing: I/O error: No space left on device (os error 28) at path "x"')


def test_a_storage_fault_requeues_the_job_then_gives_up_after_the_bound(runner):
    """Issue: an unwritable artefact directory failed the job as engine_error (SafetensorError),
    never retried once storage was back."""
    r = runner(engine_disk_full)
    job, paths = _job(r)
    assert r.run(job) is Outcome.STORAGE_RETRY
    rec = r.store.get(job)
    assert (rec.state, rec.stage, rec.storage_retries, rec.error_code) == ("queued", "waiting_for_storage", 1, "")
    assert "ENOSPC" in rec.message or "SafetensorError" in rec.message
    assert r.retry_delay_s == r.settings.storage_retry_s and paths.upload_dir.is_dir()  # nothing deleted
    for n in range(2, r.settings.storage_retries + 1):
        assert r.run(job) is Outcome.STORAGE_RETRY
        assert r.retry_delay_s == r.settings.storage_retry_delay_s(n)
    assert r.run(job) is Outcome.FAILED
    rec = r.store.get(job)
    assert rec.state == "failed" and rec.error_code == "storage_unavailable"
    r.engine = engine_ok  # a terminal job is never run again
    assert r.run(job) is Outcome.SKIPPED


def test_an_engine_error_while_storage_is_unwritable_is_a_storage_fault(runner, monkeypatch):
    import worker.runner as runner_module

    r = runner(engine_crash)
    job, _ = _job(r)
    monkeypatch.setattr(runner_module, "storage_writable", lambda directory: False)
    assert r.run(job) is Outcome.STORAGE_RETRY
    monkeypatch.setattr(runner_module, "storage_writable", lambda directory: True)
    assert r.run(job) is Outcome.FAILED and r.store.get(job).error_code == "engine_error"


def test_a_resumed_run_records_the_checkpoints_iteration_then_the_final_one(runner):
    """Issue: after a restart the job was succeeded but its record still said iteration 177/600."""

    from core.engine import JobResult
    from core.fields import FieldConfig, SceneBounds, build_field
    from core.fields.stored.artefact import save_artefact

    seen = []

    def engine(input_path, depth_path, params, out_dir, **kw):
        seen.append((r.store.get(job).iteration, r.store.get(job).message))
        field = build_field(FieldConfig(kind="grid", uses_time=False, grid={"resolution": (2, 2, 2), "env_height": 4}),
                            SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 0.0, 0.0))
        return JobResult(save_artefact(out_dir, field, {"training": {"iterations": 600}}))

    r = runner(engine)
    job, paths = _job(r)
    r.store.update(job, iteration=177, total=600)  # the dead run's last progress, beyond its checkpoint
    paths.checkpoint_dir.mkdir(parents=True)
    (paths.checkpoint_dir / "checkpoint.json").write_text('{"step": 150, "fingerprint": "x"}')
    assert r.run(job) is Outcome.SUCCEEDED
    assert seen == [(150, "resuming from the checkpoint at iteration 150")]
    rec = r.store.get(job)
    assert rec.resumed and (rec.iteration, rec.total) == (600, 600)
