"""Where a job's files live on the storage root.

    <data_dir>/uploads/<tenant-hash>/<job-id>/      input + depth, removed when the job ends
    <data_dir>/artefacts/<tenant-hash>/<job-id>/    lightfield/ (the artefact), checkpoint/

Paths are built only from a server-generated UUID4 and a hash of the tenant, never from
anything a client sent, and `JobPaths.for_job` re-checks both so a corrupted record cannot
point outside the root.
"""
from __future__ import annotations

import errno
import os
import re
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path

_HEX = re.compile(r"^[0-9a-f]{8,64}$")


def new_job_id() -> str:
    return str(uuid.uuid4())


def is_job_id(value: str) -> bool:
    try:
        return str(uuid.UUID(value, version=4)) == value
    except (ValueError, AttributeError, TypeError):
        return False


@dataclass(frozen=True)
class JobPaths:
    upload_dir: Path
    job_dir: Path  # artefact area of the job

    @property
    def artefact_dir(self) -> Path:
        return self.job_dir / "lightfield"

    @property
    def checkpoint_dir(self) -> Path:
        return self.job_dir / "checkpoint"

    @classmethod
    def for_job(cls, data_dir: Path, tenant_hash: str, job_id: str) -> "JobPaths":
        if not _HEX.match(tenant_hash) or not is_job_id(job_id):
            raise ValueError("job paths need a hex tenant hash and a UUID4 job id")
        root = Path(data_dir)
        return cls(root / "uploads" / tenant_hash / job_id, root / "artefacts" / tenant_hash / job_id)

    def remove_uploads(self) -> list[str]:
        """Delete the job's uploads; returns what is left (["uploads"] when storage refused)."""
        return [] if remove_tree(self.upload_dir) else ["uploads"]

    def remove_all(self) -> list[str]:
        """Delete everything the job owns on the storage root; returns the parts that could not be
        deleted ("uploads", "artefacts": the light field, checkpoint and preview), so a caller
        can say so and keep the record that owns them instead of orphaning files."""
        left = self.remove_uploads()
        if not remove_tree(self.job_dir):
            left.append("artefacts")
        return left


def remove_tree(path: Path) -> bool:
    """rmtree that reports instead of raising: True when nothing is left at `path`."""
    shutil.rmtree(path, ignore_errors=True)
    return not os.path.lexists(path)


# OSError numbers that mean "the storage refused", not "this job's data is bad"
STORAGE_ERRNOS = frozenset({errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EROFS, errno.EDQUOT, errno.EIO,
                            errno.ENOTDIR, errno.ENOENT, errno.ESTALE, errno.ENODEV, errno.ENXIO, errno.ETIMEDOUT})


def is_storage_error(exc: BaseException) -> bool:
    """An exception from writing or reading the storage root (a full, read-only, unmounted or
    unreachable disk) rather than from the job's data or the engine's logic. safetensors
    reports I/O failures as SafetensorError("... I/O error: ... (os error N) ...")."""
    if isinstance(exc, OSError):
        return exc.errno in STORAGE_ERRNOS or exc.errno is None and "No space" in str(exc)
    if type(exc).__name__ == "SafetensorError":
        match = re.search(r"\(os error (\d+)\)|Os \{ code: (\d+)", str(exc))
        return bool(match) and int(match.group(1) or match.group(2)) in STORAGE_ERRNOS
    return False


def storage_writable(directory: Path) -> bool:
    """Whether a file can be created, written, synced and removed in `directory` now (made if
    missing): the check a worker makes before blaming an error on the storage."""
    probe = Path(directory) / f".probe-{uuid.uuid4().hex}"
    try:
        Path(directory).mkdir(parents=True, exist_ok=True)
        with open(probe, "wb") as f:
            f.write(b"probe")
            f.flush()
            os.fsync(f.fileno())
        probe.unlink()
        return True
    except OSError:
        return False
