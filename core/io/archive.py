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

import io
import os
import posixpath
import stat
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path

from core.io.limits import DEFAULT_LIMITS, MediaError, MediaLimits, Source
from core.io.sniff import ZIP_MAGIC

MAX_MEMBERS = 20_000
MAX_RATIO = 200.0
_RATIO_MIN_BYTES = 1 << 20  # tiny members compress absurdly well and harmlessly
# zipfile reads the whole central directory into ZipInfo objects (~500 bytes each) before any
# check can run: its entry count and size are read from the end record and walked here first
MAX_DIRECTORY_BYTES_PER_MEMBER = 1024
_EOCD = struct.Struct("<4s4H2LH")  # signature, disk, cd disk, entries here, entries, cd size, cd offset, comment
_EOCD64_LOCATOR = struct.Struct("<4sLQL")
_EOCD64 = struct.Struct("<4sQ2H2L4Q")
_CD_ENTRY = struct.Struct("<4s6H3L5H2L")  # central directory file header (46 bytes)


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


def check_zip_directory(f, size: int, max_members: int = MAX_MEMBERS, what: str = "capture archive") -> int:
    """Entries in the zip open as the binary file `f` (`size` bytes), refusing more than
    `max_members` (or a central directory larger than `max_members` entries could need) from the
    end record and a walk over the directory's fixed-size headers, before zipfile builds an
    object per entry. A directory that disagrees with its end record is refused (zipfile
    trusts the byte size, not the count). Returns the entry count."""
    tail_len = min(size, _EOCD.size + 0xFFFF)
    f.seek(size - tail_len)
    tail = f.read(tail_len)
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or at + _EOCD.size > len(tail):
        raise ArchiveError("truncated", f"{what} is not a readable zip (no end of central directory record)")
    _, _, _, _, entries, cd_size, _, _ = _EOCD.unpack_from(tail, at)
    end = size - tail_len + at  # where the directory must end
    if entries == 0xFFFF or cd_size == 0xFFFFFFFF:  # ZIP64: the real values are in the ZIP64 end record
        loc = at - _EOCD64_LOCATOR.size
        if loc < 0 or tail[loc:loc + 4] != b"PK\x06\x07":
            raise ArchiveError("truncated", f"{what}: ZIP64 end record locator is missing")
        end = size - tail_len + loc - _EOCD64.size
        if end < 0:
            raise ArchiveError("truncated", f"{what}: ZIP64 end record is missing")
        f.seek(end)
        record = f.read(_EOCD64.size)
        if len(record) != _EOCD64.size or record[:4] != b"PK\x06\x06":
            raise ArchiveError("truncated", f"{what}: ZIP64 end record is missing")
        entries, cd_size = _EOCD64.unpack(record)[7], _EOCD64.unpack(record)[8]
    if entries > max_members:
        raise ArchiveError("too_large", f"{what} has {entries} entries, more than the limit of {max_members}")
    if cd_size > max(max_members, 1) * MAX_DIRECTORY_BYTES_PER_MEMBER:
        raise ArchiveError("too_large", f"{what}'s central directory is {cd_size} bytes, more than the limit of "
                                        f"{max_members * MAX_DIRECTORY_BYTES_PER_MEMBER} ({max_members} entries)")
    start = end - cd_size
    if start < 0:
        raise ArchiveError("truncated", f"{what}: central directory lies outside the file")
    f.seek(start)
    directory = f.read(cd_size)
    count, pos = 0, 0
    while pos < len(directory):
        if directory[pos:pos + 4] != b"PK\x01\x02" or pos + _CD_ENTRY.size > len(directory):
            raise ArchiveError("truncated", f"{what}: central directory is corrupt at entry {count}")
        fields = _CD_ENTRY.unpack_from(directory, pos)
        pos += _CD_ENTRY.size + fields[10] + fields[11] + fields[12]  # name, extra, comment lengths
        count += 1
        if count > max_members:
            raise ArchiveError(
                "too_large", f"{what} has more than {max_members} entries (its end record says {entries})"
            )
    return count


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

    def size(self, name: str, field: str = "file_path") -> int:
        """Bytes of a member as declared (zip) or stored (directory), without reading it."""
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
        if isinstance(source, (bytes, bytearray, memoryview)):
            limits.check_bytes(len(source), "capture archive")
            target = io.BytesIO(bytes(source))
            check_zip_directory(target, len(source), max_members)
        else:
            path = Path(source)
            limits.check_bytes(path.stat().st_size, "capture archive")
            target = str(path)
            with open(path, "rb") as f:
                check_zip_directory(f, path.stat().st_size, max_members)
        try:
            self.zip = zipfile.ZipFile(target)
        except (zipfile.BadZipFile, OSError, ValueError) as exc:
            raise ArchiveError("truncated", f"capture archive is not a readable zip ({exc})") from None
        self.members: dict[str, zipfile.ZipInfo] = {}
        self._check(max_members, max_total_bytes if max_total_bytes is not None else 4 * limits.max_bytes, max_ratio)

    def _check(self, max_members: int, max_total: int, max_ratio: float) -> None:
        infos = self.zip.infolist()
        if len(infos) > max_members:
            raise ArchiveError(
                "too_large", f"capture archive has {len(infos)} entries, more than the limit of {max_members}"
            )
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
                raise ArchiveError(
                    "too_large",
                    f"archive member {info.filename!r} expands {info.file_size / max(info.compress_size, 1):.0f}x "
                    f"(more than {max_ratio:g}x: a zip bomb?)",
                )
            total += info.file_size
            if name in self.members:
                raise ArchiveError("not_media", f"archive lists {name!r} twice")
            self.members[name] = info
        if total > max_total:
            raise ArchiveError(
                "too_large", f"capture archive expands to {total} bytes, more than the limit of {max_total}"
            )

    def exists(self, name: str) -> bool:
        try:
            return self._full(name, "file_path") in self.members
        except ArchiveError:
            return False

    def size(self, name: str, field: str = "file_path") -> int:
        info = self.members.get(self._full(name, field))
        if info is None:
            raise ArchiveError("not_found", f"{field}: {name!r} is not in the archive", field)
        return info.file_size

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

    def size(self, name: str, field: str = "file_path") -> int:
        p = self._path(name, field)
        if not p.is_file():
            raise ArchiveError("not_found", f"{field}: {name!r} does not exist in the capture", field)
        return p.stat().st_size

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
