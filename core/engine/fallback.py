"""The safer answer when the job's check (core.engine.self_check) says the field misread the capture.

The rule, from what the check measures and not from any benchmark's numbers:

* The frames are the only direct measurements of the light the job has. A field that re-renders
  them worse than the capture's constant map does (its median residual above the constant's by
  more than one 8-bit step: a flat wall both explain within a code is a tie, not a loss) is wrong where it was
  shown the answer; nothing suggests it is right where it was not, while the constant map (the
  capture's mean colour from every direction) is the answer every suite scores against. It is
  replaced by that constant map.
* When neighbouring frames disagree where their poses and depth say they overlap
  (core.engine.frame_agreement), the capture is not one scene read one way. If no run of frames
  joined by agreeing pairs holds more than half of the frames, no reading of the capture is backed
  by most of what the camera saw, and the field, fitted to all of it, stands for none:
  the constant map again. A majority run keeps the field, graded "partly explained".
* A camera that moved but could not be tracked keeps its field (static light, as
  core.capture.temporal decides), unless one of the two rules above applies: its frames stand
  at one pose, so their neighbours disagree wherever the motion was large.

The replacement is a field of the `grid` kind with every map the constant colour (no time input),
so every query, bake and export answers it; the quality block records `fallback` and its reason.
"""
from __future__ import annotations

import torch

from core.fields import FieldConfig, LightField, build_field

MAJORITY = 0.5  # a run of frames must hold more than half of them to outvote the rest


def fallback_reason(quality: dict) -> str | None:
    """Why the field is replaced by the constant map (module docstring), or None to keep it."""
    if quality.get("grade") is None:
        return None
    worse = quality["field_residual"] - quality["constant_residual"]
    if worse > quality.get("log_ratio_floor", 0.0):  # within one 8-bit step both explain the frames alike
        return "the field re-renders the frames worse than the capture's constant map"
    agreement = quality.get("frame_agreement") or {}
    if agreement.get("pairs_disagreeing") and agreement.get("largest_agreeing_share", 1.0) <= MAJORITY:
        return ("neighbouring frames disagree where they overlap and no run of agreeing frames holds most "
                "of the capture: no one reading of it stands for the field")
    return None


def constant_field(colour, like: LightField) -> LightField:
    """A field answering `colour` (linear RGB, the field's units) from every direction, at every
    point and time, within `like`'s bounds and radiance range."""
    config = FieldConfig.model_validate({
        "kind": "grid", "uses_time": False,
        "log_radiance_min": like.config.log_radiance_min, "log_radiance_max": like.config.log_radiance_max,
        "grid": {"resolution": [2, 2, 2], "env_height": 2},
    })
    field = build_field(config, like.bounds)
    logits = torch.tensor([field.logit_for_radiance(float(c)) for c in colour], dtype=field.maps.dtype)
    with torch.no_grad():
        field.maps.copy_(logits.expand_as(field.maps))
    return field.eval().requires_grad_(False)


def apply_fallback(field: LightField, quality: dict) -> tuple[LightField, dict]:
    """(the field to store, the quality block with `fallback`: None, or the reason and the answer)."""
    reason = fallback_reason(quality)
    if reason is None:
        return field, {**quality, "fallback": None}
    answer = constant_field(quality["constant_rgb"], field)
    return answer, {**quality, "fallback": {"reason": reason, "answer": "the capture's constant map",
                                            "replaced_field_kind": field.config.kind}}
