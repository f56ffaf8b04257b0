"""A live session's updates: each delivery refines the session's field from its last version
with the frames seen so far, until no new frame is waiting, and stores each result as the
next version; an ended session's last version becomes a normal stored field.

Kept free of Celery (worker.tasks is the shim), like worker.runner. One update at a time per
session: the run lease (jobs.lease) on the session id; a delivery that finds it held comes
back later. A worker killed mid-update loses only that update: the message is re-delivered
(acks_late) and the next run starts from the last stored version, which was written whole.
"""
from __future__ import annotations

import logging
import shutil
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from enum import Enum
from typing import Callable

from jobs.errors import user_error_types
from jobs.jobfiles import job_files
from jobs.lease import RunLease
from jobs.session_files import SessionPaths, fetch_version, pull_frames, push_version, write_capture
from jobs.sessions import SessionRecord, SessionStore
from jobs.settings import JobSettings
from jobs.storage import remove_tree
from jobs.store import JobRecord, JobStore

log = logging.getLogger("lightfield.worker")

KEEP_VERSIONS = 3  # older versions are deleted: a session's storage stays bounded by its frames
WARM_STATES = 4  # sessions whose last field state this worker keeps in memory


class SessionOutcome(str, Enum):
    SKIPPED = "skipped"
    REQUEUE = "requeue"  # another delivery holds the session's lease
    UPDATED = "updated"
    ABANDONED = "abandoned"


