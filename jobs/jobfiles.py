"""A job's files between this host's directory and the shared store (jobs.blobstore).

Every host (the API, each worker) works in its own data directory, laid out as
jobs.storage.JobPaths says; the store holds the same layout under the same keys:

    uploads/<tenant-hash>/<job>/input.<ext>, depth.<ext>     the API puts, the worker gets
    artefacts/<tenant-hash>/<job>/checkpoint/checkpoint.json  a pointer: {"step": n, ...}
    artefacts/<tenant-hash>/<job>/checkpoint/<n>.safetensors  the state it points at
    artefacts/<tenant-hash>/<job>/lightfield/...              field, baked lattice; lightfield.json last
    artefacts/<tenant-hash>/<job>/preview/...                 the UI preview; capture.json last

The file a reader looks for first (a checkpoint's pointer, an artefact's lightfield.json, a
preview's capture.json) is stored last, after everything it refers to, so a reader never
finds a pointer to what is not there yet. On the API the artefacts fetched form a cache
bounded in bytes (least recently used first out); on a worker a job's local files are
removed when its run ends. With the local store on the data directory itself (the default),
every transfer here is a no-op.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import threading
import uuid
from pathlib import Path

from jobs.blobstore import BlobStore, ObjectCorrupt, store_for
from jobs.storage import JobPaths, remove_tree

log = logging.getLogger("lightfield.storage")
CHECKPOINT_POINTER = "checkpoint.json"
CHECKPOINT_STATE = "checkpoint.safetensors"
USED_MARKER = ".used"  # its mtime is the last use of a cached job directory (LRU)


class JobFiles:
    def __init__(self, store: BlobStore, data_dir: Path, cache_bytes: int = 4 << 30):
        self.store, self.data_dir, self.cache_bytes = store, Path(data_dir), cache_bytes
        self._locks: dict[str, threading.Lock] = {}
        self._locks_guard = threading.Lock()
        local = store.local_path("x")
        self.shared = local is None or local.parent.resolve() != self.data_dir.resolve()

    def key(self, local: Path) -> str:
        return Path(local).relative_to(self.data_dir).as_posix()

    # -- directories --------------------------------------------------------------------------------
    def push_dir(self, local_dir: Path, last: str | None = None) -> None:
        """Put every file of `local_dir` (recursively), the file named `last` after the others."""
        if not self.shared or not local_dir.is_dir():
            return
        files = sorted(p for p in local_dir.rglob("*") if p.is_file() and not p.name.startswith("."))
        files.sort(key=lambda p: p.name == last)
        for p in files:
            self.store.put_file(self.key(p), p)

    def pull_dir(self, local_dir: Path, first: str | None = None) -> bool:
        """Get the objects below `local_dir`'s key into it, whole: into a sibling, then renamed in
        place. When `first` is given and has no object, nothing is fetched (False)."""
        if not self.shared:
            return local_dir.is_dir()
        prefix = self.key(local_dir)
        keys = self.store.list(prefix)
        if first is not None and f"{prefix}/{first}" not in keys:
            return False
        if not keys:
            return False
        tmp = local_dir.with_name(f".{local_dir.name}.{uuid.uuid4().hex[:8]}.part")
        try:
            for key in keys:
                self.store.get_file(key, tmp / key[len(prefix) + 1:])
            remove_tree(local_dir)
            os.replace(tmp, local_dir)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return True

    # -- uploads --------------------------------------------------------------------------------------
    def push_uploads(self, paths: JobPaths) -> None:
        """API: the checked upload to the store; the local copy is then dropped (the API keeps none)."""
        if not self.shared:
            return
        self.push_dir(paths.upload_dir)
        remove_tree(paths.upload_dir)

    def pull_uploads(self, paths: JobPaths, names: list[str]) -> None:
        """Worker: the job's uploads, unless already here. A missing object is FileNotFoundError."""
        if not self.shared:
            return
        for name in names:
            local = paths.upload_dir / name
            if not local.is_file() and not self.store.get_file(self.key(local), local):
                raise FileNotFoundError(f"the job's upload {name} is not in the store")

    # -- checkpoints ----------------------------------------------------------------------------------
    def push_checkpoint(self, paths: JobPaths) -> int | None:
        """Worker: the local checkpoint to the store (state, then the pointer; older states
        dropped). Returns its step, or None when there is none."""
        pointer = paths.checkpoint_dir / CHECKPOINT_POINTER
        if not self.shared or not pointer.is_file():
            return None
        step = int(json.loads(pointer.read_text())["step"])
        prefix = self.key(paths.checkpoint_dir)
        self.store.put_file(f"{prefix}/{step}.safetensors", paths.checkpoint_dir / CHECKPOINT_STATE)
        self.store.put_file(f"{prefix}/{CHECKPOINT_POINTER}", pointer)
        stale = [
            k for k in self.store.list(prefix) if k.endswith(".safetensors") and k != f"{prefix}/{step}.safetensors"
        ]
        if stale:
            self.store.delete(stale)
        return step

    def pull_checkpoint(self, paths: JobPaths) -> int | None:
        """Worker: the stored checkpoint (another host's, if its worker died) into the local
        checkpoint directory, as the engine wrote it. Returns its step, or None."""
        if not self.shared:
            return None
        prefix = self.key(paths.checkpoint_dir)
        tmp = paths.job_dir / f".checkpoint.{uuid.uuid4().hex[:8]}.part"
        try:
            if not self.store.get_file(f"{prefix}/{CHECKPOINT_POINTER}", tmp / CHECKPOINT_POINTER):
                return None
            step = int(json.loads((tmp / CHECKPOINT_POINTER).read_text())["step"])
            if not self.store.get_file(f"{prefix}/{step}.safetensors", tmp / CHECKPOINT_STATE):
                return None
            remove_tree(paths.checkpoint_dir)
            os.replace(tmp, paths.checkpoint_dir)
            return step
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    # -- artefacts on the API: a bounded cache ---------------------------------------------------------
    def fetch_artefact(self, paths: JobPaths, refresh: bool = False) -> bool:
        """API: the job's light field (and its preview) in the local cache, fetched from the store
        when missing (or `refresh`); False when the store has none. ObjectCorrupt when a stored
        object fails its SHA-256."""
        if not self.shared:
            return True
        with self._lock_for(paths.job_dir):  # a burst of first queries fetches once
            if refresh or not (paths.artefact_dir / "lightfield.json").is_file():
                if not self.pull_dir(paths.artefact_dir, first="lightfield.json"):
                    return False
                self.pull_dir(paths.job_dir / "preview", first="capture.json")
                self._touch(paths.job_dir)
                self.evict(keep=paths.job_dir)
            else:
                self._touch(paths.job_dir)
        return True

    def _lock_for(self, job_dir: Path) -> threading.Lock:
        with self._locks_guard:
            if len(self._locks) > 4096:  # bounded: locks of jobs nobody is fetching now
                self._locks = {k: v for k, v in self._locks.items() if v.locked()}
            return self._locks.setdefault(str(job_dir), threading.Lock())

    def _touch(self, job_dir: Path) -> None:
        marker = job_dir / USED_MARKER
        try:
            marker.touch()
            os.utime(marker)
        except OSError:
            pass

    def evict(self, keep: Path | None = None) -> int:
        """Remove the least recently used cached job directories until the cache holds at most
        cache_bytes; returns how many were removed."""
        if not self.shared:
            return 0
        entries = []
        for job_dir in (self.data_dir / "artefacts").glob("*/*"):
            if not job_dir.is_dir():
                continue
            size = sum(p.stat().st_size for p in job_dir.rglob("*") if p.is_file())
            marker = job_dir / USED_MARKER
            used = marker.stat().st_mtime if marker.exists() else 0.0
            entries.append((used, size, job_dir))
        total = sum(size for _, size, _ in entries)
        removed = 0
        for _used, size, job_dir in sorted(entries, key=lambda e: e[0]):
            if total <= self.cache_bytes:
                break
            if keep is not None and job_dir.resolve() == keep.resolve():
                continue
            if remove_tree(job_dir):
                total -= size
                removed += 1
        return removed

    # -- the end of a job ---------------------------------------------------------------------------
    def push_results(self, paths: JobPaths) -> None:
        """Worker: the artefact (lightfield.json last) and the UI preview (capture.json last)."""
        self.push_dir(paths.artefact_dir, last="lightfield.json")
        self.push_dir(paths.job_dir / "preview", last="capture.json")

    def finish_run(self, paths: JobPaths) -> None:
        """Worker, after success: the uploads and checkpoint are no longer needed anywhere, and
        this host keeps nothing of the job."""
        if not self.shared:
            return
        self.store.delete_prefix(self.key(paths.upload_dir))
        self.store.delete_prefix(self.key(paths.checkpoint_dir))
        self.forget_local(paths)

    def forget_local(self, paths: JobPaths) -> None:
        if self.shared:
            paths.remove_all()

    def delete_job(self, paths: JobPaths) -> list[str]:
        """Everything the job owns, in the store and here; returns what could not be deleted."""
        left = []
        if self.shared:
            if not self.store.delete_prefix(self.key(paths.upload_dir)):
                left.append("uploads")
            if not self.store.delete_prefix(self.key(paths.job_dir)):
                left.append("artefacts")
        for part in paths.remove_all():
            if part not in left:
                left.append(part)
        return left


def job_files(settings) -> JobFiles:
    """The JobFiles of a JobSettings (LIGHTFIELD_STORAGE_URL, LIGHTFIELD_DATA_DIR, LIGHTFIELD_CACHE_BYTES)."""
    return JobFiles(store_for(settings.storage_url, settings.data_dir), settings.data_dir, settings.cache_bytes)


__all__ = ["JobFiles", "ObjectCorrupt", "job_files"]
