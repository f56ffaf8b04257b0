"""Per-frame exposure estimated from the frames, for a video whose camera adjusted its exposure
but did not record it (`CaptureParams.frame_ev`; docs/captures.md, "Exposure").

A phone's auto-exposure scales every pixel of a frame alike, which the frames' overlap alone
cannot tell from a dimmer switch turning the whole room down. Two things can:
* the user: `frame_ev = "estimate"` says the camera did it, `"locked"` says it did not;
* by default (`frame_ev` unset), for a MOVING camera, the exposure's signature: an
  auto-exposure holds each frame's metered mean near one level, so while the overlap of
  consecutive frames says the brightness moved, the frames' own means move much less
  (their spread over the clip under AUTO_RATIO of the overlap's). With a locked exposure a
  dimming moves both alike. A static camera's exposure only moves because the light did, so
  it is left alone.
The overall brightness course (core.capture.temporal.global_log_course: the median over image
blocks of each frame's log change against frame 0, chained through consecutive frames warped
by depth and poses when the camera moves) is then taken as the exposure's, and the frames are
put on frame 0's scale. A change confined to part of the view (a lamp switching off) moves a
median over blocks little, so it stays a change of light.
"""
from __future__ import annotations

import math
from dataclasses import replace

import torch

from core.capture.base import Capture
from core.capture.params import FRAME_EV_ESTIMATE, FRAME_EV_LOCKED, MAX_EXPOSURE_STOPS, CaptureParams

AUTO_RATIO = 0.3  # frame means' spread / overlap course's spread below which a moving camera's exposure moved (dev pans)
AUTO_MIN_RANGE = math.log(1.08)  # a course smaller than the temporal decision's floor needs no exposure


def exposure_evidence(capture: Capture) -> dict:
    """The overall course (log, against frame 0), the frames' own mean log luminance (frame
    units, clipped pixels at white) and the ratio of their spreads."""
    from core.capture.temporal import ANALYSIS_HEIGHT, global_log_course
    from core.conventions import inverse_tonemap
    from core.exposure import luminance

    course = global_log_course(capture)
    small = capture.resized(ANALYSIS_HEIGHT)
    means = torch.log(luminance(inverse_tonemap(small.frames)).reshape(capture.num_frames, -1).mean(1).double().clamp_min(1e-8))
    spread = float(course.std()) if course.numel() > 1 else 0.0
    ratio = float((means - means[0]).std() / spread) if spread > 0 else float("inf")
    return {"course": course, "course_range": float(course.max() - course.min()) if course.numel() else 0.0,
            "frame_mean_ratio": ratio}


def with_estimated_exposure(capture: Capture, params: CaptureParams | None) -> Capture:
    """The capture with each frame's exposure estimated when `params.frame_ev` is "estimate",
    or unset for a moving camera whose frames show an auto-exposure's signature; else as is.
    Called after tracking (a moving camera's frames are compared through its poses)."""
    mode = None if params is None else params.frame_ev
    if capture.stated_ev is not None or capture.num_frames < 2 or mode == FRAME_EV_LOCKED or isinstance(mode, list):
        return capture
    if mode != FRAME_EV_ESTIMATE and capture.static_camera:
        return capture
    evidence = exposure_evidence(capture)
    meta = dict(capture.metadata)
    summary = {"course_range_stops": round(evidence["course_range"] / math.log(2.0), 4),
               "frame_mean_ratio": round(evidence["frame_mean_ratio"], 4), "auto_ratio": AUTO_RATIO}
    if mode != FRAME_EV_ESTIMATE:
        detected = evidence["course_range"] > AUTO_MIN_RANGE and evidence["frame_mean_ratio"] < AUTO_RATIO
        if not detected:
            meta["exposure_estimate"] = {**summary, "applied": False}
            return replace(capture, metadata=meta)
    ev = (evidence["course"] / math.log(2.0)).clamp(-MAX_EXPOSURE_STOPS, MAX_EXPOSURE_STOPS).float()
    meta["exposure_source"] = ("estimated from the frames (frame_ev='estimate')" if mode == FRAME_EV_ESTIMATE else
                               "estimated from the frames: a moving camera's auto-exposure detected (frame_ev unset; "
                               "'locked' turns this off)") + ": frame 0's scale"
    meta["exposure_estimate"] = {**summary, "applied": True, "frame_ev": [round(float(e), 4) for e in ev]}
    return replace(capture, stated_ev=ev, metadata=meta)
