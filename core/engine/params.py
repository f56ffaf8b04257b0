"""User-facing job parameters: ONE schema for `lightfield estimate --params` and the service
(the capture's part is core.capture.params.CaptureParams), and ONE place that turns them into
what the engine runs with (`resolve_job`: the EngineConfig and the prior's settings), used by
the engine, the CLI, the demo, the worker and the service's submission checks.

Validated with pydantic v2 (`extra="forbid"`), so a typo in a field name is an error naming
that field rather than a silently ignored option.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Literal, Mapping

from pydantic import field_validator

from core.capture.params import CaptureParams
from core.capture.temporal import TemporalMode
from core.engine.config import EngineConfig
from core.engine.presets import preset, preset_names
from core.fields import field_kinds
from core.priors.diffusion.profiles import ProfileName
from core.priors.registry import job_prior_names, prior_class

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
    # diffusion prior's inference profile (None: the card's; `seed` with preset seed)
    prior_profile: ProfileName | None = None
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


def job_prior_settings(config: EngineConfig, params: JobParams) -> dict:
    """The settings the job's prior is built with: the config's defaults for it, then the job's
    prior_weights and prior_profile as the `weights` and `profile` settings of the priors that
    have them. So the diffusion prior's profile is the job's, else the preset's (`seed` for the
    seed preset), else (None) its model card's."""
    settings = config.prior_settings(params.prior)
    fields = prior_class(params.prior).Config.model_fields
    for key, value in (("weights", params.prior_weights), ("profile", params.prior_profile)):
        if value is not None and key in fields:
            settings[key] = value
    return settings


@dataclass(frozen=True)
class ResolvedJob:
    """What a job's parameters decide for the engine: its config, and the settings its prior
    is built with (resolved on first use: naming a lazily registered prior imports its module)."""

    params: JobParams
    config: EngineConfig

    @cached_property
    def prior_settings(self) -> dict:
        return job_prior_settings(self.config, self.params)


def resolve_job(params: JobParams, overrides: Mapping[str, Any] | None = None,
                config: EngineConfig | None = None) -> ResolvedJob:
    """The job's engine config: `config` if given, else the preset params.preset; with
    `overrides` (EngineConfig.with_overrides: the worker's LIGHTFIELD_DISTILL_OVERRIDES, the
    CLI's --iterations); then the field kind params.field (None: the config's)."""
    config = config or preset(params.preset)
    if overrides:
        config = config.with_overrides(overrides)
    return ResolvedJob(params, config.with_field_kind(params.field))
