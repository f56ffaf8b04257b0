"""KTX 2.0 cube maps with mip levels: uncompressed RGBA half (VK_FORMAT_R16G16B16A16_SFLOAT) or,
when a value exceeds the half range (65504; HDR lamps can), RGBA float (R32G32B32A32_SFLOAT).

The container the Khronos tools, three.js' KTX2Loader (via ktx-parse), Babylon.js, Filament and
Vulkan engines load directly (KTX 2.0 specification, sections 3-4; data format descriptor per
the Khronos Data Format Specification 1.3, section 5). Layout written here:

    identifier, header (vkFormat 97, typeSize 2, size x size, faceCount 6, levelCount N),
    index (DFD, key/value data), level index (level 0 = largest),
    DFD (one basic block, RGBSDA model, BT.709 primaries, LINEAR transfer, 4 float samples),
    key/value data (KTXwriter), level data from the smallest level up,
    each level's faces in the order +X, -X, +Y, -Y, +Z, -Z, rows top (t = 0) first.

Alpha is 1. `precision="auto"` writes half floats unless a value exceeds the half range, so
nothing is clamped; "half" forces half floats (values beyond +-65504 clamped), "float" float32.

Written by hand because no library does the job here: KTX-Software's own binding (`pyktx` on
PyPI) ships as a source package only and needs libktx built and installed (`pip install
pyktx==4.4.2` fails to build on this machine); the other PyPI packages parse KTX2 or convert
8-bit images through Basis Universal, neither writes float cube mip chains. The files are
checked by the readers users run: three's ktx-parse in Node and three's KTX2Loader in
Chromium (tests/test_export_node.py, tests/test_integrations_browser.py).
"""
from __future__ import annotations

import struct

import numpy as np

IDENTIFIER = b"\xabKTX 20\xbb\r\n\x1a\n"
VK_FORMAT_R16G16B16A16_SFLOAT = 97
VK_FORMAT_R32G32B32A32_SFLOAT = 109
_FORMATS = {VK_FORMAT_R16G16B16A16_SFLOAT: "<f2", VK_FORMAT_R32G32B32A32_SFLOAT: "<f4"}
HALF_MAX = 65504.0
_SAMPLE_FLOAT_SIGNED = 0xC0  # KHR_DF_SAMPLE_DATATYPE_FLOAT | KHR_DF_SAMPLE_DATATYPE_SIGNED
_CHANNELS = (0, 1, 2, 15)  # KHR_DF_CHANNEL_RGBSDA_R, G, B, ALPHA


class KTX2Error(ValueError):
    """Malformed input for the writer, or a file the reader does not handle."""


