"""The model card `lightfield_prior.json` that sits next to the diffusers sub-models.

It carries what the diffusers configs cannot: the two exposure prompts, the darkest
exposure the model was trained for, the working resolution and whether the model
inpaints several balls in one image. Unknown keys are kept (free-form notes such as
licence or provenance) but never interpreted.
"""
from __future__ import annotations

import json
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from core.conventions import DEFAULT_EV_MIN
from core.priors.base import PriorError

CARD_FILENAME = "lightfield_prior.json"
CARD_FORMAT = "lightfield-prior"
CARD_VERSION = 1

PROMPT_MAX = "perfect mirrored reflective chrome ball spheres"
PROMPT_MIN = "perfect black dark mirrored reflective chrome ball spheres"


class ExposurePrompts(BaseModel):
    """Text whose embeddings anchor the exposure interpolation (zeta_max at EV 0, zeta_min at ev_min)."""

    model_config = ConfigDict(extra="forbid")
    max: str = PROMPT_MAX
    min: str = PROMPT_MIN


class ModelCard(BaseModel):
    model_config = ConfigDict(extra="allow")

    format: str = CARD_FORMAT
    version: int = CARD_VERSION
    prompts: ExposurePrompts = Field(default_factory=ExposurePrompts)
    ev_min: float = DEFAULT_EV_MIN
    resolution: tuple[int, int] = (512, 512)  # [H, W] the model was trained at
    multi_ball: bool = True
    controlnet_conditioning_scale: float = 1.0
    default_guidance_scale: float = 3.0
    base: str = ""  # provenance, e.g. "stabilityai/stable-diffusion-2-inpainting + depth controlnet"

    @field_validator("format")
    @classmethod
    def _known_format(cls, v: str) -> str:
        if v != CARD_FORMAT:
            raise ValueError(f"format must be {CARD_FORMAT!r}, got {v!r}")
        return v

    @field_validator("version")
    @classmethod
    def _known_version(cls, v: int) -> int:
        if v > CARD_VERSION:
            raise ValueError(f"version {v} is newer than this code understands ({CARD_VERSION})")
        return v

    @field_validator("ev_min")
    @classmethod
    def _negative_ev_min(cls, v: float) -> float:
        if not (v < 0.0 and v > -30.0):
            raise ValueError(f"ev_min must be in (-30, 0), got {v}")
        return v

    @field_validator("resolution")
    @classmethod
    def _positive_resolution(cls, v: tuple[int, int]) -> tuple[int, int]:
        if min(v) < 8 or max(v) > 4096:
            raise ValueError(f"resolution must be [H, W] with sides in [8, 4096], got {list(v)}")
        return v

    @field_validator("controlnet_conditioning_scale", "default_guidance_scale")
    @classmethod
    def _non_negative(cls, v: float) -> float:
        if not v >= 0.0:
            raise ValueError(f"must be >= 0, got {v}")
        return v

    @classmethod
    def load(cls, model_dir: str | Path) -> "ModelCard":
        path = Path(model_dir) / CARD_FILENAME
        if not path.is_file():
            raise PriorError(
                f"{model_dir}: missing model card {CARD_FILENAME} "
                "(see docs/diffusion-prior.md for its fields)"
            )
        try:
            return cls.model_validate(json.loads(path.read_text()))
        except (json.JSONDecodeError, ValidationError) as exc:
            raise PriorError(f"{path}: invalid model card: {exc}") from exc

    def save(self, model_dir: str | Path) -> Path:
        path = Path(model_dir) / CARD_FILENAME
        path.write_text(json.dumps(self.model_dump(mode="json"), indent=2) + "\n")
        return path
