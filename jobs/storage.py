"""Where a job's files live on the storage root.

    <data_dir>/uploads/<tenant-hash>/<job-id>/      input + depth, removed when the job ends
    <data_dir>/artefacts/<tenant-hash>/<job-id>/    lightfield/ (the artefact), checkpoint/

Paths are built only from a server-generated UUID4 and a hash of the tenant, never from
anything a client sent, and `JobPaths.for_job` re-checks both so a corrupted record cannot
point outside the root.
"""
from __future__ import annotations

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

    def remove_uploads(self) -> None:
        shutil.rmtree(self.upload_dir, ignore_errors=True)

    def remove_all(self) -> None:
        self.remove_uploads()
        shutil.rmtree(self.job_dir, ignore_errors=True)
