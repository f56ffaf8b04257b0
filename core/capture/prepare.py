"""Capture preparation, a job's first stage: load the capture (core.capture.load), track the
camera when several frames came without poses (core.capture.track), paint out what moved
through the view (core.capture.transients), then estimate the frames' exposure when the
camera changed it without recording it (core.capture.autoexposure). The last two compare a
moving camera's frames through the poses tracking found, hence the order. The camera's response is estimated right after
tracking where the capture states exposures that vary (core.capture.response).

The caller reports and times the steps: `on_stage(name, message)` when a reported stage
starts ("loading", "tracking"), `timed(name)` a context manager around each step's work
(core.engine.progress.StageTimer fits); the capture's warnings are the caller's to show."""
from __future__ import annotations

import warnings
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, replace
from typing import Callable

from core.capture.autoexposure import with_estimated_exposure
from core.capture.base import Capture
from core.capture.config import CaptureConfig, using_capture
from core.capture.load import load_capture
from core.capture.params import CaptureParams
from core.capture.response import with_estimated_response
from core.capture.track import track_capture
from core.capture.transients import without_transients
from core.io.limits import MediaLimits
from core.tracking.config import TrackingConfig, using_tracking

StageCallback = Callable[[str, str], None]  # (stage name, message)
StageTiming = Callable[[str], AbstractContextManager]


@dataclass(frozen=True)
class PreparedCapture:
    capture: Capture  # tracked, transients painted out, exposure estimated: what the engine distils
    as_uploaded: Capture  # tracked, before transients are painted out

    def preview(self) -> Capture:
        """The prepared capture showing the frames as the user took them, passers-by and all
        (the worker's UI preview)."""
        return replace(self.capture, frames=self.as_uploaded.frames, depth=self.as_uploaded.depth)


def prepare_capture(input_path, depth_path=None, params: CaptureParams | None = None,
                    limits: MediaLimits | None = None, *, on_stage: StageCallback | None = None,
                    timed: StageTiming | None = None, tracking: TrackingConfig | None = None,
                    knobs: CaptureConfig | None = None) -> PreparedCapture:
    """Load -> track -> transients -> exposure (module docstring); `limits` as load_capture's;
    `tracking` and `knobs`: the tracker's and the stages' settings (EngineConfig.tracking and
    .capture; None: those already active)."""
    params = params or CaptureParams()
    on_stage = on_stage or (lambda name, message: None)
    timed = timed or (lambda name: nullcontext())
    on_stage("loading", "reading input")
    with timed("loading"):
        capture = load_capture(input_path, depth_path, params, limits)
    if capture.num_frames > 1:  # tracked, or given poses placed in a world-fixed room (track_capture)
        tracks = not capture.metadata.get("poses_source")
        if tracks:
            on_stage("tracking", "finding the camera's motion")
        with timed("tracking" if tracks else "loading"), using_tracking(tracking):
            capture = track_capture(capture, params)
    if capture.stated_ev is not None:  # a curve is told by stated exposures only (core.capture.response)
        with timed("response"):
            capture, _ = with_estimated_response(capture)
    as_uploaded = capture
    # after tracking: a moving camera's frames are compared through its poses
    with timed("transients"), using_capture(knobs):
        capture = without_transients(capture, params)
    capture = with_estimated_exposure(capture, params)  # after tracking: a pan is compared through its poses
    return PreparedCapture(capture, as_uploaded)


def load_prepared_capture(input_path, depth_path=None, params: CaptureParams | None = None,
                          limits: MediaLimits | None = None, tracking: TrackingConfig | None = None,
                          knobs: CaptureConfig | None = None) -> Capture:
    """The capture as a job distils it (prepare_capture in one call, its warnings shown): what
    scripts and tests that load a capture outside a job want."""
    capture = prepare_capture(input_path, depth_path, params, limits, tracking=tracking, knobs=knobs).capture
    for w in capture.warnings:
        warnings.warn(w, stacklevel=2)
    return capture
