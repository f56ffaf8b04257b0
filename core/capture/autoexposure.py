"""Per-frame exposure estimated from the frames, for a video whose camera adjusted its exposure
but did not record it (`CaptureParams.frame_ev`; docs/captures.md, "Exposure").

A phone's auto-exposure scales every pixel of a frame alike, which the frames' overlap alone
cannot tell from a dimmer turning every light in the room down at once. The default follows
how such videos are made:
* a MOVING camera with no stated exposure is taken to have auto-exposed, as phones and AR
  sessions do unless the user locks it: the overall brightness course of what its frames both
  show is the exposure's. `frame_ev = "locked"` says the exposure was fixed, and that course
  then stays a change of light;
* a STATIC camera's brightness only moves because the light did (a still camera meters the
  same view), so it is left alone unless `frame_ev = "estimate"` says otherwise.
The course (core.capture.temporal.global_log_course: the median over image blocks of each
frame's log change against frame 0, from every pair of frames that show the same surfaces,
warped by depth and poses) puts the frames on frame 0's scale. A change confined to part of
the view (a lamp switching off) moves a median over blocks little, so it stays a change of
light. An earlier default looked for an auto-exposure's signature instead (thresholds on the
frames' metered means, chosen on dev pans); under cross-validation on room scans it missed
13 of 24 auto-exposures, each then read as the light changing (docs/engine.md).
"""
from __future__ import annotations

import math
from dataclasses import replace

from core.capture.base import Capture
from core.capture.params import FRAME_EV_ESTIMATE, FRAME_EV_LOCKED, MAX_EXPOSURE_STOPS, CaptureParams
from core.capture.temporal import ABS_FLOOR, global_log_course


def with_estimated_exposure(capture: Capture, params: CaptureParams | None) -> Capture:
    """The capture with each frame's exposure estimated when `params.frame_ev` is "estimate",
    or unset for a moving camera (module docstring); else as is. Called after tracking (a
    moving camera's frames are compared through its poses)."""
    mode = None if params is None else params.frame_ev
    if capture.stated_ev is not None or capture.num_frames < 2 or mode == FRAME_EV_LOCKED or isinstance(mode, list):
        return capture
    if mode != FRAME_EV_ESTIMATE and capture.static_camera:
        return capture
    course = global_log_course(capture)
    span = float(course.max() - course.min())
    meta = dict(capture.metadata)
    summary = {"course_range_stops": round(span / math.log(2.0), 4)}
    if mode != FRAME_EV_ESTIMATE and span <= ABS_FLOOR:  # under the temporal decision's floor: nothing to correct
        meta["exposure_estimate"] = {**summary, "applied": False}
        return replace(capture, metadata=meta)
    ev = (course / math.log(2.0)).clamp(-MAX_EXPOSURE_STOPS, MAX_EXPOSURE_STOPS).float()
    meta["exposure_source"] = ("estimated from the frames (frame_ev='estimate')" if mode == FRAME_EV_ESTIMATE else
                               "estimated from the frames: a moving camera is taken to auto-expose (frame_ev unset; "
                               "'locked' says it did not)") + ": frame 0's scale"
    meta["exposure_estimate"] = {**summary, "applied": True, "frame_ev": [round(float(e), 4) for e in ev]}
    return replace(capture, stated_ev=ev, metadata=meta)