def _dfd(bits: int) -> bytes:
    samples = b"".join(
        struct.pack("<HBB4BII", bits * i, bits - 1, _SAMPLE_FLOAT_SIGNED | ch, 0, 0, 0, 0, 0xBF800000, 0x3F800000)
        for i, ch in enumerate(_CHANNELS)
    )
    block_size = 24 + len(samples)
    block = struct.pack("<IHH", 0, 2, block_size)  # vendor 0 / type 0, version 2, size
    block += struct.pack("<BBBB", 1, 1, 1, 0)  # RGBSDA, BT709, LINEAR, straight alpha
    block += bytes(4)  # texel block dimensions 1x1x1x1 (stored minus one)
    block += bytes([bits // 2, 0, 0, 0, 0, 0, 0, 0])  # bytes per plane (4 channels x bits / 8)
    block += samples
    return struct.pack("<I", 4 + len(block)) + block


def _kvd(entries: dict[str, str]) -> bytes:
    out = b""
    for key in sorted(entries):  # the spec requires keys sorted by their UTF-8 bytes
        kv = key.encode() + b"\0" + entries[key].encode() + b"\0"
        out += struct.pack("<I", len(kv)) + kv + bytes(-len(kv) % 4)
    return out


def encode_ktx2_cubemap(levels: list[np.ndarray], writer: str = "lightfield", precision: str = "auto") -> bytes:
    """KTX2 bytes for a cube mip chain: `levels[i]` float [6, S >> i, S >> i, 3 or 4]."""
    if not levels:
        raise KTX2Error("a KTX2 cube map needs at least one level")
    if precision not in ("auto", "half", "float"):
        raise KTX2Error(f"precision must be 'auto', 'half' or 'float', got {precision!r}")
    peak = max(float(np.max(np.abs(np.asarray(lv, np.float32)))) if np.size(lv) else 0.0 for lv in levels)
    use_float = precision == "float" or (precision == "auto" and peak > HALF_MAX)
    vk = VK_FORMAT_R32G32B32A32_SFLOAT if use_float else VK_FORMAT_R16G16B16A16_SFLOAT
    bits = 32 if use_float else 16
    size = int(np.shape(levels[0])[1])
    data = []
    for i, level in enumerate(levels):
        a = np.asarray(level, dtype=np.float32)
        expect = max(size >> i, 1)
        if a.ndim != 4 or a.shape[0] != 6 or a.shape[1] != expect or a.shape[2] != expect or a.shape[3] not in (3, 4):
            raise KTX2Error(f"level {i} must have shape [6, {expect}, {expect}, 3|4], got {a.shape}")
        if not np.isfinite(a).all():
            raise KTX2Error(f"level {i} has NaN/inf values")
        if a.shape[3] == 3:
            a = np.concatenate((a, np.ones(a.shape[:3] + (1,), np.float32)), axis=-1)
        data.append((a if use_float else np.clip(a, -HALF_MAX, HALF_MAX)).astype(_FORMATS[vk]).tobytes())
    dfd = _dfd(bits)
    kvd = _kvd({"KTXwriter": writer})
    header_len = 12 + 9 * 4 + 4 * 4 + 2 * 8 + len(levels) * 24
    dfd_offset = header_len
    kvd_offset = dfd_offset + len(dfd)
    offset = kvd_offset + len(kvd)
    align = bits // 2  # lcm(texel block size, 4)
    offset += -offset % align
    placed = {}
    for i in reversed(range(len(levels))):  # smallest level first in the file
        placed[i] = offset
        offset += len(data[i])
        offset += -offset % align
    out = bytearray(IDENTIFIER)
    out += struct.pack("<9I", vk, bits // 8, size, size, 0, 0, 6, len(levels), 0)
    out += struct.pack("<4I2Q", dfd_offset, len(dfd), kvd_offset, len(kvd), 0, 0)
    for i in range(len(levels)):
        out += struct.pack("<3Q", placed[i], len(data[i]), len(data[i]))
    out += dfd + kvd
    for i in reversed(range(len(levels))):
        out += bytes(placed[i] - len(out))
        out += data[i]
    return bytes(out)


def decode_ktx2_cubemap(blob: bytes) -> list[np.ndarray]:
    """Inverse of `encode_ktx2_cubemap` (RGBA half/float cube maps only): levels [6, S, S, 4] float32."""
    if not blob.startswith(IDENTIFIER) or len(blob) < 80:
        raise KTX2Error("not a KTX 2.0 file")
    vk, _, width, height, _, _, faces, count, scheme = struct.unpack_from("<9I", blob, 12)
    if vk not in _FORMATS or faces != 6 or width != height or scheme != 0:
        raise KTX2Error(f"only uncompressed RGBA16F/RGBA32F cube maps are read here (vkFormat {vk}, faces {faces})")
    dtype = np.dtype(_FORMATS[vk])
    out = []
    for i in range(max(count, 1)):
        off, length, _ = struct.unpack_from("<3Q", blob, 80 + 24 * i)
        s = max(width >> i, 1)
        if length != 6 * s * s * 4 * dtype.itemsize or off + length > len(blob):
            raise KTX2Error(f"level {i} is truncated or has the wrong size")
        out.append(np.frombuffer(blob, dtype, 6 * s * s * 4, off).astype(np.float32).reshape(6, s, s, 4))
    return out


__all__ = ["encode_ktx2_cubemap", "decode_ktx2_cubemap", "KTX2Error"]
