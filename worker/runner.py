"""One delivery of a distillation job: lease, run the engine, record the outcome.

Kept free of Celery so its decisions (skip, re-queue, resume, fail) are plain functions of
the job record, the lease and the engine's behaviour. The engine is a constructor argument
(the project's `run_job` in worker.app, scripted engines in tests); `worker.tasks` is the
Celery shim.
"""
from __future__ import annotations

import errno
import json
import logging
import time
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from jobs.errors import broker_errors, error_code_of, user_error_types
from jobs.jobfiles import job_files
from jobs.lease import RunLease
from jobs.settings import JobSettings
from jobs.storage import JobPaths, is_storage_error, remove_tree, storage_writable
from jobs.store import JobStore

if TYPE_CHECKING:
    from core.engine import JobResult
    from core.fields.stored.artefact import LightFieldArtefact

log = logging.getLogger("lightfield.worker")

PROGRESS_MIN_INTERVAL_S = 0.2  # progress writes per job are throttled to ~5/s


class Outcome(str, Enum):
    SKIPPED = "skipped"  # unknown or already finished job, or cancelled before it started
    REQUEUE = "requeue"  # another delivery holds the lease; try again later
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"
    ABANDONED = "abandoned"  # lease lost mid-run: another worker owns the job now
    STORAGE_RETRY = "storage_retry"  # the storage failed: re-queued to resume from its checkpoint later


