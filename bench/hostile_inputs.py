"""Hostile and damaged inputs of issue 45, generated in code (a few KB to a few MB each):
files that declare far more than they hold, or values a capture may not state. Used by the
tests (tests/test_io_bounds.py, tests/test_service_hostile2.py) and by bench/hostile_uploads.py."""
from __future__ import annotations

import io
import json
import struct
import zipfile
import zlib
from fractions import Fraction
from pathlib import Path

import numpy as np


def room_frames(t: int = 1, h: int = 48, w: int = 64) -> np.ndarray:
    """Float frames [T, H, W, 3]: a lit wall gradient with a bright window."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    base = 0.25 + 0.35 * (yy / h)[..., None] * np.array([1.0, 0.9, 0.8], np.float32)
    frames = []
    for k in range(t):
        img = np.broadcast_to(base, (h, w, 3)).copy()
        img[(np.abs(xx - w * 0.7) < w * 0.1) & (yy < h * 0.35)] = 1.0 - 0.3 * k / max(t - 1, 1)
        frames.append(img)
    return np.stack(frames)


def tiny_mp4(path: Path, frames: int = 6) -> Path:
    from core.io.video import write_video

    return write_video(path, room_frames(frames), fps=6.0)


def mp4_declaring(path: Path, samples: int) -> Path:
    """A real 6-frame MP4 whose `stts` box says its one entry holds `samples` samples."""
    data = bytearray(tiny_mp4(path).read_bytes())
    at = data.find(b"stts")
    assert at > 0 and struct.unpack_from(">I", data, at + 8)[0] == 1  # one entry: count, delta
    struct.pack_into(">I", data, at + 12, samples)
    path.write_bytes(bytes(data))
    return path


def vfr_mkv(path: Path, times_s: list[float], size=(64, 48)) -> Path:
    """A Matroska clip whose frames are stamped at `times_s` (a variable frame rate)."""
    import av

    w, h = size
    with av.open(str(path), "w", format="matroska") as c:
        stream = c.add_stream("mpeg4", rate=10)
        stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
        stream.time_base = Fraction(1, 1000)
        for i, t in enumerate(times_s):
            frame = av.VideoFrame.from_ndarray(np.full((h, w, 3), 20 * i % 255, np.uint8), format="rgb24")
            frame.pts, frame.time_base = int(round(t * 1000)), Fraction(1, 1000)
            for packet in stream.encode(frame):
                c.mux(packet)
        for packet in stream.encode():
            c.mux(packet)
    return path


def png_bytes(w: int = 64, h: int = 48) -> bytes:
    from core.io.images import encode_png

    return encode_png(room_frames(1, h, w)[0])


def jpeg_bytes(w: int = 64, h: int = 48) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray((room_frames(1, h, w)[0] * 255).astype(np.uint8)).save(buf, "JPEG", quality=90)
    return buf.getvalue()


def truncated_jpeg(w: int = 64, h: int = 48) -> bytes:
    data = jpeg_bytes(w, h)
    return data[: len(data) * 2 // 3]


def png_bomb(width: int = 50_000, height: int = 50_000) -> bytes:
    """A tiny PNG whose header declares width x height pixels."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(bytes(4096))) + chunk(b"IEND", b"")
    )


EYE = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]


def capture_index(frames: int = 2, **camera) -> dict:
    meta = {"camera_model": "PINHOLE", "fl_x": 50.0, "fl_y": 50.0, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48,
            "frames": [{"file_path": f"images/{i}.png", "transform_matrix": EYE} for i in range(frames)]}
    meta.update(camera)
    return meta


def capture_zip(index, images: dict[str, bytes] | None = None, extra: dict[str, bytes] | None = None) -> bytes:
    """A capture-app zip: transforms.json (a dict, or raw bytes) + images (default: two PNGs)."""
    images = images if images is not None else {"images/0.png": png_bytes(), "images/1.png": png_bytes()}
    raw = index if isinstance(index, bytes) else json.dumps(index).encode()
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        # stored: a repetitive index compresses beyond the zip-bomb ratio, refused before its budget
        z.writestr("transforms.json", raw, compress_type=zipfile.ZIP_STORED)
        for name, data in {**images, **(extra or {})}.items():
            z.writestr(name, data)
    return buf.getvalue()


def nested_index(depth: int = 100_000) -> bytes:
    """transforms.json nesting empty lists `depth` deep (json.loads: RecursionError)."""
    return b'{"frames": ' + b"[" * depth + b"]" * depth + b"}"


def container_bomb_index(lists: int = 2_000_000) -> bytes:
    """A few MB of JSON that builds millions of Python lists."""
    return b'{"frames": [' + b",".join([b"[]"] * lists) + b"]}"


def many_frames_index(frames: int = 100_000) -> bytes:
    return json.dumps(capture_index(frames=1) | {"frames": [{"file_path": "images/0.png", "transform_matrix": EYE}]
                                                          * frames}).encode()


def zip_with_entries(entries: int) -> bytes:
    """`entries` empty members (plus transforms.json)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        z.writestr("transforms.json", json.dumps(capture_index(1)))
        z.writestr("images/0.png", png_bytes())
        for i in range(entries):
            z.writestr(f"e/{i}", b"")
    return buf.getvalue()


def zip_lying_about_entries(entries: int, declared: int = 2) -> bytes:
    """A zip whose end record declares `declared` entries while its directory holds `entries`."""
    data = bytearray(zip_with_entries(entries))
    at = data.rfind(b"PK\x05\x06")
    struct.pack_into("<HH", data, at + 8, declared, declared)
    return bytes(data)


def npz(depth: np.ndarray, compress: bool = True) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(buf, depth=depth)
    return buf.getvalue()


def fortran_npz_bomb(shape=(40, 500, 500), dtype=np.float64) -> bytes:
    """An .npz whose depth.npy header says a Fortran-ordered stack of zeros: ~1 MB that inflates
    to shape x itemsize bytes (80 MB by default), written without holding the array."""
    header = {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": True, "shape": shape}
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, header)
    total = int(np.prod(shape)) * np.dtype(dtype).itemsize
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        with z.open("depth.npy", "w", force_zip64=True) as member:
            member.write(head.getvalue())
            block = bytes(8 << 20)
            for start in range(0, total, len(block)):
                member.write(block[: min(len(block), total - start)])
    return buf.getvalue()


def fortran_depth(frames: int = 60, h: int = 400, w: int = 400, metres: float = 2.0) -> bytes:
    """A genuine (incompressible) Fortran-ordered depth stack, float32."""
    rng = np.random.default_rng(0)
    stack = np.asfortranarray(metres + rng.random((frames, h, w), np.float32))
    buf = io.BytesIO()
    np.save(buf, stack)
    return buf.getvalue()
