"""The model card `lightfield_prior.json` that sits next to the diffusers sub-models.

It carries what the diffusers configs cannot: the two exposure prompts, the darkest
exposure the model was trained for, the working resolution, whether the model inpaints
several balls in one image, and (version 2, written by `lightfield prior import`) what
the weights are: base family, UNet input channels, what the ControlNet is fed (depth or
normals), the inference profile they were released with, an optional exposure LoRA and
the record of the import. Version-1 cards (no such fields) read with the defaults, which
describe what version 1 assumed: SD-2 family, 9-channel UNet, depth ControlNet, `paper`.
Unknown keys are kept (free-form notes such as licence or provenance) but never interpreted.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from core.conventions import DEFAULT_EV_MIN
from core.priors.base import PriorError
from core.priors.diffusion.profiles import ProfileName

CARD_FILENAME = "lightfield_prior.json"
CARD_FORMAT = "lightfield-prior"
CARD_VERSION = 2

PROMPT_MAX = "perfect mirrored reflective chrome ball spheres"
PROMPT_MIN = "perfect black dark mirrored reflective chrome ball spheres"


class ExposurePrompts(BaseModel):
    """Text whose embeddings anchor the exposure interpolation (zeta_max at EV 0, zeta_min at ev_min)."""

    model_config = ConfigDict(extra="forbid")
    max: str = PROMPT_MAX
    min: str = PROMPT_MIN


BaseFamily = Literal["sd1", "sd2", "sdxl"]
Conditioning = Literal["depth", "normals"]
SamplerName = Literal["ddim", "unipc"]


class LoraSpec(BaseModel):
    """A LoRA fused into the UNet at load time (DiffusionLight's exposure LoRA: w + scale * dW)."""

    model_config = ConfigDict(extra="forbid")
    file: str = "lora/pytorch_lora_weights.safetensors"  # relative to the model directory
    scale: float = 0.75

    @field_validator("file")
    @classmethod
    def _relative_inside(cls, v: str) -> str:
        p = Path(v)
        if p.is_absolute() or ".." in p.parts or not v.endswith(".safetensors"):
            raise ValueError(f"lora.file must be a relative *.safetensors path inside the model directory, got {v!r}")
        return v


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
    # version 2: what the weights are (checked against the sub-model configs at load time)
    base_family: BaseFamily = "sd2"
    unet_in_channels: int = 9  # 9: inpainting UNet; 4: base UNet, inpainting by latent blending
    controlnet_conditioning: Conditioning = "depth"
    negative_prompt: str = ""  # the classifier-free-guidance branch's prompt
    profile: ProfileName = "paper"  # inference conventions the weights were released with
    sampler: SamplerName = "ddim"  # scheduler of direct sampling
    sampling_steps: int = Field(30, ge=1, le=1000)
    lora: LoraSpec | None = None
    imported: dict | None = None  # written by `lightfield prior import`: sources, conversions, hashes

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

    @field_validator("unet_in_channels")
    @classmethod
    def _known_channels(cls, v: int) -> int:
        if v not in (4, 9):
            raise ValueError(f"unet_in_channels must be 9 (inpainting UNet) or 4 (base UNet), got {v}")
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
