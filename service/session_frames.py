"""Frames sent to a live session: read (a multipart POST or a WebSocket message) and checked
one by one, so a bad frame is refused with a 4xx naming it and its problem while the session
goes on.

One batch is images with their metadata, or one short video chunk:
    multipart: `frame` parts (images, repeatable), `depth` parts (one per frame, same order),
               or one `video` part; `meta` JSON {"poses": [[16 floats], ...], "ev": [...]}
    WebSocket: {"type": "frames", "frames": [{"image": b64, "pose": [16], "ev": e, "depth": b64}]}
               or {"type": "frames", "video": b64, "poses": [...], "ev": [...]}

Every frame of a session has the first frame's size; every frame has a pose or none does,
and depth or none does (the first frame decides), because the worker reads the session as one
capture. Checks decode the pixels (the upload check of a job reads headers only): a frame is
small, and one that cannot be decoded must be refused now, not found by the worker later.
"""
from __future__ import annotations

import base64
import binascii
import io
import json
import math
from dataclasses import dataclass, field

from python_multipart.multipart import MultipartParser, parse_options_header

from service.errors import BadRequest, InvalidInput, PayloadTooLarge, UnsupportedMedia
from service.upload import feed_multipart
from service.validation import media_error_to_api

MAX_FRAMES_PER_BATCH = 64
PARTS = ("frame", "depth", "video", "meta")


@dataclass
class FrameBatch:
    """What one request or message carried, before any check."""

    images: list[bytes] = field(default_factory=list)
    depths: list[bytes] = field(default_factory=list)
    video: bytes | None = None
    poses: list | None = None
    evs: list | None = None


@dataclass(frozen=True)
class CheckedFrame:
    image: bytes  # the file to store: as sent, or a video frame as PNG
    suffix: str
    width: int
    height: int
    depth: bytes | None  # float32 [H, W] as .npy
    pose: list[float] | None
    ev: float | None


# -- reading -------------------------------------------------------------------------------
async def read_multipart(content_type: str | None, chunks, max_bytes: int) -> FrameBatch:
    """A multipart body, in memory (bounded by `max_bytes`: a batch is a few frames)."""
    mime, options = parse_options_header(content_type or "")
    if mime != b"multipart/form-data" or not options.get(b"boundary"):
        raise UnsupportedMedia("POST /sessions/{id}/frames takes multipart/form-data (fields frame, depth, video, "
                               "meta)", code="not_multipart")
    parts: list[tuple[str, bytearray]] = []
    state = {"headers": {}, "field": bytearray(), "value": bytearray(), "size": 0, "ended": False}

    def on_header_end():
        state["headers"][bytes(state["field"]).lower()] = bytes(state["value"])
        state["field"].clear()
        state["value"].clear()

    def on_headers_finished():
        _, opts = parse_options_header(state["headers"].get(b"content-disposition", b""))
        name = opts.get(b"name", b"").decode("utf-8", "replace")
        if name not in PARTS:
            raise InvalidInput(f"unknown form field {name!r}; expected one of {', '.join(PARTS)}", code="unknown_field")
        parts.append((name, bytearray()))
        state["headers"] = {}

    def on_part_data(data, start, end):
        state["size"] += end - start
        if state["size"] > max_bytes:
            raise PayloadTooLarge(f"a frames request may carry at most {max_bytes} bytes", code="too_large")
        parts[-1][1].extend(data[start:end])

    parser = MultipartParser(options[b"boundary"], callbacks={
        "on_header_field": lambda d, s, e: state["field"].extend(d[s:e]),
        "on_header_value": lambda d, s, e: state["value"].extend(d[s:e]),
        "on_header_end": on_header_end, "on_headers_finished": on_headers_finished,
        "on_part_data": on_part_data, "on_end": lambda: state.update(ended=True)})
    await feed_multipart(parser, chunks)
    if not state["ended"]:
        raise BadRequest("multipart body ended before its closing boundary", code="truncated_body")
    batch = FrameBatch()
    for name, data in parts:
        if name == "frame":
            batch.images.append(bytes(data))
        elif name == "depth":
            batch.depths.append(bytes(data))
        elif name == "video":
            if batch.video is not None:
                raise InvalidInput("one 'video' part per request", code="duplicate_field")
            batch.video = bytes(data)
        else:
            _apply_meta(batch, _json_object(bytes(data), "meta"))
    return batch


