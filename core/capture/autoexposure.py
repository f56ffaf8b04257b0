"""Per-frame exposure estimated from the frames, for a video whose camera adjusted its exposure
but did not record it (`CaptureParams.frame_ev = "estimate"`; docs/captures.md).

A phone's auto-exposure scales every pixel of a frame alike, which the frames alone cannot tell
from a dimmer switch turning the whole room down. The user's "estimate" says which it is: the
overall brightness course of the frames (core.capture.temporal.global_log_course: the median
over image blocks of each frame's log change against frame 0, chained through consecutive
frames warped by depth and poses when the camera moves) is taken as the exposure's, and the
frames are put on frame 0's scale with it. A change confined to part of the view (a lamp
switching off) moves a median over blocks little, so it stays a change of light.
"""
from __future__ import annotations

import math
from dataclasses import replace

import torch

from core.capture.base import Capture
from core.capture.params import FRAME_EV_ESTIMATE, MAX_EXPOSURE_STOPS, CaptureParams


def with_estimated_exposure(capture: Capture, params: CaptureParams | None) -> Capture:
    """The capture with each frame's exposure estimated when `params.frame_ev == "estimate"`
    (after tracking: a moving camera's frames are compared through its poses); else as is."""
    if params is None or params.frame_ev != FRAME_EV_ESTIMATE:
        return capture
    from core.capture.temporal import global_log_course

    ev = (global_log_course(capture) / math.log(2.0)).clamp(-MAX_EXPOSURE_STOPS, MAX_EXPOSURE_STOPS).float()
    meta = dict(capture.metadata)
    meta["exposure_source"] = "estimated from the frames (frame_ev='estimate'): frame 0's scale"
    meta["exposure_estimate"] = {"frame_ev": [round(float(e), 4) for e in ev],
                                 "range_stops": round(float(ev.max() - ev.min()), 4) if ev.numel() else 0.0}
    return replace(capture, stated_ev=ev if capture.num_frames > 1 else torch.zeros(capture.num_frames), metadata=meta)
