"""Video decoding with limits (PyAV), and mp4 writing.

Limits are applied from the stream header before decoding: the frame size against
`max_pixels`, and the frame budget `min(max_frames, max_total_pixels // (H*W))` against
the number of frames left after `frame_stride`. Too many frames are, by default,
subsampled evenly over the whole clip (first and last kept), so a long clip still covers
its full duration; `on_too_many='error'` refuses instead. Rotation metadata (phone
videos: the display matrix, or a legacy `rotate` tag) is applied, so frames come upright
as a player shows them, like images (core.io.metadata); `rotation_ccw_deg` says by how much.
Containers are recognised by magic bytes (MP4/MOV, WebM/Matroska, AVI, MPEG-PS, Ogg, and animated GIF).

Colour: frames are the file's CODE values, still in its transfer (`VideoFrames.stated_transfer`
says which, core.io.colour; converting them to light is core.transfer's). 8-bit streams are
converted to RGB by swscale (rgb24 / 255). Deeper ones (10/12-bit HDR from phones) never pass
through 8 bits: planar Y'CbCr is converted here by H.273's equations (the stream's matrix,
BT.2020 non-constant luminance, BT.709 or BT.601, and its range; core.io.colour), other deep
formats by swscale at 16 bits (rgb48le). `write_video` can state a transfer and write 10/12 bits.
"""
from __future__ import annotations

import functools
import io
import os
import re
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Literal

import av
import numpy as np

from core.io.colour import (
    PRIMARIES_CODES,
    StatedTransfer,
    colour_tag,
    h273_transfer_code,
    rgb_to_yuv420_planes,
    video_stated_transfer,
    yuv_planes_to_rgb,
)
from core.io.limits import DEFAULT_LIMITS, MediaError, MediaLimits, Source, existing_file
from core.io.metadata import rotate_frames, video_rotation_ccw
from core.io.sniff import sniff_image, sniff_media, sniff_video
from core.transfer import Transfer, parse_transfer

OnTooMany = Literal["subsample", "error"]
_SNIFF_BYTES = 64


@dataclass
class VideoFrames:
    """Decoded frames. `fps` is the SOURCE frame rate; frame k was source frame
    `source_frame_indices[k]`. Its time `times[k]` (seconds from the first frame) is its
    presentation timestamp when the stream has them (a variable-frame-rate clip keeps its
    real timing), else index / fps."""

    frames: np.ndarray  # float32 [T, H, W, 3] in [0, 1]
    fps: float
    source_frame_indices: np.ndarray  # int64 [T], increasing
    original_frame_count: int  # frames in the source (declared, or counted when undeclared)
    warnings: list[str] = field(default_factory=list)
    rotation_ccw_deg: int = 0  # display rotation applied to the stored frames
    presentation_times: np.ndarray | None = None  # float64 [T] s from the first frame's timestamp
    stated_transfer: StatedTransfer | None = None  # what the stream states (always set by read_video)

    @property
    def times(self) -> np.ndarray:
        if self.presentation_times is not None:
            return self.presentation_times
        return self.source_frame_indices.astype(np.float64) / self.fps


