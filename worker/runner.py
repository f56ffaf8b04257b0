"""One delivery of a distillation job: lease, run the engine, record the outcome.

Kept free of Celery so its decisions (skip, re-queue, resume, fail) are plain functions of
the job record, the lease and the engine's behaviour. The engine is a constructor argument
(the project's `run_job` in worker.app, scripted engines in tests); `worker.tasks` is the
Celery shim.
"""
from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from jobs.errors import error_code_of, user_error_types
from jobs.lease import RunLease
from jobs.settings import JobSettings
from jobs.storage import JobPaths
from jobs.store import JobStore

if TYPE_CHECKING:
    from core.engine import JobResult
    from core.fields.artefact import LightFieldArtefact

log = logging.getLogger("lightfield.worker")

PROGRESS_MIN_INTERVAL_S = 0.2  # progress writes per job are throttled to ~5/s


class Outcome(str, Enum):
    SKIPPED = "skipped"  # unknown or already finished job, or cancelled before it started
    REQUEUE = "requeue"  # another delivery holds the lease; try again later
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"
    ABANDONED = "abandoned"  # lease lost mid-run: another worker owns the job now


@dataclass
class JobRunner:
    store: JobStore
    settings: JobSettings
    # core.engine.run_job(input, depth, params, out_dir, *, progress, should_cancel, checkpoint_dir,
    #                    limits, on_capture, config=None, prior_factory=None) -> JobResult
    engine: Callable[..., "JobResult"]
    # how the engine builds the job's prior (worker.prior_cache keeps weight-loading ones); None: the engine's own
    prior_factory: Callable[..., object] | None = None

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
        resumed = paths.checkpoint_dir.is_dir() and any(paths.checkpoint_dir.iterdir())
        started = self.store.update(
            job_id, allowed=("queued", "running"), state="running", attempts=record.attempts + 1,
            started_at=record.started_at or time.time(), resumed=record.resumed or resumed,
            stage="starting", message="resuming from checkpoint" if resumed else "",
        )
        if not started:
            return Outcome.SKIPPED
        log.info("job %s: run %d%s", job_id, record.attempts + 1, " (resuming)" if resumed else "")

        from core.engine.progress import Cancelled

        user_errors = user_error_types()
        try:
            result = None if self._artefact_saved(paths) else self._call_engine(record, paths, lease)
            relative = self._relative_artefact(result.path if result else paths.artefact_dir, paths)
        except Cancelled:
            if lease.lost.is_set():
                return Outcome.ABANDONED
            self.store.update(job_id, allowed=("running",), state="cancelled", finished_at=time.time(),
                              stage="cancelled", eta_s=None)
            paths.remove_all()
            return Outcome.CANCELLED
        except user_errors as exc:
            self._fail(record, paths, error_code_of(exc), str(exc))
            return Outcome.FAILED
        except Exception as exc:  # the engine broke: log it, tell the user without internals
            log.exception("job %s: engine error", job_id)
            self._fail(record, paths, "engine_error", f"the estimation failed ({type(exc).__name__}); see worker logs")
            return Outcome.FAILED

        if lease.lost.is_set():
            return Outcome.ABANDONED
        self._prebake(job_id, result.artefact if result else paths.artefact_dir)
        self.store.update(job_id, allowed=("running",), state="succeeded", progress=1.0, stage="done",
                          message="light field ready", eta_s=0.0, artefact=relative, finished_at=time.time())
        paths.remove_uploads()
        shutil.rmtree(paths.checkpoint_dir, ignore_errors=True)
        return Outcome.SUCCEEDED

    def _call_engine(self, record, paths: JobPaths, lease: RunLease) -> "JobResult":
        from core.engine.params import JobParams
        from core.io.limits import MediaLimits

        params = JobParams.model_validate_json(record.params or "{}")
        paths.job_dir.mkdir(parents=True, exist_ok=True)
        kwargs = dict(
            progress=self._progress_writer(record.id),
            should_cancel=lambda: lease.lost.is_set() or self.store.cancel_requested(record.id),
            checkpoint_dir=paths.checkpoint_dir,
            limits=MediaLimits.from_env(),
            on_capture=lambda capture: self._save_ui_preview(record.id, capture, paths),
        )
        if self.settings.distill_overrides:
            from core.engine.presets import preset

            kwargs["config"] = preset(params.preset).with_overrides({"distill": self.settings.distill_overrides})
        if self.prior_factory is not None:
            kwargs["prior_factory"] = self.prior_factory
        depth = paths.upload_dir / record.depth_file if record.depth_file else None
        return self.engine(paths.upload_dir / record.input_file, depth, params, paths.artefact_dir, **kwargs)

    @staticmethod
    def _artefact_saved(paths: JobPaths) -> bool:
        """Whether a previous run saved the artefact before dying (the engine renames a
        complete directory into place, so its metadata file means it is whole): finish, don't redo."""
        from core.fields.artefact import META_FILE

        return (paths.artefact_dir / META_FILE).is_file()

    def _prebake(self, job_id: str, artefact: "LightFieldArtefact | Path") -> None:
        """Precompute the quality=fast lattice now, from the field in memory (or the directory
        a previous run saved), so no API request pays for it. Optional: a failure here only
        means the API bakes on the first fast query."""
        try:
            from core.fields.artefact import LightFieldArtefact
            from core.fields.bake import load_or_bake

            self.store.update(job_id, allowed=("running",), stage="baking", message="precomputing quality=fast")
            load_or_bake(LightFieldArtefact.load(artefact) if isinstance(artefact, Path) else artefact, save=True)
        except Exception:
            log.warning("job %s: baking the fast path failed", job_id, exc_info=True)

    @staticmethod
    def _save_ui_preview(job_id: str, capture, paths: JobPaths) -> None:
        """Keep small frames + depth of the engine's decoded capture for the web page
        (jobs.capture_preview), since the uploads are deleted when the job ends. Optional:
        without it the page cannot show frames."""
        try:
            from jobs.capture_preview import write_capture_preview

            write_capture_preview(capture, paths.job_dir)
        except Exception:
            log.warning("job %s: storing the UI preview failed", job_id, exc_info=True)

    def _progress_writer(self, job_id: str):
        last = {"t": 0.0, "stage": None}

        def write(p) -> None:
            now = time.monotonic()
            if p.stage == last["stage"] and now - last["t"] < PROGRESS_MIN_INTERVAL_S:
                return
            last["t"], last["stage"] = now, p.stage
            self.store.update(
                job_id, allowed=("running",), progress=min(max(float(p.fraction), 0.0), 1.0), stage=p.stage,
                iteration=int(p.iteration), total=int(p.total), loss=p.loss, eta_s=p.eta_s,
                message=getattr(p, "message", "") or "",
            )

        return write

    def _fail(self, record, paths: JobPaths, code: str, message: str) -> None:
        self.store.update(record.id, allowed=("running",), state="failed", error_code=code,
                          error_message=message[:2000], finished_at=time.time(), eta_s=None)
        paths.remove_all()

    def _relative_artefact(self, artefact: Path, paths: JobPaths) -> str:
        """The engine's returned directory, checked to lie inside this job's area."""
        resolved = artefact.resolve()
        if not resolved.is_relative_to(paths.job_dir.resolve()):
            raise RuntimeError(f"engine wrote its artefact outside the job area: {artefact}")
        return str(resolved.relative_to(Path(self.settings.data_dir).resolve()))
