"""User-facing job parameters: ONE schema for `lightfield estimate --params` and the service
(the capture's part is core.capture.params.CaptureParams).

Validated with pydantic v2 (`extra="forbid"`), so a typo in a field name is an error naming
that field rather than a silently ignored option.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

from pydantic import field_validator

from core.capture.params import CaptureParams
from core.capture.temporal import TemporalMode
from core.engine.presets import preset_names
from core.fields import field_kinds
from core.priors.diffusion.profiles import ProfileName
from core.priors.registry import job_prior_names

# the choices are the registries' names (a registered preset, prior or field kind is offered here)
PresetName = Literal[preset_names()]
PriorName = Literal[job_prior_names()]
FieldKind = Literal[field_kinds()]


class JobParams(CaptureParams):
    """A full estimation job. `prior_weights` is a LOCAL directory; the service restricts it
    to its configured model directories, the CLI takes it as given."""

    preset: PresetName = "draft"
    prior: PriorName = "reprojection"
    prior_weights: str | None = None
    prior_profile: ProfileName | None = None  # diffusion prior's inference profile (None: the card's; `seed` with preset seed)
    temporal: TemporalMode = "auto"
    seed: int = 0
    field: FieldKind | None = None  # None -> the preset's default

    @field_validator("seed")
    @classmethod
    def _seed(cls, v):
        if not (0 <= v < 2**63):
            raise ValueError(f"seed must be in [0, 2^63), got {v}")
        return v


def parse_job_params(text_or_path: str | None, **overrides) -> JobParams:
    """Parse `--params` (a JSON string or a path to a JSON file) and apply CLI overrides
    (None values are ignored, so unset flags keep the JSON's value)."""
    data: dict = {}
    if text_or_path:
        s = text_or_path.strip()
        if not s.startswith("{") and Path(s).is_file():
            s = Path(s).read_text()
        try:
            data = json.loads(s)
        except json.JSONDecodeError as exc:
            raise ValueError(f"--params is neither a JSON object nor a JSON file: {exc}") from None
        if not isinstance(data, dict):
            raise ValueError("--params must be a JSON object")
    data.update({k: v for k, v in overrides.items() if v is not None})
    return JobParams.model_validate(data)
