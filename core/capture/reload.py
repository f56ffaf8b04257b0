"""The capture a job estimated from, rebuilt from its input file and the artefact's record of it
(`capture` in the artefact's meta: Capture.summary), without tracking again: what
`lightfield preview` composites into.

Loading the input again is not enough: tracking may have left frames out
(`metadata.tracking.frames_dropped`), refined the intrinsics, and given a capture without
depth a room fixed in the world (`metadata.room`). The record says all three, so the frames
the job kept are picked by the tracking's own indices, the recorded cameras and exposures are
put back, and the depth of a capture that had none is the recorded room's, as the job saw it.
The frames are decoded with the recorded transfer and, where the job estimated one, its
response (core.capture.response).
"""
from __future__ import annotations

import dataclasses

import torch

from core.capture.base import Capture, CaptureError
from core.capture.depth import ASSUMED_DEPTH_SOURCE
from core.capture.params import CaptureParams
from core.capture.response import apply_curve
from core.tracking.room import RoomFitError, box_depth, room_from_dict
from core.transfer import AUTO

DURATION_TOLERANCE_S = 1e-3


def recorded_params(record: dict) -> CaptureParams:
    """The parameters that load the input as the job loaded it, before tracking: the recorded
    intrinsics and fps, and the frame count the job subsampled to (so a clip limited by
    `max_frames` is subsampled alike). Poses and exposures are put back after the frames are
    picked, since tracking may have dropped some."""
    k = record.get("intrinsics") or {}
    meta = record.get("metadata") or {}
    tracking = meta.get("tracking") or {}
    transfer = (meta.get("transfer") or {}).get("curve", AUTO)
    loaded = len(tracking.get("frames_kept", [])) + len(tracking.get("frames_dropped", []))
    return CaptureParams(
        intrinsics={n: k[n] for n in ("fx", "fy", "cx", "cy")} if k else None,
        fps=record.get("fps"),
        max_frames=loaded or record.get("frames") or None,
        frame_ev="locked",  # the recorded exposures are put back below: nothing to estimate
        transfer=transfer,  # the curve the job decoded the frames with
    )


def reload_capture(input_path, depth_path, record: dict) -> Capture:
    """The capture of `record` (an artefact's meta["capture"]) from its input file; raises
    CaptureError naming what does not match."""
    from core.capture.load import load_capture  # noqa: PLC0415 — core.capture.load pulls in av, cv2, OpenEXR, PIL: imported when used

    raw = load_capture(input_path, depth_path, recorded_params(record))
    meta = record.get("metadata") or {}
    response = meta.get("response") or {}
    if response.get("used"):  # the response the job estimated from the frames, applied as the job did
        raw = dataclasses.replace(raw, frames=apply_curve(raw.frames, response["codes"], response["log_linear"]))
    tracking = meta.get("tracking") or {}
    kept = tracking.get("frames_kept")
    count = int(record.get("frames", raw.num_frames))
    if kept is not None and len(kept) + len(tracking.get("frames_dropped", [])) == raw.num_frames:
        keep = [int(i) for i in kept]
    elif raw.num_frames == count:
        keep = list(range(count))
    else:
        raise CaptureError(
            "input",
            f"it loads as {raw.num_frames} frames, but the artefact was estimated from {count}: "
            "is it the file the artefact was estimated from, with the same limits?",
        )
    if len(keep) != count or max(keep, default=0) >= raw.num_frames:
        raise CaptureError("input", f"the artefact records {count} frames and tracking kept {len(keep)}")
    times = raw.times[keep]
    duration = float(times[-1] - times[0]) if count > 1 else 0.0
    if abs(duration - float(record.get("duration_s", duration))) > DURATION_TOLERANCE_S:
        raise CaptureError(
            "input",
            f"its kept frames span {duration:.3f} s, the artefact's {record['duration_s']:.3f} s: "
            "not the file (or the fps) the artefact was estimated from",
        )
    try:
        poses = torch.as_tensor(record["poses"], dtype=torch.float64).reshape(count, 4, 4)
        ev = (
            None
            if record.get("frame_ev") is None
            else torch.tensor(record["frame_ev"], dtype=torch.float32).reshape(count)
        )
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise CaptureError(
            "artefact", f"its recorded poses or exposures do not describe {count} frames: {exc}"
        ) from None
    capture = dataclasses.replace(
        raw, frames=raw.frames[keep].contiguous(), depth=raw.depth[keep].contiguous(), poses=poses, times=times,
        stated_ev=ev, metadata=dict(meta))
    room = meta.get("room")
    if room is not None and raw.depth_source == ASSUMED_DEPTH_SOURCE:  # the job's depth was the room's
        try:
            box = room_from_dict(room)
        except RoomFitError as exc:
            raise CaptureError("artefact", f"its recorded room: {exc}") from None
        depth = box_depth(box, [capture.camera(i) for i in range(count)])
        capture = dataclasses.replace(
            capture, depth=depth.float().contiguous(), depth_source=record.get("depth_source", "")
        )
    return capture
