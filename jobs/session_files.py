"""Where a live session's files live, and the capture a worker builds from them.

    uploads/<tenant-hash>/<session>/frames/<n>.<ext>       each accepted frame, as sent (a video
                                                           chunk's frames as 16-bit PNGs)
    uploads/<tenant-hash>/<session>/frames/<n>.depth.npy   its depth, when the session has depth
    artefacts/<tenant-hash>/<session>/versions/<v>/        version v: a whole artefact (lightfield.json last)
    artefacts/<tenant-hash>/<session>/lightfield/          the final field once the session ends,
                                                           where a job's artefact lives

Frame files go to the blob store one by one as they are accepted (the API keeps none), and a
worker fetches only the frames it does not hold yet, so an update costs the new frames'
transfer, not the session's. Paths come from jobs.storage.JobPaths (a server UUID4 and the
tenant's hash) and server-chosen frame numbers, never from what a client sent.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from jobs.jobfiles import JobFiles
from jobs.storage import JobPaths, remove_tree

CAPTURE_DIR = "capture"  # the worker's capture directory (core.capture.load's lightfield-capture format)


@dataclass(frozen=True)
class SessionPaths:
    job: JobPaths

    @classmethod
    def of(cls, data_dir: Path, tenant_hash: str, session_id: str) -> "SessionPaths":
        return cls(JobPaths.for_job(data_dir, tenant_hash, session_id))

    @property
    def frames_dir(self) -> Path:
        return self.job.upload_dir / "frames"

    def version_dir(self, version: int) -> Path:
        return self.job.job_dir / "versions" / str(int(version))

    @property
    def final_dir(self) -> Path:
        return self.job.artefact_dir

    @property
    def capture_dir(self) -> Path:
        return self.job.upload_dir / CAPTURE_DIR


def frame_name(index: int, suffix: str) -> str:
    return f"{int(index):06d}{suffix}"


def store_frame(files: JobFiles, paths: SessionPaths, name: str, data: bytes) -> None:
    """API: one accepted frame's file into the store (written locally first: with the local
    store that is the store; with a shared one the local copy is dropped once uploaded)."""
    local = paths.frames_dir / name
    local.parent.mkdir(parents=True, exist_ok=True)
    tmp = local.with_name(f".{name}.part")
    tmp.write_bytes(data)
    os.replace(tmp, local)
    if files.shared:
        files.store.put_file(files.key(local), local)
        local.unlink(missing_ok=True)


def pull_frames(files: JobFiles, paths: SessionPaths, names: list[str]) -> None:
    """Worker: the frames it does not hold yet. A missing object is FileNotFoundError."""
    for name in names:
        local = paths.frames_dir / name
        if local.is_file() or not files.shared:
            continue
        if not files.store.get_file(files.key(local), local):
            raise FileNotFoundError(f"the session's frame {name} is not in the store")


def write_capture(paths: SessionPaths, frames: list[dict], fps: float | None, intrinsics: dict | None) -> Path:
    """The session's frames as a lightfield-capture directory (core.capture.load reads it as any
    capture): capture.json naming the frame files, their poses and exposures, and one depth
    array [T, H, W] when the session has depth. Returns the directory."""
    out = paths.capture_dir
    remove_tree(out)
    out.mkdir(parents=True)
    names = []
    for i, frame in enumerate(frames):
        link = out / f"{i:06d}{Path(frame['image']).suffix}"
        os.link(paths.frames_dir / frame["image"], link)  # same file system: no copy
        names.append(link.name)
    index: dict = {"format": "lightfield-capture", "frames": names, "fps": fps or 1.0}
    if intrinsics:
        index["intrinsics"] = intrinsics
    if all(f.get("pose") for f in frames):
        index["poses"] = [f["pose"] for f in frames]
    if any(f.get("ev") is not None for f in frames):
        index["frame_ev"] = [float(f.get("ev") or 0.0) for f in frames]
    if all(f.get("depth") for f in frames):
        depth = np.stack([np.load(paths.frames_dir / f["depth"], allow_pickle=False) for f in frames])
        np.save(out / "depth.npy", depth.astype(np.float32), allow_pickle=False)
        index["depth"] = "depth.npy"
    (out / "capture.json").write_text(json.dumps(index))
    return out


def push_version(files: JobFiles, paths: SessionPaths, version: int) -> None:
    """Worker: a finished version to the store, lightfield.json last (readers look for it first)."""
    files.push_dir(paths.version_dir(version), last="lightfield.json")


def fetch_version(files: JobFiles, paths: SessionPaths, version: int) -> bool:
    """A version's artefact in this host's directory (fetched when the store is shared); False
    when the store has none."""
    directory = paths.version_dir(version)
    if (directory / "lightfield.json").is_file():
        return True
    return files.pull_dir(directory, first="lightfield.json")
