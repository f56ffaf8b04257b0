"""What a user tells us about a capture beyond its pixels (intrinsics, poses, fps, frame
budget): the capture part of the job parameters (core.engine.params.JobParams), one schema
for `lightfield estimate --params` and the service.

Validated with pydantic v2 (`extra="forbid"`), so a typo in a field name is an error naming
that field rather than a silently ignored option.
"""
from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from core.transfer import AUTO, parse_transfer

MAX_FPS = 240.0
MAX_FRAMES_LIMIT = 10_000  # hard ceiling; MediaLimits may be stricter
FRAME_EV_ESTIMATE = "estimate"  # frame_ev: estimate each frame's exposure from the frames (core.capture.autoexposure)
FRAME_EV_LOCKED = "locked"  # frame_ev: the exposure was locked (no estimate, not even the automatic one)
MAX_EXPOSURE_STOPS = 20.0  # |frame_ev|: the simulator's and tone map's exposure range


class _Strict(BaseModel):
    # strict: JSON true is not 1.0, "2" is not 2 (a typo must not become a value)
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


class IntrinsicsParams(_Strict):
    """Either the pinhole matrix entries (pixels, continuous coordinates) or a horizontal FOV."""

    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    hfov_deg: float | None = None

    @model_validator(mode="after")
    def _one_form(self) -> "IntrinsicsParams":
        pinhole = [self.fx, self.fy, self.cx, self.cy]
        has_pinhole = any(v is not None for v in pinhole)
        if has_pinhole and self.hfov_deg is not None:
            raise ValueError("intrinsics: give either fx, fy, cx, cy or hfov_deg, not both")
        if has_pinhole:
            for name in ("fx", "fy", "cx", "cy"):
                v = getattr(self, name)
                if v is None:
                    raise ValueError(f"intrinsics.{name} is missing (fx, fy, cx, cy go together)")
                if not math.isfinite(v):
                    raise ValueError(f"intrinsics.{name} must be finite, got {v}")
            if self.fx <= 0 or self.fy <= 0:
                raise ValueError(f"intrinsics.fx/fy must be > 0, got fx={self.fx}, fy={self.fy}")
        elif self.hfov_deg is None:
            raise ValueError("intrinsics: give fx, fy, cx, cy or hfov_deg")
        else:
            if not math.isfinite(self.hfov_deg) or not (0.0 < self.hfov_deg < 180.0):
                raise ValueError(f"intrinsics.hfov_deg must be in (0, 180), got {self.hfov_deg}")
        return self


class CaptureParams(_Strict):
    """What we know about the capture beyond its pixels (all optional; defaults are documented
    in docs/engine.md: DEFAULT_HFOV_DEG, a static camera, the file's own fps)."""

    intrinsics: IntrinsicsParams | None = None
    poses: list[list[float]] | None = Field(default=None, description="T x 16 camera-to-world, row-major")
    fps: float | None = None
    max_frames: int | None = None
    frame_ev: list[float] | Literal["estimate", "locked"] | None = Field(
        default=None, description="each frame's exposure in stops, one per frame of the input (an auto-exposure "
                                  "video's per-frame metadata, e.g. log2(exposure time x ISO / reference)); a "
                                  "frame's linear values are divided by 2^ev, so the frames share one radiance scale. "
                                  "'estimate': the camera adjusted its exposure without recording it, so the frames' "
                                  "overall brightness course is taken as the exposure's; 'locked': it did not; unset: "
                                  "estimated for a moving camera whose frames show an auto-exposure (docs/captures.md)")
    transfer: str = Field(
        default=AUTO, description="the camera's transfer function (how its code values relate to light): 'srgb', "
                                  "'rec709', 'gamma:G' (1 <= G <= 4), 'linear', 'hlg', 'pq', or 'auto': what the file "
                                  "says (PNG sRGB/gAMA/iCCP/cICP chunks, a JPEG's ICC profile or EXIF colour space, a "
                                  "video stream's transfer characteristics), and sRGB when it says nothing. Where the "
                                  "frames' exposures vary, the response is also estimated from the frames and used "
                                  "when it explains them better (docs/captures.md, 'The camera's response')")
    tracking: Literal["auto", "off"] = Field(
        default="auto", description="camera tracking when several frames come without poses: 'auto' detects camera "
                                     "motion and tracks it; 'off' treats the camera as static (docs/captures.md)")
    transients: Literal["remove", "keep"] = Field(
        default="remove", description="something moving through the view (a person walking through): 'remove' "
                                      "paints it out (a static camera: from the frames where its pixels are clear; a "
                                      "moving one: from the neighbouring frames), so it is not read as the light "
                                      "changing; 'keep' leaves the frames as they are (docs/captures.md)")

    @field_validator("poses")
    @classmethod
    def _poses(cls, v):
        if v is None:
            return v
        if len(v) == 0:
            raise ValueError("poses must not be empty")
        for i, row in enumerate(v):
            if len(row) != 16:
                raise ValueError(f"poses[{i}] must have 16 numbers (row-major 4x4), got {len(row)}")
            if not all(math.isfinite(x) for x in row):
                raise ValueError(f"poses[{i}] contains non-finite values")
        return v

    @field_validator("frame_ev")
    @classmethod
    def _frame_ev(cls, v):
        if v is None or isinstance(v, str):
            return v
        if len(v) == 0:
            raise ValueError("frame_ev must not be empty")
        for i, e in enumerate(v):
            if not (math.isfinite(e) and abs(e) <= MAX_EXPOSURE_STOPS):
                raise ValueError(f"frame_ev[{i}] must be finite and within +-{MAX_EXPOSURE_STOPS:g} stops, got {e}")
        return v

    @field_validator("transfer")
    @classmethod
    def _transfer(cls, v):
        if v != AUTO:
            parse_transfer(v)  # ValueError naming the accepted forms
        return v

    @field_validator("fps")
    @classmethod
    def _fps(cls, v):
        if v is not None and (not math.isfinite(v) or not (0.0 < v <= MAX_FPS)):
            raise ValueError(f"fps must be in (0, {MAX_FPS:g}], got {v}")
        return v

    @field_validator("max_frames")
    @classmethod
    def _max_frames(cls, v):
        if v is not None and not (1 <= v <= MAX_FRAMES_LIMIT):
            raise ValueError(f"max_frames must be in [1, {MAX_FRAMES_LIMIT}], got {v}")
        return v
