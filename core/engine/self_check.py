"""The job's check of itself: does the stored field explain what the camera saw?

Every stage reports its own failures (tracking, exposure, the response, the temporal decision),
but none sees the whole job. A frame is a measurement of the very quantity the field stores:
pixel (u, v) of frame i is the radiance arriving at the camera's centre from the pixel's ray, at
the frame's time, so L(x_i, t_i, d_uv) should reproduce it once the frame's exposure is removed.
Re-rendering each frame from the field and comparing it with the frame therefore checks every
stage at once, with no threshold learned from any benchmark: a field that explains the frames
worse than the capture's constant map (its mean colour from every direction, the baseline every
benchmark scores against) has misread the capture somewhere, and the answer should not be served
as if it had not.

The residual is the median over a frame's usable pixels (neither clipped nor near black) of the
mean |log| error over the colour channels, for the field and for the constant map; the grade
compares the two over the checked frames. A field can absorb a misread (a time input explains two
rooms as a change of light), so the frames are also checked against each other through their
poses and depth (core.engine.frame_agreement): a pair that disagrees caps the grade at "partly
explained". `stage` names the first stage whose own report says it failed or fell back, else the
frames' disagreement, as the place to look; core.engine.fallback decides what is answered.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from core.capture.base import Capture
from core.conventions import direction_to_equirect_pixel, equirect_width
from core.engine.frame_agreement import frame_agreement
from core.envmap import solid_angles

GRADES = ("explained", "partly explained", "worse than a constant map")
DISAGREEING_FRAMES = ("capture: neighbouring frames disagree where their poses and depth say they overlap "
                      "(a track, a depth scale or a cut to another scene misread)")


@dataclass(frozen=True)
class SelfCheckConfig:
    frames: int = 12  # frames re-rendered, spread over the capture
    height: int = 24  # at this height (the check is about the light's layout, not its detail)
    dark_ldr: float = 0.04  # convention codes below: noise and quantisation
    clip_ldr: float = 0.99  # at or above: clipped, the frame says only "at least this bright"


DEFAULT = SelfCheckConfig()
_EPS = 1e-6


def _log_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (torch.log(a.clamp_min(_EPS)) - torch.log(b.clamp_min(_EPS))).abs().mean(-1)


def failed_stage(capture: Capture) -> str | None:
    """The first stage of the capture's preparation whose own record says it failed or fell back."""
    meta = capture.metadata
    tracking = meta.get("tracking") or {}
    if str(tracking.get("method", "")).startswith("failed"):
        return "tracking: " + ("the camera moves but no track registered" if tracking.get("camera_moves")
                               else "no track registered")
    if tracking.get("frames_dropped") and len(tracking["frames_dropped"]) > len(tracking.get("frames_kept", [])):
        return "tracking: most frames could not be registered"
    return None


SEEN_ROWS = 16  # the sphere's cells for the seen share: about 11 degrees each


def seen_share(capture: Capture) -> float:
    """The share of the sphere of directions (by solid angle) the frames saw from their cameras:
    the rest of an answer near them is filled by the prior and the field, not measured."""
    width = equirect_width(SEEN_ROWS)
    hit = torch.zeros(SEEN_ROWS * width, dtype=torch.bool)
    for i in range(capture.num_frames):
        _, d = capture.camera(i).pixel_rays(dtype=torch.float64)
        row, col = direction_to_equirect_pixel(d.reshape(-1, 3), SEEN_ROWS)
        row = row.round().long().clamp(0, SEEN_ROWS - 1)
        col = col.round().long().remainder(width)
        hit[row * width + col] = True
    area = solid_angles(SEEN_ROWS, dtype=torch.float64).reshape(-1)
    return float(area[hit].sum() / area.sum())


@torch.no_grad()
def self_check(field, capture: Capture, uses_time: bool, config: SelfCheckConfig = DEFAULT) -> dict:
    """The `quality` block of a job (module docstring): per checked frame the field's and the
    constant map's residuals, how many frames the field explains better, their ratio and the grade."""
    small = capture.resized(config.height)
    linear = small.linear().double()
    peak = small.frames.amax(-1)
    usable = (peak < config.clip_ldr) & (peak > config.dark_ldr)
    if int(usable.sum()) == 0:
        return {"grade": None, "why": "no frame pixel is neither clipped nor dark: nothing to check against",
                "frames_checked": 0, "stage": failed_stage(capture)}
    constant = linear.reshape(-1, 3).mean(0)  # every pixel, clipped ones at their white: the benches' constant map
    rows = []
    for i in small.spread_frames(config.frames).tolist():
        keep = usable[i]
        if int(keep.sum()) < 16:
            continue
        x, d = small.camera(i).pixel_rays()
        d = d[keep]
        t = torch.full((d.shape[0],), float(small.times[i])) if uses_time else None
        pred = field(x.expand(d.shape[0], 3).contiguous(), t, d).double()
        seen = linear[i][keep]
        const = constant.expand_as(seen)
        rows.append((i, float(_log_error(pred, seen).median()), float(_log_error(const, seen).median())))
    if not rows:
        return {"grade": None, "why": "no frame has enough usable pixels to check against", "frames_checked": 0,
                "stage": failed_stage(capture)}
    agreement = frame_agreement(small, usable, linear)
    field_res = torch.tensor([r[1] for r in rows])
    const_res = torch.tensor([r[2] for r in rows])
    ratio = float(field_res.median() / const_res.median().clamp_min(_EPS))
    explained = int((field_res < const_res).sum())
    consistent = not agreement["pairs_disagreeing"]
    grade = (GRADES[0] if explained == len(rows) and ratio < 1.0 and consistent else
             GRADES[1] if ratio < 1.0 else GRADES[2])
    stage = failed_stage(capture) or (None if consistent else DISAGREEING_FRAMES)
    return {
        "grade": grade,
        "residual_ratio": round(ratio, 4),  # field / constant map, medians over the checked frames
        "frames_checked": len(rows),
        "frames_explained": explained,  # frames the field explains better than the constant map
        "field_residual": round(float(field_res.median()), 4),  # median |log| error (natural log units)
        "constant_residual": round(float(const_res.median()), 4),
        "constant_rgb": [round(float(c), 6) for c in constant],  # the constant map (linear, the field's units)
        "per_frame": [{"frame": i, "field": round(f, 4), "constant": round(c, 4)} for i, f, c in rows],
        "frame_agreement": agreement,
        "seen_share": round(seen_share(small), 4),  # of the sphere, from the cameras; the rest is filled
        "stage": stage,
        "why": ("the field re-renders what the camera saw better than a constant map" if ratio < 1.0 else
                "the field re-renders what the camera saw worse than a constant map: a stage misread the capture"),
        "note": f"frames re-rendered at {config.height} px from the stored field at each frame's camera and time",
        "log_ratio_floor": round(math.log(1.0 + 1.0 / 255.0), 5),  # one 8-bit step: residuals under it are noise
    }
