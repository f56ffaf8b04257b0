"""The capture preparation's tuning knobs (CaptureConfig; so far the transients stage's), as
`EngineConfig.capture`: `--set capture.transients.transient_ratio=0.2` in the benches that take
`--set` runs an ablation without a commit. Read when the stage runs (`capture_config()`);
`using_capture(cfg)` makes `cfg` active inside it, as core.tracking.config's `using_tracking`
does for the tracker (core.capture.prepare applies both; bench.overrides.knobs_of for a job).

Constants that stay in their modules: those of core/capture/response.py and temporal.py, the
HDR merge's (the prior reads them during distillation, outside the capture stage), the clip
rule's fitted coefficients (bench/calibration fits them) and the texts of sources."""
from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field

from core.active_settings import ActiveSettings


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class TransientsConfig(_Section):
    """Things moving through the view, told from a change of light (core.capture.transients)."""

    min_frames: int = Field(8, ge=2, description="fewer frames cannot separate a course of light from a passer-by")
    # what stays + up to two lights changing on their own courses (12+ frames; 8-11 frames: 2)
    rank: int = Field(3, ge=1)
    # the static camera's model is fitted on frames area-downsampled to this height: noise averages
    # out and a passer-by still spans many pixels
    analysis_height: int = Field(36, ge=4)
    transient_ratio: float = Field(math.log(1.3), gt=0, description="log departure from the model under which "
                                                                    "a pixel is not a transient (30 %)")
    k_sigma: float = Field(5.0, ge=0, description="... nor within this many times the pixel's own noise")
    max_frame_share: float = Field(0.5, gt=0, le=1, description="a frame more transient than this is left as is")
    min_share: float = Field(1e-3, ge=0, description="a clip with fewer transient pixels is left as it is")
    iterations: int = Field(12, ge=1, description="robust low-rank refits")
    moving_height: int = Field(72, ge=4, description="a moving camera's frames are compared at this height")
    moving_window: int = Field(3, ge=1, description="... each with this many neighbours either side, warped into it")
    moving_min_side: int = Field(2, ge=1, description="... where at least this many on each side see the point")
    # ... or, at the edge of a pan's view or the clip, this many on one side
    moving_one_side: int = Field(3, ge=1)
    # ... unless a light switched in the window (this share of points agree with one side only)
    switch_share: float = Field(0.03, ge=0, le=1)
    min_shared_pixels: int = Field(50, ge=1, description="a neighbour sharing fewer usable pixels is not used")
    keep_course: float = Field(0.5, gt=0, le=1, description="a course of light is kept if it explains this share "
                                                            "of the departures left")


class CaptureConfig(_Section):
    transients: TransientsConfig = TransientsConfig()


DEFAULT_CAPTURE = CaptureConfig()
_ACTIVE = ActiveSettings("capture_config", DEFAULT_CAPTURE)


def capture_config() -> CaptureConfig:
    """The settings the capture stage runs with now."""
    return _ACTIVE.get()


def using_capture(config: CaptureConfig | None):
    """Prepare captures with `config` inside the block (None: the settings already active)."""
    return _ACTIVE.using(config)
