"""Inference profiles: which conventions the diffusion prior follows when it computes a target.

* `paper` -- the paper's text (§3.1-3.2) as this project implemented it first; the default.
* `seed` -- the authors' released code (ORionTMT/Sig25_4DLighting: Lighting/sds_utils.py
  `PipeSDS21.loss_sds_image` + `noise_predict`, Lighting/pipeline_utils.py
  `custom_prepare_mask_latents` + `rescale_noise_cfg`, Lighting/sds_scheduler.py
  `DDIMSchedulerSDS`, SDS/multiball_sds.py `sds_loop` + `project_multiball`), read and
  re-implemented in core/priors/diffusion/seed.py. The six deviations from `paper`:

  | | paper | seed |
  |---|---|---|
  | 1 masked-image input | frame with the ball cells blanked | the clean ball-free frame |
  | 2 guidance | plain CFG | CFG then rescale, phi = 1.0 |
  | 3 ControlNet depth | robust 1-99 % inverse depth of the composite | min-max disparity, balls (1/z)^(1/2.4), 8-bit |
  | 4 canvas | card pixel count, aspect kept | squashed to the card resolution |
  | 5 sub-steps | k = ceil(10 tau) >= 1, trailing spacing | t = int(T tau), k = round(10 tau), k <= 1 -> 5, linspace
  over the T-step grid |
  | 6 mask / VAE | max-pooled binary mask, posterior mode | bilinear (soft) latent mask, posterior sample |

  plus: no latent blending after the last sub-step (its background is the model's), the
  generated pixels replace the ball pixels outright (binary mask) instead of a coverage
  blend, and guidance applies when g > 1 (ours when g != 1).
* `diffusionlight` -- the `paper` denoiser with DiffusionLight's input conventions:
  letterboxed square canvas (`pil_square_image`) and its depth encoding (min-max
  disparity, ball pixels nearest). Normal-map ControlNets use the `normals` encoding in
  every profile.

The profile is part of the prior's configuration, chosen per job (`prior_profile`) or taken
from the model card, and recorded in the artefact through `DiffusionPrior.describe()`.
"""
from __future__ import annotations

from typing import Literal, get_args

from pydantic import BaseModel, ConfigDict, Field

from core.priors.base import PriorError

ProfileName = Literal["paper", "seed", "diffusionlight"]  # the keys of PROFILES (checked below)


class InferenceProfile(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    name: ProfileName
    canvas: Literal["keep_aspect", "squash", "letterbox"]
    depth_encoding: Literal["robust_inverse_depth", "authors_disparity", "diffusionlight_nearest"]
    schedule: Literal["trailing", "authors"] = Field(
        description="'trailing': our partial DDIM (paper); 'authors': the released loss_sds_image loop (seed.py)")
    masked_image: Literal["blank_balls", "clean_frame"]
    latent_mask: Literal["max_pool", "bilinear"]
    vae_latents: Literal["mode", "sample"]
    cfg_rescale: float = Field(0.0, ge=0.0, le=1.0)
    paste: Literal["coverage", "binary"] = "coverage"


PROFILES: dict[str, InferenceProfile] = {
    "paper": InferenceProfile(
        name="paper",
        canvas="keep_aspect",
        depth_encoding="robust_inverse_depth",
        schedule="trailing",
        masked_image="blank_balls",
        latent_mask="max_pool",
        vae_latents="mode",
    ),
    "seed": InferenceProfile(
        name="seed",
        canvas="squash",
        depth_encoding="authors_disparity",
        schedule="authors",
        masked_image="clean_frame",
        latent_mask="bilinear",
        vae_latents="sample",
        cfg_rescale=1.0,
        paste="binary",
    ),
    "diffusionlight": InferenceProfile(
        name="diffusionlight",
        canvas="letterbox",
        depth_encoding="diffusionlight_nearest",
        schedule="trailing",
        masked_image="blank_balls",
        latent_mask="max_pool",
        vae_latents="mode",
    ),
}

assert tuple(PROFILES) == get_args(ProfileName), "PROFILES and ProfileName list the same profiles"


def get_profile(name: str) -> InferenceProfile:
    if name not in PROFILES:
        raise PriorError(f"unknown inference profile {name!r}; choose one of {', '.join(PROFILES)}")
    return PROFILES[name]
