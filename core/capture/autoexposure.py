"""Per-frame exposure estimated from the frames, for a video whose camera adjusted its exposure
but did not record it (`CaptureParams.frame_ev`; docs/captures.md, "Exposure").

A phone's auto-exposure scales every pixel of a frame alike, which the frames' overlap alone
cannot tell from a dimmer switch turning the whole room down. Two things can:
* the user: `frame_ev = "estimate"` says the camera did it, `"locked"` says it did not;
* by default (`frame_ev` unset), for a MOVING camera, the exposure's signature. An
  auto-exposure answers what the frame shows: it holds each frame's metered mean near one
  level, so while the overlap of consecutive frames says the brightness moved, the frames'
  own means move much less: their spread over the clip under AUTO_RATIO of the overlap's,
  or their steps under AUTO_STEP_RATIO of the overlap's (root mean square; a fast exposure).
  With a locked exposure a frame's mean steps by the overlap's step plus what the view brings,
  so its steps are that small only if the light moved against the view, which is what an
  auto-exposure does. A lagging exposure steps the brightness up when the frame it meters is
  dark and down when it is bright, so the overlap's steps fall as the frames' means rise
  (rank correlation under -AUTO_STEP_CORRELATION, with the frame itself or the one before
  it: a one-frame metering delay), where a locked exposure's steps follow the light, not the
  view. A static camera's exposure only moves because the light did, so it is left alone.
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
AUTO_STEP_RATIO = 0.5  # frame means' steps / the overlap's (rms) below which the exposure moved (dev pans)
AUTO_STEP_CORRELATION = 0.7  # a lagging exposure's steps against the metered means (dev pans; bench.auto_exposure_pans)
AUTO_MIN_STEPS = 6  # fewer overlap steps say nothing by their rank correlation


def _ranks(x: torch.Tensor) -> torch.Tensor:
    """Ranks from 0, ties sharing their mean rank (so equal values carry no order)."""
    values, order = x.double().sort()
    _, group, counts = torch.unique_consecutive(values, return_inverse=True, return_counts=True)
    first = counts.cumsum(0) - counts
    ranks = torch.empty_like(values)
    ranks[order] = (first + (counts - 1) / 2.0).double()[group]
    return ranks


def rank_correlation(a: torch.Tensor, b: torch.Tensor) -> float:
    """Spearman's rank correlation of two series (0 when either is constant): a rank statistic,
    so one large step (a light switching) cannot make it by itself."""
    ra, rb = _ranks(a), _ranks(b)
    ra, rb = ra - ra.mean(), rb - rb.mean()
    den = float(ra.norm() * rb.norm())
    return float((ra * rb).sum()) / den if den > 0 else 0.0


def exposure_evidence(capture: Capture) -> dict:
    """The overall course (log, against frame 0), the frames' own mean log luminance (frame
    units, clipped pixels at white), the ratio of their spreads and of their steps, and the
    course's steps' rank correlation with the means of the frame they end at or the one before
    (the lower)."""
    from core.capture.temporal import ANALYSIS_HEIGHT, global_log_course
    from core.conventions import inverse_tonemap
    from core.exposure import luminance

    course = global_log_course(capture)
    small = capture.resized(ANALYSIS_HEIGHT)
    means = torch.log(luminance(inverse_tonemap(small.frames)).reshape(capture.num_frames, -1).mean(1).double().clamp_min(1e-8))
    spread = float(course.std()) if course.numel() > 1 else 0.0
    ratio = float((means - means[0]).std() / spread) if spread > 0 else float("inf")
    steps = course.diff()
    step_rms = float(steps.square().mean().sqrt()) if steps.numel() else 0.0
    step_ratio = float(means.diff().square().mean().sqrt()) / step_rms if step_rms > 0 else float("inf")
    step_corr = (min(rank_correlation(steps, means[1:]), rank_correlation(steps, means[:-1]))
                 if steps.numel() >= AUTO_MIN_STEPS else 0.0)
    return {"course": course, "course_range": float(course.max() - course.min()) if course.numel() else 0.0,
            "frame_mean_ratio": ratio, "frame_step_ratio": step_ratio, "step_mean_correlation": step_corr}


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
               "frame_mean_ratio": round(evidence["frame_mean_ratio"], 4), "auto_ratio": AUTO_RATIO,
               "frame_step_ratio": round(evidence["frame_step_ratio"], 4), "auto_step_ratio": AUTO_STEP_RATIO,
               "step_mean_correlation": round(evidence["step_mean_correlation"], 4),
               "auto_step_correlation": -AUTO_STEP_CORRELATION}
    if mode != FRAME_EV_ESTIMATE:
        detected = evidence["course_range"] > AUTO_MIN_RANGE and (
            evidence["frame_mean_ratio"] < AUTO_RATIO or evidence["frame_step_ratio"] < AUTO_STEP_RATIO
            or evidence["step_mean_correlation"] < -AUTO_STEP_CORRELATION)
        if not detected:
            meta["exposure_estimate"] = {**summary, "applied": False}
            return replace(capture, metadata=meta)
    ev = (evidence["course"] / math.log(2.0)).clamp(-MAX_EXPOSURE_STOPS, MAX_EXPOSURE_STOPS).float()
    meta["exposure_source"] = ("estimated from the frames (frame_ev='estimate')" if mode == FRAME_EV_ESTIMATE else
                               "estimated from the frames: a moving camera's auto-exposure detected (frame_ev unset; "
                               "'locked' turns this off)") + ": frame 0's scale"
    meta["exposure_estimate"] = {**summary, "applied": True, "frame_ev": [round(float(e), 4) for e in ev]}
    return replace(capture, stated_ev=ev, metadata=meta)