def batch_from_message(message: dict) -> FrameBatch:
    """A WebSocket `frames` message (base64 payloads)."""
    batch = FrameBatch()
    frames = message.get("frames")
    if message.get("video") is not None:
        batch.video = _b64(message["video"], "video")
        _apply_meta(batch, {"poses": message.get("poses"), "ev": message.get("ev")})
        return batch
    if not isinstance(frames, list):
        raise InvalidInput("a frames message has 'frames' (a list) or 'video'", code="invalid_message")
    poses, evs = [], []
    for i, f in enumerate(frames):
        if not isinstance(f, dict) or "image" not in f:
            raise InvalidInput(f"frames[{i}] must be an object with 'image' (base64)", code="invalid_message")
        batch.images.append(_b64(f["image"], f"frames[{i}].image"))
        if f.get("depth") is not None:
            batch.depths.append(_b64(f["depth"], f"frames[{i}].depth"))
        poses.append(f.get("pose"))
        evs.append(f.get("ev"))
    batch.poses = poses if any(p is not None for p in poses) else None
    batch.evs = evs if any(e is not None for e in evs) else None
    return batch


def _b64(value, what: str) -> bytes:
    if not isinstance(value, str):
        raise InvalidInput(f"{what} must be a base64 string", code="invalid_message")
    try:
        return base64.b64decode(value, validate=True)
    except (binascii.Error, ValueError):
        raise InvalidInput(f"{what} is not valid base64", code="invalid_message") from None


def _json_object(data: bytes, what: str) -> dict:
    try:
        value = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidInput(f"{what} is not JSON: {exc}", code="invalid_meta") from None
    if not isinstance(value, dict):
        raise InvalidInput(f"{what} must be a JSON object", code="invalid_meta")
    return value


def _apply_meta(batch: FrameBatch, meta: dict) -> None:
    unknown = set(meta) - {"poses", "ev"}
    if unknown:
        raise InvalidInput(f"meta: unknown key(s) {sorted(unknown)}; expected poses, ev", code="invalid_meta")
    for key, attr in (("poses", "poses"), ("ev", "evs")):
        value = meta.get(key)
        if value is not None and not isinstance(value, list):
            raise InvalidInput(f"meta.{key} must be a list, one entry per frame", code="invalid_meta")
        setattr(batch, attr, value)


# -- checking ------------------------------------------------------------------------------
def check_batch(batch: FrameBatch, size: tuple[int, int] | None, with_pose: bool | None,
                with_depth: bool | None) -> list[CheckedFrame]:
    """The batch's frames, decoded and checked against the session (its frame size, and
    whether its frames have poses and depth: None where the session has no frame yet).
    Raises a 4xx ApiError naming the first bad frame (blocking: run in a thread)."""
    from core.io.limits import MediaError, MediaLimits  # noqa: PLC0415 — core.io.limits pulls in av, cv2, OpenEXR, PIL: imported when used

    limits = MediaLimits.from_env()
    try:
        images = _video_frames(batch.video, limits) if batch.video is not None else _images(batch.images, limits)
    except MediaError as exc:
        raise media_error_to_api(exc) from None
    n = len(images)
    if n == 0:
        raise InvalidInput("the request carries no frame ('frame' parts or one 'video')", code="missing_file")
    if n > MAX_FRAMES_PER_BATCH:
        raise PayloadTooLarge(f"{n} frames in one request; at most {MAX_FRAMES_PER_BATCH}", code="too_many_frames")
    for what, values in (("poses", batch.poses), ("ev", batch.evs)):
        if values is not None and len(values) != n:
            raise InvalidInput(f"{what} has {len(values)} entries for {n} frames", code="invalid_meta")
    if batch.depths and len(batch.depths) != n:
        raise InvalidInput(f"{len(batch.depths)} depth maps for {n} frames: one per frame", code="invalid_depth")
    first_size = size or (images[0][2], images[0][3])
    pose_rule = (batch.poses is not None and batch.poses[0] is not None) if with_pose is None else with_pose
    depth_rule = bool(batch.depths) if with_depth is None else with_depth
    return [_check_frame(i, images[i], batch, first_size, pose_rule, depth_rule, limits) for i in range(n)]


def _images(blobs: list[bytes], limits) -> list[tuple[bytes, str, int, int]]:
    from core.io.images import decode_image  # noqa: PLC0415 — core.io.images pulls in PIL: imported when used
    from core.io.limits import MediaError  # noqa: PLC0415 — core.io.limits pulls in av, cv2, OpenEXR, PIL: imported when used
    from core.io.sniff import sniff_image  # noqa: PLC0415 — core.io pulls in av, cv2, OpenEXR: imported when used

    out = []
    for i, data in enumerate(blobs):
        kind = sniff_image(data[:64])
        if kind is None or kind == "gif":
            raise UnsupportedMedia(f"frame {i}: not a still image (PNG, JPEG, WebP, BMP or TIFF)", code="not_media")
        try:
            h, w = decode_image(data, limits).pixels.shape[:2]
        except MediaError as exc:
            raise media_error_to_api(MediaError(exc.code, f"frame {i}: {exc}")) from None
        out.append((data, "." + ("jpg" if kind == "jpeg" else kind), w, h))
    return out