def select_frame_indices(
    frame_count: int, frame_pixels: int, limits: MediaLimits, on_too_many: OnTooMany = "subsample"
) -> np.ndarray:
    """Source frame indices to keep: every `frame_stride`-th frame, then an even
    subsample (or a 'too_many_frames' error) if more than the frame budget remain."""
    if on_too_many not in ("subsample", "error"):
        raise ValueError(f"on_too_many must be 'subsample' or 'error', got {on_too_many!r}")
    # Nothing is allocated from the declared count (a file may declare 2e9 frames): only the
    # kept indices, at most `budget` of them.
    stride = limits.frame_stride
    count = (max(int(frame_count), 0) + stride - 1) // stride  # candidates 0, stride, 2 stride, ...
    budget = min(limits.max_frames, limits.max_total_pixels // max(frame_pixels, 1))
    if budget < 1:
        raise MediaError(
            "too_many_pixels", f"one frame of {frame_pixels} pixels exceeds max_total_pixels={limits.max_total_pixels}"
        )
    if count <= budget:
        return np.arange(count, dtype=np.int64) * stride
    if on_too_many == "error":
        raise MediaError(
            "too_many_frames",
            f"video has {count} frames after frame_stride={stride}, more than the limit of {budget} "
            f"(max_frames={limits.max_frames}, max_total_pixels={limits.max_total_pixels})",
        )
    pick = np.round(np.linspace(0, count - 1, budget)).astype(np.int64)
    return pick * stride


def _open_container(source: Source, limits: MediaLimits):
    """-> (av container, first bytes) after the size check."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        data = bytes(source)
        limits.check_bytes(len(data), "video")
        head, target = data[:_SNIFF_BYTES], io.BytesIO(data)
    else:
        path = existing_file(source, "video")
        limits.check_bytes(path.stat().st_size, f"video {str(path)!r}")
        with path.open("rb") as f:
            head = f.read(_SNIFF_BYTES)
        target = str(path)
    if sniff_media(head) != "video" and sniff_image(head) != "gif":  # animated GIFs decode as video
        raise MediaError("not_media", "not a supported video container (unrecognised magic bytes)")
    try:
        return av.open(target, mode="r"), head
    except av.error.FFmpegError as exc:
        kind = sniff_video(head) or sniff_image(head)
        raise MediaError("truncated", f"{kind} container is truncated or corrupt ({exc.strerror})") from None


def _video_stream(container):
    if not container.streams.video:
        if container.streams.audio:
            raise MediaError("not_media", "file has audio but no video stream")
        # a video container cut inside its stream table opens with no or codec-less streams
        raise MediaError("truncated", "video container is truncated or corrupt (no video stream found)")
    stream = container.streams.video[0]
    if stream.codec_context is None:  # the container names a codec this ffmpeg does not know
        raise MediaError(
            "unsupported_codec",
            "the video stream's codec is unknown to the bundled ffmpeg; re-encode as H.264, VP9 or MPEG-4",
        )
    # Slice threading only: with frame threading, a decode error in a cut file discards the
    # frames already queued in other threads, so a truncated clip would yield none at all.
    stream.thread_type = "SLICE"
    return stream


def _source_bytes(source: Source) -> int:
    if isinstance(source, (bytes, bytearray, memoryview)):
        return len(source)
    return Path(source).stat().st_size


def _count_packets(source: Source, limits: MediaLimits) -> int:
    """Frame count of a stream that does not declare one: its non-empty packets."""
    container, _ = _open_container(source, limits)
    with container:
        stream = _video_stream(container)
        return sum(1 for packet in container.demux(stream) if packet.size > 0)


@dataclass(frozen=True)
class VideoHeader:
    """What the container declares, checked against the limits (see `probe_video`)."""

    width: int
    height: int
    fps: float  # the source frame rate (30 when the file declares none)
    frame_count: int  # declared, or counted from the packets
    selected: np.ndarray  # source frame indices read_video keeps under the limits
    warnings: list[str] = field(default_factory=list)
    stated_transfer: StatedTransfer | None = None  # what the stream states (from the first frame)


def _header(source: Source, container, stream, limits: MediaLimits, on_too_many: OnTooMany, warnings: list[str]):
    """(fps, frame count, selected indices) from the stream header, refusing what the limits forbid."""
    ctx = stream.codec_context
    if ctx.width and ctx.height:
        limits.check_pixels(ctx.width, ctx.height, "video frame")
    rate = stream.average_rate or stream.guessed_rate or stream.base_rate
    fps = float(rate) if rate else 0.0
    if not (fps > 0 and np.isfinite(fps)):
        fps = 30.0
        warnings.append("video has no frame rate; assumed 30 fps")
    declared = int(stream.frames or 0)
    if declared > _source_bytes(source):  # every frame takes bytes: a count the file cannot hold is a lie
        counted = _count_packets(source, limits)
        warnings.append(f"the container declares {declared} frames but holds {counted}; using {counted}")
        frame_count = counted
    else:
        frame_count = declared if declared > 0 else _count_packets(source, limits)
    if frame_count <= 0:
        raise MediaError("truncated", "video stream has no frames (empty, truncated or corrupt file)")
    pixels = (ctx.width * ctx.height) if ctx.width and ctx.height else 1
    return fps, frame_count, select_frame_indices(frame_count, pixels, limits, on_too_many)


def probe_video(
    source: Source, limits: MediaLimits = DEFAULT_LIMITS, on_too_many: OnTooMany = "subsample"
) -> VideoHeader:
    """What `read_video` would decode, from the container's metadata and the FIRST frame only
    (which proves the stream decodes): the same size (upright, after the display rotation),
    frame-count and pixel limits, refused with the same MediaError codes, at the cost of one
    frame however many the file declares."""
    container, _ = _open_container(source, limits)
    warnings: list[str] = []
    with container:
        stream = _video_stream(container)
        fps, frame_count, selected = _header(source, container, stream, limits, on_too_many, warnings)
        first = next(_decoded_frames(container, stream, warnings), None)
        if first is None:
            raise MediaError("truncated", f"no frame could be decoded (the stream declares {frame_count})")
        limits.check_pixels(first.width, first.height, "video frame")
        turned = video_rotation_ccw(stream, first) in (90, 270)
        w, h = (first.height, first.width) if turned else (first.width, first.height)
        stated = video_stated_transfer(stream.codec_context, first)
        return VideoHeader(w, h, fps, frame_count, selected, warnings, stated)


def read_video(
    source: Source, limits: MediaLimits = DEFAULT_LIMITS, on_too_many: OnTooMany = "subsample"
) -> VideoFrames:
    """Decode a video (path or bytes) into float32 frames under `limits` (see module doc)."""
    container, _ = _open_container(source, limits)
    warnings: list[str] = []
    with container:
        stream = _video_stream(container)
        fps, frame_count, wanted = _header(source, container, stream, limits, on_too_many, warnings)
        kept, indices, rotation, stamps, stated = _decode_selected(container, stream, wanted, limits, warnings)
    if not kept:
        raise MediaError("truncated", f"no frame could be decoded (the stream declares {frame_count})")
    if len(kept) < wanted.size:
        warnings.append(f"decoded {len(kept)} of {wanted.size} selected frames; the file ends early or is corrupt")
    frames = rotate_frames(np.stack(kept), rotation).astype(np.float32)
    frames /= np.float32(255.0 if kept[0].dtype == np.uint8 else 65535.0)
    times = presentation_times(stamps, indices, fps, warnings)
    return VideoFrames(frames, fps, np.asarray(indices, np.int64), frame_count, warnings, rotation, times, stated)


UNEVEN_INTERVALS = 0.25  # frame intervals spread more than this fraction of the median: a variable rate


def presentation_times(stamps: list[float | None], indices: list[int], fps: float,
                       warnings: list[str]) -> np.ndarray | None:
    """Seconds from the first frame of the kept frames (`indices` into `stamps`, the
    presentation time of every decoded frame in order), or None when the stream has no usable
    timestamps (then index / fps is the frame time). Uneven intervals (a variable frame rate:
    phones, screen recordings) are reported, since the frame times are then not index / fps."""
    if not stamps or any(s is None for s in stamps):
        return None
    t = np.asarray(stamps, np.float64) - float(stamps[0])
    steps = np.diff(t)
    if steps.size and (not np.isfinite(t).all() or (steps <= 0).any()):
        warnings.append("the video's presentation timestamps are not increasing; frame times taken as index / fps")
        return None
    if steps.size >= 2:
        median = float(np.median(steps))
        if float(steps.max() - steps.min()) > UNEVEN_INTERVALS * median:
            warnings.append(f"variable frame rate: frame intervals range from {steps.min():.4g} to {steps.max():.4g} s "
                            f"(nominal {1 / fps:.4g} s); frame times are the presentation timestamps")
    return t[np.asarray(indices, np.int64)]


def _decoded_frames(container, stream, warnings: list[str]):
    """Frames in presentation order. A cut or corrupt file ends the demuxing early; the
    decoder is then flushed so frames it already holds (reordering delay) are not lost."""
    try:
        for packet in container.demux(stream):
            try:
                yield from packet.decode()  # the final empty packet flushes the decoder
            except av.error.InvalidDataError as exc:
                warnings.append(f"skipped a corrupt packet ({exc.strerror})")
        return
    except av.error.DecoderNotFoundError:
        raise MediaError("unsupported_codec", f"no decoder for video codec {stream.codec_context.name!r}") from None
    except av.error.FFmpegError as exc:
        warnings.append(f"the file ends early or is corrupt ({exc.strerror})")
    try:
        yield from stream.codec_context.decode(None)
    except av.error.FFmpegError:
        pass


_PLANAR_YUV = re.compile(r"^yuva?(420|422|440|444)p(9|10|12|14|16)le$")


def _plane_array(plane) -> np.ndarray:
    return np.frombuffer(plane, np.uint16).reshape(plane.height, plane.line_size // 2)[:, : plane.width]


def deep_frame_codes(frame, codec_context=None) -> np.ndarray:
    """uint16 [H, W, 3] R'G'B' code values (0..65535 for 0..1) of a frame of more than 8 bits,
    without passing through 8 bits (module doc)."""
    fmt = frame.format
    if _PLANAR_YUV.match(fmt.name):
        y, cb, cr = (_plane_array(frame.planes[i]) for i in range(3))
        stated_range = int(frame.color_range or (codec_context.color_range if codec_context is not None else 0))
        full = stated_range == 2  # AVCOL_RANGE_JPEG; unspecified is limited, as video is
        rgb = yuv_planes_to_rgb(y, cb, cr, fmt.components[0].bits, colour_tag(frame, codec_context, "colorspace"),
                                colour_tag(frame, codec_context, "color_primaries"), full)
        return np.round(rgb * np.float32(65535.0)).astype(np.uint16)
    return frame.to_ndarray(format="rgb48le")


def _decode_selected(container, stream, wanted: np.ndarray, limits: MediaLimits, warnings: list[str]):
    """(frames at the `wanted` source indices (presentation order): uint8, or uint16 for a
    stream of more than 8 bits, their indices, the display rotation in ccw degrees, the
    presentation time in seconds (None: unknown) of every frame decoded, what the stream states
    about its colour), stopping after the last wanted frame."""
    wanted_set = set(wanted.tolist())
    last = int(wanted[-1])
    kept: list[np.ndarray] = []
    indices: list[int] = []
    stamps: list[float | None] = []
    rotation, deep = 0, False
    stated = StatedTransfer(None, "no frame decoded")
    for index, frame in enumerate(_decoded_frames(container, stream, warnings)):
        stamps.append(frame.time)
        if index == 0:  # streams that did not declare a size are checked here
            limits.check_pixels(frame.width, frame.height, "video frame")
            rotation = video_rotation_ccw(stream, frame)
            stated = video_stated_transfer(stream.codec_context, frame)
            deep = stated.bit_depth > 8
        if index in wanted_set:
            rgb = deep_frame_codes(frame, stream.codec_context) if deep else frame.to_ndarray(format="rgb24")
            if kept and rgb.shape != kept[0].shape:
                raise MediaError(
                    "shape_mismatch",
                    f"frame {index} is {rgb.shape[1]}x{rgb.shape[0]}, frame 0 was "
                    f"{kept[0].shape[1]}x{kept[0].shape[0]}",
                )
            kept.append(rgb)
            indices.append(index)
        if index >= last:
            break
    return kept, indices, rotation, stamps, stated


@functools.lru_cache(maxsize=None)
def video_codec() -> str:
    """'libx264' when PyAV's bundled ffmpeg has it (H.264 plays in browsers), else 'mpeg4'."""
    try:
        av.codec.Codec("libx264", "w")
        return "libx264"
    except Exception:
        return "mpeg4"


BIT_DEPTH_PIX_FMTS = {8: "yuv420p", 10: "yuv420p10le", 12: "yuv420p12le"}
_LIMITED_RANGE = 1  # AVCOL_RANGE_MPEG


def _prepare_frames(frames: np.ndarray, bit_depth: int) -> np.ndarray:
    """Checked [T, H, W, 3] frames, padded to even sizes: uint8 for 8 bits (float rounded to
    /255 codes, as ever), float32 in [0, 1] for more (never rounded to 8 bits)."""
    a = np.asarray(frames)
    if a.ndim != 4 or a.shape[-1] != 3 or min(a.shape[:3]) < 1:
        raise MediaError("shape_mismatch", f"frames must be [T, H, W, 3], got shape {a.shape}")
    if bit_depth == 8:
        if a.dtype != np.uint8:
            a = np.asarray(a, np.float32)
            if not np.isfinite(a).all():
                raise MediaError("non_finite", "frames contain NaN/inf values")
            a = np.round(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8)
    else:
        scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(a.dtype, 1.0)
        a = np.asarray(a, np.float32) / np.float32(scale)
        if not np.isfinite(a).all():
            raise MediaError("non_finite", "frames contain NaN/inf values")
        a = np.clip(a, 0.0, 1.0)
    pad_h, pad_w = a.shape[1] % 2, a.shape[2] % 2
    if pad_h or pad_w:
        a = np.pad(a, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
    return a


def _deep_frame(image: np.ndarray, pix_fmt: str, bits: int, matrix: int) -> av.VideoFrame:
    """A yuv420p10le/12le frame from float R'G'B' [H, W, 3] by H.273's equations (core.io.colour)."""
    frame = av.VideoFrame(image.shape[1], image.shape[0], pix_fmt)
    for plane, values in zip(frame.planes, rgb_to_yuv420_planes(image, bits, matrix, matrix)):
        padded = np.zeros((plane.height, plane.line_size // 2), np.uint16)
        padded[: values.shape[0], : values.shape[1]] = values
        plane.update(padded.tobytes())
    frame.colorspace, frame.color_range = matrix, _LIMITED_RANGE
    return frame


def _with_dts(packet, codec: str):
    if codec == "libx265" and packet.pts is not None:
        packet.dts = packet.pts  # see the libx265 options in write_video
    return packet


def write_video(path: str | os.PathLike, frames: np.ndarray, fps: float, crf: int = 18,
                display_rotation_ccw: int = 0, transfer: str | Transfer | None = None, bit_depth: int = 8,
                primaries: str | None = None, codec: str | None = None) -> Path:
    """Write frames [T, H, W, 3] (float in [0, 1], or uint8) as an mp4 (4:2:0, moov atom
    first so browsers can stream it). 4:2:0 needs even sizes: odd heights/widths are
    padded by repeating the last row/column. `display_rotation_ccw` stores a display matrix
    (as phones do for portrait clips) without touching the pixels.

    Colour: the frames are written as the code values they are; `transfer` ('srgb', 'rec709',
    'hlg', 'pq', 'linear', 'gamma:G') and `primaries` ('bt709', the default when anything is
    stated, or 'bt2020') only STATE what they are, in the stream's colour description (H.273
    transfer characteristics srgb 13, rec709 1, hlg 18, pq 16, linear 8, gamma:2.2 4,
    gamma:2.8 5; other gamma curves, the engine's gamma:2.4 included, have no code and are
    written as 2, unspecified). With transfer and primaries None and 8 bits the stream is written
    as it always was (untagged, swscale's default matrix); otherwise it is limited range with the
    matrix of its primaries (BT.709, or BT.2020 non-constant luminance), and says so.
    `bit_depth` 10 or 12 writes yuv420p10le/12le from the float frames by H.273's equations,
    never rounding to 8 bits (libx264's High 10 for 10 bits; 12 bits needs codec='libx265').
    `codec`: 'libx264' (the default when PyAV's ffmpeg has it, else 'mpeg4'), 'libx265' (mp4
    tag hvc1), or another ffmpeg encoder. libx264 is run with mbtree off, for repeatable output."""
    if bit_depth not in BIT_DEPTH_PIX_FMTS:
        raise ValueError(f"bit_depth must be one of {sorted(BIT_DEPTH_PIX_FMTS)}, got {bit_depth!r}")
    if primaries is not None and primaries not in PRIMARIES_CODES:
        raise ValueError(f"primaries must be one of {sorted(PRIMARIES_CODES)} or None, got {primaries!r}")
    stated = transfer if isinstance(transfer, Transfer) or transfer is None else parse_transfer(transfer)
    a = _prepare_frames(frames, bit_depth)
    if not (np.isfinite(fps) and fps > 0):
        raise MediaError("non_finite", f"fps must be a positive number, got {fps}")
    codec = codec or video_codec()
    pix_fmt = BIT_DEPTH_PIX_FMTS[bit_depth]
    try:
        encodable = {f.name for f in (av.codec.Codec(codec, "w").video_formats or ())}
    except Exception as exc:
        raise ValueError(f"no video encoder {codec!r} in PyAV's ffmpeg ({exc})") from None
    if encodable and pix_fmt not in encodable:
        raise ValueError(f"encoder {codec!r} cannot write {bit_depth}-bit video ({pix_fmt})")
    tagged = stated is not None or primaries is not None or bit_depth > 8
    matrix = PRIMARIES_CODES[primaries or "bt709"]  # the matrix follows the primaries: BT.709 or BT.2020 NCL
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with av.open(str(tmp), mode="w", format="mp4", options={"movflags": "faststart"}) as container:
            stream = container.add_stream(codec, rate=Fraction(fps).limit_denominator(1001))
            stream.width, stream.height, stream.pix_fmt = a.shape[2], a.shape[1], pix_fmt
            if display_rotation_ccw:
                stream.set_display_rotation(int(display_rotation_ccw))
            if tagged:
                ctx = stream.codec_context
                ctx.color_trc, ctx.color_primaries = h273_transfer_code(stated), matrix
                ctx.colorspace, ctx.color_range = matrix, _LIMITED_RANGE
            if codec == "libx264":
                # mbtree off: with it this x264 encoded the same frames differently from run to run
                # (even in one thread), and simulated captures and the benches on them must repeat
                stream.options = {"crf": str(int(crf)), "preset": "medium", "x264-params": "mbtree=0"}
            elif codec == "libx265":
                # no B-frames: the libx265 wrapper of PyAV's ffmpeg at times hands out packets with an
                # uninitialised DTS (the mp4 muxer then fails, 'pts/dts pair unsupported'); without
                # reordering DTS = PTS, which is set on every packet below
                stream.options = {"crf": str(int(crf)), "preset": "medium", "x265-params": "log-level=error:bframes=0"}
                stream.codec_context.codec_tag = "hvc1"  # what Apple's players and Safari want in mp4
            else:
                stream.bit_rate = 8_000_000
            for image in a:
                if bit_depth > 8:
                    frame = _deep_frame(image, pix_fmt, bit_depth, matrix)
                elif tagged:
                    frame = av.VideoFrame.from_ndarray(image, format="rgb24").reformat(
                        format=pix_fmt, dst_colorspace=matrix, dst_color_range=_LIMITED_RANGE)
                else:
                    frame = av.VideoFrame.from_ndarray(image, format="rgb24")
                for packet in stream.encode(frame):
                    container.mux(_with_dts(packet, codec))
            for packet in stream.encode():
                container.mux(_with_dts(packet, codec))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
