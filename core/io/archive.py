"""Read files of an uploaded capture (a zip or a directory) by relative name, safely.

Names inside a capture come from a user's JSON, so every lookup goes through `member_name`:
POSIX relative paths only (no absolute paths, drive letters, backslashes, NUL, or `..`
anywhere), normalised (`./a//b` -> `a/b`). A zip is checked once when opened, from its
central directory: at most `max_members` entries, no symlinks, no encrypted entries, every
member's declared size within `limits.max_bytes`, the declared total within
`max_total_bytes`, and no member compressed more than `max_ratio` : 1 (zip bombs).
Reading a member stops at its declared size + 1 byte, so a lying header is caught too.
A directory is read only below its root: a name that resolves (through symlinks) outside
it is refused.
"""
from __future__ import annotations

import os
import posixpath
import stat
import zipfile
from dataclasses import dataclass
from pathlib import Path

from core.io.limits import DEFAULT_LIMITS, MediaError, MediaLimits, Source
from core.io.sniff import ZIP_MAGIC

MAX_MEMBERS = 20_000
MAX_RATIO = 200.0
_RATIO_MIN_BYTES = 1 << 20  # tiny members compress absurdly well and harmlessly


class ArchiveError(MediaError):
    """An unsafe or malformed capture archive; `.field` names what is wrong."""

    def __init__(self, code: str, message: str, field: str = "file"):
        super().__init__(code, message)
        self.field = field


def member_name(name: str, field: str = "file_path") -> str:
    """A safe, normalised relative name, or ArchiveError naming `field`."""
    if not isinstance(name, str) or not name or "\x00" in name or "\\" in name:
        raise ArchiveError("not_found", f"{field}: {name!r} is not a relative path with '/' separators", field)
    if name.startswith("/") or (len(name) > 1 and name[1] == ":"):
        raise ArchiveError("not_found", f"{field}: {name!r} is absolute; paths must be relative to the capture", field)
    parts = [p for p in name.split("/") if p not in ("", ".")]
    if not parts or ".." in parts:
        raise ArchiveError("not_found", f"{field}: {name!r} leaves the capture ('..' is not allowed)", field)
    return "/".join(parts)


def is_zip(source: Source) -> bool:
    if isinstance(source, (bytes, bytearray, memoryview)):
        return bytes(source[:4]) == ZIP_MAGIC
    p = Path(source)
    if not p.is_file():
        return False
    with p.open("rb") as f:
        return f.read(4) == ZIP_MAGIC


@dataclass
class CaptureFiles:
    """Files of a capture by relative name. `prefix` is the folder holding the index file
    (zips often wrap everything in one top-level folder)."""

    limits: MediaLimits
    prefix: str = ""

    def read(self, name: str, field: str = "file_path") -> bytes:
        raise NotImplementedError

    def exists(self, name: str) -> bool:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _full(self, name: str, field: str) -> str:
        base = member_name(name, field)
        return posixpath.join(self.prefix, base) if self.prefix else base