def _video_frames(data: bytes, limits) -> list[tuple[bytes, str, int, int]]:
    """A video chunk's frames as 8-bit PNGs (what the worker's capture reads)."""
    import numpy as np  # noqa: PLC0415 — numpy is heavy: imported when used

    from core.io import read_video  # noqa: PLC0415 — core.io pulls in av, cv2, OpenEXR, PIL: imported when used
    from core.io.images import encode_png  # noqa: PLC0415 — core.io.images pulls in PIL: imported when used

    video = read_video(data, limits, on_too_many="error")
    out = []
    for frame in video.frames:
        h, w = frame.shape[:2]
        # the chunk's code values as they are, tagged sRGB: what a phone's video holds and what
        # the capture's loader assumes of an untagged file
        out.append((encode_png(np.clip(frame, 0.0, 1.0), "srgb"), ".png", w, h))
    return out


def _check_frame(i: int, image: tuple[bytes, str, int, int], batch: FrameBatch, size: tuple[int, int],
                 with_pose: bool, with_depth: bool, limits) -> CheckedFrame:
    data, suffix, w, h = image
    if (w, h) != tuple(size):
        raise InvalidInput(f"frame {i} is {w}x{h}; this session's frames are {size[0]}x{size[1]}",
                           code="frame_size_mismatch")
    pose = batch.poses[i] if batch.poses is not None else None
    if with_pose and pose is None:
        raise InvalidInput(f"frame {i} has no pose; this session's frames have poses (meta.poses)", code="invalid_pose")
    if not with_pose and pose is not None:
        raise InvalidInput(f"frame {i} has a pose; this session's first frame had none, so none may",
                           code="invalid_pose")
    if pose is not None:
        pose = _checked_pose(i, pose)
    ev = batch.evs[i] if batch.evs is not None else None
    if ev is not None and not (isinstance(ev, (int, float)) and not isinstance(ev, bool) and math.isfinite(ev)
                               and abs(ev) <= 20):
        raise InvalidInput(f"frame {i}: ev must be a finite number of stops within +-20, got {ev!r}",
                           code="invalid_ev")
    depth = None
    if with_depth != bool(batch.depths):
        raise InvalidInput(f"frame {i}: {'no' if with_depth else 'a'} depth map, but this session's frames have "
                           f"{'depth' if with_depth else 'none'}", code="invalid_depth")
    if batch.depths:
        depth = _checked_depth(i, batch.depths[i], w, h, limits)
    return CheckedFrame(data, suffix, w, h, depth, pose, None if ev is None else float(ev))


def _checked_pose(i: int, pose) -> list[float]:
    import torch  # noqa: PLC0415 — torch is heavy: imported when used

    from core.camera import CameraError, check_rigid_pose  # noqa: PLC0415 — core.camera pulls in torch: imported when used

    flat = pose if not (isinstance(pose, list) and pose and isinstance(pose[0], list)) else [v for r in pose for v in r]
    if not (isinstance(flat, list) and len(flat) == 16
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in flat)):
        raise InvalidInput(f"frame {i}: pose must be 16 numbers (a row-major 4x4 camera-to-world)", code="invalid_pose")
    try:
        check_rigid_pose(torch.tensor(flat, dtype=torch.float64).reshape(4, 4), f"frame {i} pose")
    except CameraError as exc:
        raise InvalidInput(str(exc), code="invalid_pose") from None
    return [float(v) for v in flat]


def _checked_depth(i: int, data: bytes, w: int, h: int, limits) -> bytes:
    import numpy as np  # noqa: PLC0415 — numpy is heavy: imported when used

    from core.io import read_depth  # noqa: PLC0415 — core.io pulls in av, cv2, OpenEXR, PIL: imported when used
    from core.io.limits import MediaError  # noqa: PLC0415 — core.io.limits pulls in av, cv2, OpenEXR, PIL: imported when used

    try:
        depth = np.asarray(read_depth(data, limits), dtype=np.float32)
    except MediaError as exc:
        raise media_error_to_api(MediaError(exc.code, f"frame {i} depth: {exc}")) from None
    if depth.ndim == 3 and depth.shape[0] == 1:
        depth = depth[0]
    if depth.shape != (h, w):
        raise InvalidInput(f"frame {i}: depth is {'x'.join(map(str, depth.shape))}, the frame {h}x{w} (H x W)",
                           code="invalid_depth")
    buf = io.BytesIO()
    np.save(buf, depth, allow_pickle=False)
    return buf.getvalue()