@dataclass
class JobRunner:
    store: JobStore
    settings: JobSettings
    # core.engine.run_job(input, depth, params, out_dir, *, progress, should_cancel, checkpoint_dir,
    #                    limits, on_capture, overrides=None, prior_factory=None) -> JobResult
    engine: Callable[..., "JobResult"]
    # how the engine builds the job's prior (worker.prior_cache keeps weight-loading ones); None: the engine's own
    prior_factory: Callable[..., object] | None = None
    retry_delay_s: float = 0.0  # after Outcome.STORAGE_RETRY: when to deliver the job again
    _files: object = None

    @property
    def files(self):
        """jobs.jobfiles.JobFiles: this host's directory and the shared store (a no-op by default)."""
        if self._files is None:
            self._files = job_files(self.settings)
        return self._files

    def run(self, job_id: str) -> Outcome:
        record = self.store.get(job_id)
        if record is None or record.is_terminal:
            return Outcome.SKIPPED
        if self.store.cancel_requested(job_id) and record.state == "queued":
            self.store.update(job_id, allowed=("queued",), state="cancelled", finished_at=time.time())
            return Outcome.SKIPPED
        lease = RunLease(self.store, job_id, self.settings.lease_ttl_s)
        if not lease.acquire():
            return Outcome.REQUEUE
        with lease:
            record = self.store.get(job_id)  # re-read under the lease
            if record is None or record.is_terminal:
                return Outcome.SKIPPED
            return self._run_leased(record, lease)

    def _run_leased(self, record, lease: RunLease) -> Outcome:
        job_id = record.id
        paths = JobPaths.for_job(self.settings.data_dir, record.tenant_hash, job_id)
        try:  # with a shared store: the uploads, and a checkpoint another host's run left (jobs.jobfiles)
            self.files.pull_uploads(paths, [n for n in (record.input_file, record.depth_file) if n])
            self.files.pull_checkpoint(paths)
        except Exception as exc:
            if is_storage_error(exc):
                return self._storage_fault(job_id, paths, exc)
            raise
        resumed = paths.checkpoint_dir.is_dir() and any(paths.checkpoint_dir.iterdir())
        step = checkpoint_step(paths.checkpoint_dir) if resumed else None
        # the record says where the run restarts: the checkpoint's iteration, not the dead run's last progress
        restart = {"iteration": step, "message": f"resuming from the checkpoint at iteration {step}"} if step else \
            {"message": "resuming from checkpoint" if resumed else ""}
        started = self.store.update(
            job_id, allowed=("queued", "running"), state="running", attempts=record.attempts + 1,
            started_at=record.started_at or time.time(), resumed=record.resumed or resumed,
            stage="starting", **restart,
        )
        if not started:
            return Outcome.SKIPPED
        log.info("job %s: run %d%s", job_id, record.attempts + 1, " (resuming)" if resumed else "")

        from core.engine.progress import Cancelled  # noqa: PLC0415 — core.engine.progress pulls in av, cv2, OpenEXR, PIL, safetensors, scipy, torch: imported when used

        user_errors = user_error_types()
        try:
            saved = self._saved_artefact(job_id, paths)
            result = None if saved is not None else self._call_engine(record, paths, lease)
            relative = self._relative_artefact(result.path if result else paths.artefact_dir, paths)
        except Cancelled:
            if lease.lost.is_set():
                return Outcome.ABANDONED
            self.store.update(job_id, allowed=("running",), state="cancelled", finished_at=time.time(),
                              stage="cancelled", eta_s=None)
            if self.files.delete_job(paths):
                log.warning("job %s: files left on storage after cancelling; DELETE removes them", job_id)
            return Outcome.CANCELLED
        except user_errors as exc:
            self._fail(record, paths, error_code_of(exc), str(exc))
            return Outcome.FAILED
        except Exception as exc:  # the engine broke: log it, tell the user without internals
            if isinstance(exc, broker_errors()):  # Redis went away mid-run: not the job's fault, retry it
                raise
            if is_storage_error(exc) or not storage_writable(paths.job_dir):  # the disk's fault, not the job's
                return self._storage_fault(job_id, paths, exc)
            log.exception("job %s: engine error", job_id)
            self._fail(record, paths, "engine_error", f"the estimation failed ({type(exc).__name__}); see worker logs")
            return Outcome.FAILED

        if lease.lost.is_set():
            self.files.forget_local(paths)  # another host runs it now
            return Outcome.ABANDONED
        artefact = result.artefact if result else saved
        self._prebake(job_id, artefact)
        try:  # the artefact, its bake and the preview to the shared store, lightfield.json last
            self.files.push_results(paths)
        except Exception as exc:
            if is_storage_error(exc):
                return self._storage_fault(job_id, paths, exc)
            raise
        iterations = int(artefact.meta.get("training", {}).get("iterations") or 0)
        done = {"iteration": iterations, "total": iterations} if iterations else {}
        self.store.update(job_id, allowed=("running",), state="succeeded", progress=1.0, stage="done",
                          message="light field ready", eta_s=0.0, artefact=relative, finished_at=time.time(), **done)
        if paths.remove_uploads() or not remove_tree(paths.checkpoint_dir):
            log.warning("job %s: its uploads or checkpoint could not be deleted (storage); DELETE removes them", job_id)
        try:
            self.files.finish_run(paths)  # shared store: uploads and checkpoint deleted there, nothing kept here
        except OSError:
            log.warning("job %s: its uploads or checkpoint could not be deleted from the store", job_id, exc_info=True)
        return Outcome.SUCCEEDED

    def _storage_fault(self, job_id: str, paths: JobPaths, exc: Exception) -> Outcome:
        """The storage failed mid-run (full, read-only, gone): give the job back to the queue to
        resume from its last checkpoint (written atomically, so it survived) once storage is
        back, after a growing delay; failed as storage_unavailable after settings.storage_retries."""
        record = self.store.get(job_id)
        if record is None:
            return Outcome.SKIPPED
        kind = errno.errorcode.get(getattr(exc, "errno", None) or 0, type(exc).__name__)
        retry, limit = record.storage_retries + 1, self.settings.storage_retries
        log.warning("job %s: storage error during %s (%s: %s); retry %d of %d", job_id, record.stage or "the run",
                    type(exc).__name__, exc, retry, limit)
        if retry > limit:
            self.store.update(job_id, allowed=("running", "queued"), state="failed", error_code="storage_unavailable",
                              error_message=f"the storage failed {retry} times in a row ({kind}); the job was "
                                            "given up", finished_at=time.time(), eta_s=None, storage_retries=retry)
            return Outcome.FAILED
        self.retry_delay_s = self.settings.storage_retry_delay_s(retry)
        applied = self.store.update(
            job_id,
            allowed=("running", "queued"),
            state="queued",
            stage="waiting_for_storage",
            eta_s=None,
            storage_retries=retry,
            message=f"storage error ({kind}) during {record.stage or 'the run'}: resuming from "
            f"the last checkpoint in {self.retry_delay_s:g} s (retry {retry} of {limit})",
        )
        return Outcome.STORAGE_RETRY if applied else Outcome.SKIPPED

    def _call_engine(self, record, paths: JobPaths, lease: RunLease) -> "JobResult":
        from core.engine.params import JobParams  # noqa: PLC0415 — core.engine.params pulls in av, cv2, OpenEXR, PIL, safetensors, scipy, torch: imported when used
        from core.io.limits import MediaLimits  # noqa: PLC0415 — core.io.limits pulls in av, cv2, OpenEXR, PIL, torch: imported when used

        params = JobParams.model_validate_json(record.params or "{}")
        paths.job_dir.mkdir(parents=True, exist_ok=True)
        kwargs = dict(
            progress=self._progress_writer(record.id, paths),
            should_cancel=lambda: lease.lost.is_set() or self._cancel_requested(record.id),
            checkpoint_dir=paths.checkpoint_dir,
            limits=MediaLimits.from_env(),
            on_capture=lambda capture: self._save_ui_preview(record.id, capture, paths),
        )
        if self.settings.distill_overrides:  # applied to the job's preset by the engine (resolve_job)
            kwargs["overrides"] = {"distill": self.settings.distill_overrides}
        if self.prior_factory is not None:
            kwargs["prior_factory"] = self.prior_factory
        depth = paths.upload_dir / record.depth_file if record.depth_file else None
        return self.engine(paths.upload_dir / record.input_file, depth, params, paths.artefact_dir, **kwargs)

    def _saved_artefact(self, job_id: str, paths: JobPaths) -> "LightFieldArtefact | None":
        """The artefact a previous run saved before dying (the engine renames a complete
        directory into place): finish it, don't redo it. One that fails verification is
        removed and the engine runs again (from its checkpoint), so it is never served."""
        from core.fields.stored.artefact import META_FILE, ArtefactError, LightFieldArtefact  # noqa: PLC0415 — core.fields.stored.artefact pulls in safetensors, torch: imported when used

        self.files.pull_dir(paths.artefact_dir, first=META_FILE)  # a shared store's copy, if one was pushed
        if not (paths.artefact_dir / META_FILE).is_file():
            return None
        try:
            return LightFieldArtefact.load(paths.artefact_dir)
        except ArtefactError as exc:
            log.error("job %s: the saved artefact failed verification (%s); estimating it again", job_id, exc)
            remove_tree(paths.artefact_dir)
            return None

    def _cancel_requested(self, job_id: str) -> bool:
        try:
            return self.store.cancel_requested(job_id)
        except broker_errors():  # Redis restarting: keep going, the next step asks again
            return False

    def _prebake(self, job_id: str, artefact: "LightFieldArtefact") -> None:
        """Precompute the quality=baked lattice now, from the field in memory (or the directory
        a previous run saved), so no API request pays for it. Optional: a failure here only
        means the API bakes on the first fast query."""
        try:
            from core.fields.stored.bake import load_or_bake  # noqa: PLC0415 — core.fields.stored.bake pulls in safetensors, torch: imported when used

            self.store.update(job_id, allowed=("running",), stage="baking", message="precomputing quality=baked")
            load_or_bake(artefact, save=True)
        except Exception:
            log.warning("job %s: baking the fast path failed", job_id, exc_info=True)

    @staticmethod
    def _save_ui_preview(job_id: str, capture, paths: JobPaths) -> None:
        """Keep small frames + depth of the engine's decoded capture for the web page
        (jobs.capture_preview), since the uploads are deleted when the job ends. Optional:
        without it the page cannot show frames."""
        try:
            from jobs.capture_preview import write_capture_preview  # noqa: PLC0415 — jobs.capture_preview pulls in numpy: imported when used

            write_capture_preview(capture, paths.job_dir)
        except Exception:
            log.warning("job %s: storing the UI preview failed", job_id, exc_info=True)

    def _progress_writer(self, job_id: str, paths: JobPaths | None = None):
        last = {"t": 0.0, "stage": None, "checkpoint": None}

        def write(p) -> None:
            if paths is not None and self.files.shared:  # a new checkpoint goes to the store at once
                pointer = paths.checkpoint_dir / "checkpoint.json"
                stamp = pointer.stat().st_mtime_ns if pointer.is_file() else None
                if stamp is not None and stamp != last["checkpoint"]:
                    self.files.push_checkpoint(paths)  # a storage error here is the run's (retried)
                    last["checkpoint"] = stamp
            now = time.monotonic()
            if p.stage == last["stage"] and now - last["t"] < PROGRESS_MIN_INTERVAL_S:
                return
            last["t"], last["stage"] = now, p.stage
            # a stage change carries no iteration (0 of 0): the record keeps the last one it had,
            # which after a resume is the checkpoint's, until the loop reports again
            steps = {"iteration": int(p.iteration), "total": int(p.total)} if p.total else {}
            try:
                self.store.update(
                    job_id, allowed=("running",), progress=min(max(float(p.fraction), 0.0), 1.0), stage=p.stage,
                    loss=p.loss, eta_s=p.eta_s, message=getattr(p, "message", "") or "", **steps,
                )
            except broker_errors():  # progress is best effort: a Redis restart must not fail the job
                log.warning("job %s: progress not recorded (Redis unreachable)", job_id)

        return write

    def _fail(self, record, paths: JobPaths, code: str, message: str) -> None:
        self.store.update(record.id, allowed=("running",), state="failed", error_code=code,
                          error_message=message[:2000], finished_at=time.time(), eta_s=None)
        if self.files.delete_job(paths):
            log.warning("job %s: files left on storage after failing; DELETE removes them", record.id)

    def _relative_artefact(self, artefact: Path, paths: JobPaths) -> str:
        """The engine's returned directory, checked to lie inside this job's area."""
        resolved = artefact.resolve()
        if not resolved.is_relative_to(paths.job_dir.resolve()):
            raise RuntimeError(f"engine wrote its artefact outside the job area: {artefact}")
        return str(resolved.relative_to(Path(self.settings.data_dir).resolve()))


def checkpoint_step(checkpoint_dir: Path) -> int | None:
    """The iteration a run restarting from `checkpoint_dir` resumes at (its checkpoint.json), or None."""
    from core.engine.checkpoints import CHECKPOINT_META  # noqa: PLC0415 — core.engine.checkpoints pulls in av, cv2, OpenEXR, PIL, safetensors, scipy, torch: imported when used

    try:
        step = json.loads((checkpoint_dir / CHECKPOINT_META).read_text()).get("step")
    except (OSError, ValueError, AttributeError):
        return None
    return int(step) if isinstance(step, int) and step > 0 else None
