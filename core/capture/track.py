"""Camera tracking for a loaded capture that came without poses (docs/captures.md).

`track_capture(capture, params)` returns the capture with what tracking found
(core.tracking.capture_geometry.resolve_geometry): poses, the frames that could be registered,
the focal length a pan refined when the intrinsics were assumed, and, when no depth was
given, a room that stays put in the world (fitted to the sparse points, or the assumed one).
The evidence goes to `capture.metadata["tracking"]`; a failure is a warning and a labelled
static camera, never an error. Nothing is tracked for one frame, given poses, or
`params.tracking == "off"` (recorded); given poses of a moving camera without depth still get
the assumed room fixed in the world rather than one that turns with each frame.
"""
from __future__ import annotations

from dataclasses import replace

from core.capture.base import Capture
from core.capture.depth import ASSUMED_DEPTH_SOURCE
from core.capture.params import CaptureParams
from core.tracking.room import assumed_room, box_depth

_ASSUMED_DEPTH_WARNING = "no depth given: using the assumed box-room geometry"
_ASSUMED_FOV_WARNING = "no intrinsics given: assuming"


def _world_fixed_room(capture: Capture, meta: dict) -> Capture:
    """Given poses of a moving camera but no depth: the assumed room stays put in the world
    (upright, in front of the first camera) instead of turning with every frame."""
    from core.tracking.capture_geometry import ASSUMED_ROOM_SOURCE, WORLD_FIXED_ROOM_WARNING  # noqa: PLC0415 — core.tracking.capture_geometry pulls in cv2, scipy: imported when used

    box = assumed_room(first_camera=capture.poses[0])
    depth = box_depth(box, [capture.camera(i) for i in range(capture.num_frames)])
    warnings = [w for w in capture.warnings if not w.startswith(_ASSUMED_DEPTH_WARNING)] + [WORLD_FIXED_ROOM_WARNING]
    meta["room"] = {"source": "assumed", **box.as_dict()}
    return replace(capture, depth=depth.float().contiguous(), depth_source=ASSUMED_ROOM_SOURCE, warnings=warnings,
                   metadata=meta)


def track_capture(capture: Capture, params: CaptureParams | None = None) -> Capture:
    params = params or CaptureParams()
    meta = dict(capture.metadata)
    if capture.num_frames < 2:
        return capture
    if meta.get("poses_source"):
        moving = not capture.static_camera
        return _world_fixed_room(capture, meta) if moving and capture.depth_source == ASSUMED_DEPTH_SOURCE else capture
    if params.tracking == "off":
        meta["tracking"] = {"method": "off", "reason": "params.tracking = 'off': the camera is treated as static"}
        return replace(capture, metadata=meta)
    from core.tracking.capture_geometry import resolve_geometry  # noqa: PLC0415 — core.tracking.capture_geometry pulls in cv2, scipy: imported when used

    depth_given = bool(meta.get("depth_given"))
    assumed_k = str(meta.get("intrinsics_source", "")).startswith("assumed")
    geo = resolve_geometry(capture.frames, capture.intrinsics, capture.depth if depth_given else None,
                           intrinsics_assumed=assumed_k)
    keep = geo.keep
    warnings = list(capture.warnings)
    depth, depth_source = capture.depth[keep], capture.depth_source
    if geo.depth is not None and capture.depth_source == ASSUMED_DEPTH_SOURCE:  # not a file, not a depth model
        depth, depth_source = geo.depth.float(), geo.depth_source
        warnings = [w for w in warnings if not w.startswith(_ASSUMED_DEPTH_WARNING)]
    if geo.intrinsics_source:
        meta["intrinsics_source"] = geo.intrinsics_source
        warnings = [w for w in warnings if not w.startswith(_ASSUMED_FOV_WARNING)]
    meta.update(geo.metadata())
    for w in geo.warnings:
        if w not in warnings:
            warnings.append(w)
    return replace(
        capture,
        frames=capture.frames[keep].contiguous(),
        depth=depth.contiguous(),
        intrinsics=geo.intrinsics,
        poses=geo.poses.clone(),
        times=capture.times[keep],
        depth_source=depth_source,
        warnings=warnings,
        metadata=meta,
        stated_ev=None if capture.stated_ev is None else capture.stated_ev[keep],
    )