@dataclass
class SessionUpdater:
    store: JobStore
    sessions: SessionStore
    settings: JobSettings
    engine: Callable  # core.engine.run_job
    prior_factory: Callable | None = None
    _files: object = None
    _states: OrderedDict = field(default_factory=OrderedDict)  # session id -> (version, state_dict)

    @property
    def files(self):
        if self._files is None:
            self._files = job_files(self.settings)
        return self._files

    def run(self, session_id: str) -> SessionOutcome:
        if self.sessions.get(session_id) is None:
            return SessionOutcome.SKIPPED
        lease = RunLease(self.store, session_id, self.settings.lease_ttl_s)
        if not lease.acquire():
            return SessionOutcome.REQUEUE
        with lease:
            self.sessions.unschedule(session_id)  # frames from now on queue another delivery
            updated = False
            while not lease.lost.is_set():
                record = self.sessions.get(session_id)
                if record is None:
                    return SessionOutcome.SKIPPED
                if record.frames <= max(record.latest_frames, record.tried_frames):
                    if not record.is_live and not record.final:
                        self._finish(record)
                    break
                self._update(record, record.frames, lease)
                updated = True
            if lease.lost.is_set():
                return SessionOutcome.ABANDONED
        return SessionOutcome.UPDATED if updated else SessionOutcome.SKIPPED

    # -- one version ------------------------------------------------------------------------
    def _update(self, record: SessionRecord, count: int, lease: RunLease) -> None:
        from core.engine.params import JobParams  # noqa: PLC0415 — core.engine.params pulls in av, cv2, OpenEXR, PIL, safetensors, scipy, torch: imported when used
        from core.io.limits import MediaLimits  # noqa: PLC0415 — core.io.limits pulls in av, cv2, OpenEXR, PIL, torch: imported when used

        t0 = time.perf_counter()
        paths = SessionPaths.of(self.settings.data_dir, record.tenant_hash, record.id)
        version = record.latest + 1
        params = JobParams.model_validate_json(record.params or "{}")
        try:
            frames = self.sessions.frames(record.id, count)
            pull_frames(self.files, paths, [n for f in frames for n in (f["image"], f.get("depth")) if n])
            capture = write_capture(paths, frames, params.fps, None)
            result = self.engine(
                capture, None, params, paths.version_dir(version),
                should_cancel=lease.lost.is_set, checkpoint_dir=None, limits=MediaLimits.from_env(),
                overrides={"distill": self._loop_settings(first=not record.latest)},
                init_state=self._last_state(record, paths),
                **({"prior_factory": self.prior_factory} if self.prior_factory is not None else {}))
        except user_error_types() as exc:  # the frames so far cannot make a field: say so, wait for more
            log.info("session %s: update on %d frames failed: %s", record.id, count, exc)
            self.sessions.set(record.id, tried_frames=count, update_error=str(exc)[:2000])
            return
        except Exception as exc:
            if lease.lost.is_set():
                return
            log.exception("session %s: update on %d frames failed", record.id, count)
            self.sessions.set(record.id, tried_frames=count,
                              update_error=f"the update failed ({type(exc).__name__}); see worker logs")
            return
        finally:
            remove_tree(paths.capture_dir)
        if lease.lost.is_set():
            return
        push_version(self.files, paths, version)
        self._remember(record.id, version, result.artefact.field.state_dict())
        self.sessions.set(record.id, latest=version, latest_frames=count, latest_at=time.time(), update_error="")
        self._drop_old_versions(paths, version)
        log.info("session %s: version %d from %d frames in %.2f s", record.id, version, count,
                 time.perf_counter() - t0)

    def _loop_settings(self, first: bool) -> dict:
        """The operator's loop overrides, with at most settings.session_steps steps (a bounded
        cost per version; session_first_steps for the first, so the first answer comes soon), and
        no fallback."""
        loop = dict(self.settings.distill_overrides)
        steps = self.settings.session_first_steps if first else self.settings.session_steps
        loop["iterations"] = min(int(loop.get("iterations", steps)), steps)
        loop["checkpoint_every"] = loop["iterations"] + 1  # a version is the checkpoint
        # a version is a step of a refinement, not a final answer: stored as distilled (graded; its
        # grade travels with every answer) so the next version warm-starts from it, not from a
        # constant map that the first few steps' field would lose to
        loop["fallback"] = False
        return loop

    def _last_state(self, record: SessionRecord, paths: SessionPaths):
        """The last version's field state (this worker's memory, else the store), or None."""
        if not record.latest:
            return None
        held = self._states.get(record.id)
        if held is not None and held[0] == record.latest:
            return held[1]
        from core.fields.stored.artefact import ArtefactError, LightFieldArtefact  # noqa: PLC0415 — core.fields.stored.artefact pulls in safetensors, torch: imported when used

        try:
            if not fetch_version(self.files, paths, record.latest):
                return None
            state = LightFieldArtefact.load(paths.version_dir(record.latest)).field.state_dict()
        except (ArtefactError, OSError):
            log.warning("session %s: version %d unreadable; starting afresh", record.id, record.latest, exc_info=True)
            return None
        self._remember(record.id, record.latest, state)
        return state

    def _remember(self, session_id: str, version: int, state: dict) -> None:
        self._states[session_id] = (version, state)
        self._states.move_to_end(session_id)
        while len(self._states) > WARM_STATES:
            self._states.popitem(last=False)

    def _drop_old_versions(self, paths: SessionPaths, latest: int) -> None:
        for old in range(max(latest - KEEP_VERSIONS - 2, 1), latest - KEEP_VERSIONS + 1):
            if self.files.shared:
                self.files.store.delete_prefix(self.files.key(paths.version_dir(old)))
            remove_tree(paths.version_dir(old))

    # -- the end of a session ---------------------------------------------------------------
    def _finish(self, record: SessionRecord) -> None:
        """The last version as the session's stored field (a succeeded job of the same id, so
        every query route and DELETE /jobs/<id> treat it as any job's), then the frames go."""
        paths = SessionPaths.of(self.settings.data_dir, record.tenant_hash, record.id)
        if record.latest and fetch_version(self.files, paths, record.latest):
            remove_tree(paths.final_dir)
            shutil.copytree(paths.version_dir(record.latest), paths.final_dir)
            self.files.push_results(paths.job)
            now = time.time()
            job = JobRecord(id=record.id, tenant=record.tenant, tenant_hash=record.tenant_hash, input_kind="session",
                            params=record.params, message=f"live session: version {record.latest} from "
                                                          f"{record.latest_frames} frames")
            if self.store.get(record.id) is None:
                self.store.create(job, max_in_flight=1 << 30)  # not a queued job: never refused
            relative = str(paths.final_dir.resolve().relative_to(self.settings.data_dir.resolve()))
            self.store.update(record.id, state="succeeded", progress=1.0, stage="done", artefact=relative,
                              started_at=record.created_at, finished_at=now)
        for version in range(1, record.latest + 1):
            if self.files.shared:
                self.files.store.delete_prefix(self.files.key(paths.version_dir(version)))
            remove_tree(paths.version_dir(version))
        if self.files.shared:
            self.files.store.delete_prefix(self.files.key(paths.job.upload_dir))
        remove_tree(paths.job.upload_dir)
        self.sessions.set(record.id, final=True)
        self._states.pop(record.id, None)
        log.info("session %s: ended with version %d", record.id, record.latest)