class ZipFiles(CaptureFiles):
    def __init__(self, source: Source, limits: MediaLimits = DEFAULT_LIMITS, max_members: int = MAX_MEMBERS,
                 max_total_bytes: int | None = None, max_ratio: float = MAX_RATIO):
        super().__init__(limits)
        import io

        if isinstance(source, (bytes, bytearray, memoryview)):
            limits.check_bytes(len(source), "capture archive")
            target = io.BytesIO(bytes(source))
        else:
            path = Path(source)
            limits.check_bytes(path.stat().st_size, "capture archive")
            target = str(path)
        try:
            self.zip = zipfile.ZipFile(target)
        except (zipfile.BadZipFile, OSError, ValueError) as exc:
            raise ArchiveError("truncated", f"capture archive is not a readable zip ({exc})") from None
        self.members: dict[str, zipfile.ZipInfo] = {}
        self._check(max_members, max_total_bytes if max_total_bytes is not None else 4 * limits.max_bytes, max_ratio)

    def _check(self, max_members: int, max_total: int, max_ratio: float) -> None:
        infos = self.zip.infolist()
        if len(infos) > max_members:
            raise ArchiveError("too_large", f"capture archive has {len(infos)} entries, more than the limit of {max_members}")
        total = 0
        for info in infos:
            if info.is_dir():
                continue
            name = member_name(info.filename, f"archive member {info.filename!r}")
            mode = info.external_attr >> 16
            if stat.S_ISLNK(mode):
                raise ArchiveError("not_media", f"archive member {info.filename!r} is a symbolic link (not allowed)")
            if info.flag_bits & 0x1:
                raise ArchiveError("unsupported_codec", f"archive member {info.filename!r} is encrypted")
            if info.file_size > self.limits.max_bytes:
                raise ArchiveError("too_large", f"archive member {info.filename!r} is {info.file_size} bytes, "
                                                f"more than the limit of {self.limits.max_bytes}")
            if info.file_size > _RATIO_MIN_BYTES and info.file_size > max_ratio * max(info.compress_size, 1):
                raise ArchiveError("too_large", f"archive member {info.filename!r} expands {info.file_size / max(info.compress_size, 1):.0f}x "
                                                f"(more than {max_ratio:g}x: a zip bomb?)")
            total += info.file_size
            if name in self.members:
                raise ArchiveError("not_media", f"archive lists {name!r} twice")
            self.members[name] = info
        if total > max_total:
            raise ArchiveError("too_large", f"capture archive expands to {total} bytes, more than the limit of {max_total}")

    def exists(self, name: str) -> bool:
        try:
            return self._full(name, "file_path") in self.members
        except ArchiveError:
            return False

    def read(self, name: str, field: str = "file_path") -> bytes:
        full = self._full(name, field)
        info = self.members.get(full)
        if info is None:
            raise ArchiveError("not_found", f"{field}: {name!r} is not in the archive", field)
        self.limits.check_bytes(info.file_size, f"{field} {name!r}")
        try:
            with self.zip.open(info) as f:
                data = f.read(info.file_size + 1)
        except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
            raise ArchiveError("truncated", f"{field}: {name!r} cannot be extracted ({exc})", field) from None
        if len(data) != info.file_size:
            raise ArchiveError("truncated", f"{field}: {name!r} does not match its declared size", field)
        return data

    def find(self, basename: str) -> list[str]:
        return sorted(n for n in self.members if posixpath.basename(n) == basename)

    def close(self) -> None:
        self.zip.close()


class DirectoryFiles(CaptureFiles):
    def __init__(self, root: str | os.PathLike, limits: MediaLimits = DEFAULT_LIMITS):
        super().__init__(limits)
        self.root = Path(root).resolve()

    def _path(self, name: str, field: str) -> Path:
        p = (self.root / self._full(name, field)).resolve()
        if not p.is_relative_to(self.root):
            raise ArchiveError("not_found", f"{field}: {name!r} resolves outside the capture directory", field)
        return p

    def exists(self, name: str) -> bool:
        try:
            return self._path(name, "file_path").is_file()
        except ArchiveError:
            return False

    def read(self, name: str, field: str = "file_path") -> bytes:
        p = self._path(name, field)
        if not p.is_file():
            raise ArchiveError("not_found", f"{field}: {name!r} does not exist in the capture", field)
        self.limits.check_bytes(p.stat().st_size, f"{field} {name!r}")
        return p.read_bytes()


def open_capture_files(source: Source, limits: MediaLimits = DEFAULT_LIMITS) -> CaptureFiles:
    """A zip (path or bytes) or a directory."""
    if not isinstance(source, (bytes, bytearray, memoryview)) and Path(source).is_dir():
        return DirectoryFiles(source, limits)
    if is_zip(source):
        return ZipFiles(source, limits)
    raise ArchiveError("not_media", "a capture must be a directory or a zip archive")
