"""The prior interface: one call turns a composite with chrome balls into a pseudo-target.

A prior knows nothing about the light field. The engine renders balls under the current
field, composites them into a frame, tone maps at exposure `ev` and asks the prior what
those balls *should* look like. The returned image is a stop-gradient target.

Implementations:
* core.priors.reprojection.ReprojectionPrior — embedded default, weights-free, classical.
* core.priors.known.KnownRadiancePrior — renders balls from a known radiance function
  (tests; the simulator's OracleSimPrior builds on it).
* core.priors.diffusion.DiffusionPrior — the paper's SD inpainting + depth ControlNet.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import torch

from core.camera import Camera
from core.capture.base import Capture


class PriorError(RuntimeError):
    """A prior cannot be built or cannot answer (missing weights, bad model card, ...)."""


@dataclass
class ProbeGeometry:
    """Where the N chrome balls of one step are, for the frame being composited."""

    centers: torch.Tensor  # [N, 3] world coordinates (metres)
    radii: torch.Tensor  # [N] world radii
    pixels: torch.Tensor  # [N, 2] (u, v) continuous pixel coordinates of the ball centres
    camera: Camera  # camera of this frame (intrinsics + camera-to-world)
    frame_index: int
    time: float  # seconds from the first frame


@dataclass
class PriorRequest:
    """One call's input. `extras` from the engine: "frame_linear" ([H, W, 3] ball-free linear
    frame, so geometric priors composite exactly) and "ball_rays" (core.chrome_ball.BallRays,
    the engine's ball samples); other priors may ignore both."""

    image: torch.Tensor  # [3, H, W] LDR in [0, 1]: the frame with balls composited, tone mapped at ev
    ball_masks: torch.Tensor  # [N, H, W] anti-aliased coverage in [0, 1], mutual occlusion applied
    depth: torch.Tensor  # [H, W] planar depth with the balls composited (ControlNet condition)
    ev: float  # exposure of `image` (<= 0)
    tau: float  # noise level in [0, 1] (diffusion priors); others may ignore it
    steps: int  # denoising steps k = ceil(10 tau) (diffusion priors)
    guidance_scale: float
    probes: ProbeGeometry
    generator: torch.Generator | None = None
    extras: dict = field(default_factory=dict)


@runtime_checkable
class Prior(Protocol):
    name: str

    def bind(self, capture: Capture) -> None:
        """Called once per job before distillation (precompute per-capture state)."""

    def __call__(self, request: PriorRequest) -> torch.Tensor:
        """Return the pseudo-target LDR image [3, H, W] in [0, 1] (same size as request.image).

        Pixels outside the union of ball masks must equal request.image.
        """

    def describe(self) -> dict:
        """JSON-able description recorded in the artefact metadata (name, settings, weights)."""
