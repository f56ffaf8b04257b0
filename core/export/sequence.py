"""EXR sequences of env maps over a time range at one probe, streamed as a zip (VFX shots).

Files `envmap.<frame:04d>.exr` (frame numbers from `first_frame`, the usual `name.####.exr`
pattern Nuke / Houdini / Blender read as a sequence), each with `core.export.metadata`
attributes (probe position, time, units, colour space, artefact id, and the standard
`timeCode` / `framesPerSecond` of evenly spaced frames), plus `sequence.json` listing
frame -> t. `colour="acescg"` writes ACEScg pixels (AP1 chromaticities). Members are regular
files with mode 0644 (what unzip restores), not Python's default of no permissions. The zip is produced incrementally:
`zip_stream` yields its bytes as each
member is written, so a caller can send frames while later ones are still being evaluated.
"""
from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Iterable, Iterator

import numpy as np


class _Sink(io.RawIOBase):
    """A write-only, non-seekable stream that hands out what was written since the last take()."""

    def __init__(self):
        self._chunks: list[bytes] = []
        self._pos = 0

    def writable(self) -> bool:
        return True

    def write(self, b) -> int:
        data = bytes(b)
        self._chunks.append(data)
        self._pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self._pos

    def take(self) -> bytes:
        out, self._chunks = b"".join(self._chunks), []
        return out


def zip_member(name: str) -> zipfile.ZipInfo:
    """A stored zip entry for a regular file with mode 0644 (Unix), fixed date."""
    info = zipfile.ZipInfo(name, date_time=(2020, 1, 1, 0, 0, 0))
    info.create_system = 3  # Unix: the mode bits below are honoured by unzip / Python's extract
    info.external_attr = (0o100644 & 0xFFFF) << 16
    return info


def zip_stream(members: Iterable[tuple[str, bytes]]) -> Iterator[bytes]:
    """Stream a zip (stored, no compression: EXR is already compressed) of (name, bytes) members."""
    sink = _Sink()
    with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_STORED) as z:
        for name, data in members:
            z.writestr(zip_member(name), data)
            chunk = sink.take()
            if chunk:
                yield chunk
    tail = sink.take()
    if tail:
        yield tail


def sequence_times(t0: float, t1: float, frames: int) -> list[float]:
    """`frames` evenly spaced times from t0 to t1 inclusive (one frame: t0)."""
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    return [float(t0)] if frames == 1 else [float(v) for v in np.linspace(t0, t1, frames)]


def sequence_fps(times: list[float]) -> float | None:
    """Frames per second of evenly spaced times (None for one frame or a zero range)."""
    if len(times) < 2 or times[-1] <= times[0]:
        return None
    return (len(times) - 1) / (times[-1] - times[0])


def sequence_members(maps: Iterable[tuple[float, np.ndarray]], x, artefact: str | None = None,
                     first_frame: int = 1, extra: dict | None = None, fps: float | None = None,
                     colour: str = "rec709") -> Iterator[tuple[str, bytes]]:
    """(name, EXR bytes) per (t, env map), then `sequence.json`. `fps` (see `sequence_fps`) gives
    each frame its `framesPerSecond` and `timeCode`."""
    from core.export.metadata import envmap_attributes, in_colour, sequence_attributes  # noqa: PLC0415 — core.export.metadata pulls in torch: imported when used
    from core.io.exr import encode_exr  # noqa: PLC0415 — core.io.exr pulls in av, cv2, OpenEXR, PIL, torch: imported when used

    index = []
    for i, (t, env) in enumerate(maps):
        frame = first_frame + i
        name = f"envmap.{frame:04d}.exr"
        attrs = {**envmap_attributes(x, t, artefact, colour=colour, frame=float(frame)), **sequence_attributes(t, fps)}
        index.append({"frame": frame, "t": float(t), "file": name})
        yield name, encode_exr(in_colour(env, colour), attributes=attrs)
    doc = {"x": [float(v) for v in x], "artefact": artefact, "frames": index, "fps": fps, "colour": colour,
           **(extra or {})}
    yield "sequence.json", json.dumps(doc, indent=1).encode()
