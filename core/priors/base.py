"""The prior interface: one call turns a composite with chrome balls into a pseudo-target.

A prior knows nothing about the light field. The engine renders balls under the current
field, composites them into a frame, tone maps at exposure `ev` and asks the prior what
those balls *should* look like. The returned image is a stop-gradient target. What else a
prior can do is declared in `PriorCapabilities`; its settings are its `Config`.

Implementations (registered by name, core.priors.registry):
* reprojection: core.priors.reprojection.ReprojectionPrior — default, weights-free, classical.
* known: core.priors.known.KnownRadiancePrior — renders balls from a known radiance function
  (tests).
* oracle: core.sim.oracle.OracleSimPrior — the simulator's ground truth (benchmarks, tests).
* diffusion: core.priors.diffusion.prior.DiffusionPrior — the paper's SD inpainting + depth
  ControlNet.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import ClassVar

import torch
from pydantic import BaseModel, ConfigDict

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
    frame, so geometric priors composite exactly), "ball_rays" (core.chrome_ball.BallRays,
    the engine's ball samples) and "depth_background" ([H, W] the scene's planar depth without
    the balls, for ControlNet encodings that treat ball pixels apart); priors may ignore them."""

    image: torch.Tensor  # [3, H, W] LDR in [0, 1]: the frame with balls composited, tone mapped at ev
    ball_masks: torch.Tensor  # [N, H, W] anti-aliased coverage in [0, 1], mutual occlusion applied
    depth: torch.Tensor  # [H, W] planar depth with the balls composited (ControlNet condition)
    ev: float  # exposure of `image`: the frame's own (`frame_ev`, 0 unless stated) plus the step's sweep (<= 0)
    tau: float  # noise level in [0, 1] (diffusion priors); others may ignore it
    steps: int  # denoising steps k = ceil(10 tau) (diffusion priors)
    guidance_scale: float
    probes: ProbeGeometry
    generator: torch.Generator | None = None
    extras: dict = field(default_factory=dict)
    frame_ev: float = 0.0  # the exposure the camera took this frame at (a capture's stated per-frame ev)

    @property
    def sweep_ev(self) -> float:
        """The step's exposure relative to the frame as taken (what an exposure-conditioned
        prior is told): `ev` less the frame's own."""
        return float(self.ev) - float(self.frame_ev)


class PriorConfig(BaseModel):
    """Base of every prior's own settings (`Prior.Config`): strict, a misspelt key is an error."""

    model_config = ConfigDict(extra="forbid", frozen=True)


@dataclass(frozen=True)
class PriorCapabilities:
    """What a prior offers beyond the call, declared by its class (the engine reads these flags
    and never probes for methods):

    * frame_geometry: it builds per-frame geometry (`prepare_frame(i)`) that is worth building
      before the loop, so its cost is reported as its own stage;
    * envmaps: it answers linear HDR env maps at probe centres directly
      (`envmaps(centers, time, height)`). With `distill.supervision="auto"` (the draft preset)
      the engine then fits the field to these maps in log radiance instead of rendering balls
      (core.engine.radiance), calling `envmaps` for ~12 probes every step: declare it only
      when an answer costs milliseconds, not a diffusion sampling.
    * envmaps_anywhere: its `envmaps` answers at any point of the scene box, not only in the free
      space a camera saw (the reprojection prior splats whatever the frames saw from anywhere;
      the simulator's oracle refuses points inside furniture). Radiance supervision then also
      fits probes off the camera rays (`distill.envmap_free_probes`, core.engine.free_space).
    * view_radiance: it says what linear radiance it assigns to each frame's own pixels
      (`view_radiance(i)`, [H, W, 3] in the units of its env maps). Radiance supervision then
      also fits the camera-centre probe along the frame's pixel rays at the photo's own
      resolution, which a prior's coarse env maps blur (core.engine.radiance).
    """

    frame_geometry: bool = False
    envmaps: bool = False
    envmaps_anywhere: bool = False
    view_radiance: bool = False


class Prior(ABC):
    """The prior interface. Subclasses are registered by name (`core.priors.registry.register_prior`)
    with their settings class `Config`; `from_config` builds one from its settings."""

    name: ClassVar[str]  # the registry name, set by @register_prior
    Config: ClassVar[type[PriorConfig]] = PriorConfig
    capabilities: ClassVar[PriorCapabilities] = PriorCapabilities()

    @classmethod
    def from_config(cls, config: PriorConfig, device: torch.device | None = None) -> "Prior":
        """A prior from its validated settings; `device` is where the engine trains (priors that
        run a network place it there, the others ignore it)."""
        return cls(**dict(config))

    @property
    def device(self) -> torch.device:
        """Where the prior wants its request tensors (the engine moves them there)."""
        return torch.device("cpu")

    def bind(self, capture: Capture, *, lighting_changes: bool = True) -> None:  # noqa: B027 — an optional hook
        """Called once per job before distillation (precompute per-capture state).
        `lighting_changes` is the engine's temporal decision: False lets a prior pool what
        different frames saw."""

    @abstractmethod
    def __call__(self, request: PriorRequest) -> torch.Tensor:
        """Return the pseudo-target LDR image [3, H, W] in [0, 1] (same size as request.image).

        Pixels outside the union of ball masks must equal request.image.
        """

    @abstractmethod
    def describe(self) -> dict:
        """JSON-able description recorded in the artefact metadata (name, settings, weights)."""

    # -- optional capabilities (see PriorCapabilities) ----------------------------------------
    def prepare_frame(self, frame_index: int) -> None:
        """Build frame `frame_index`'s geometry now (capabilities.frame_geometry)."""
        raise PriorError(f"prior {self.name!r} does not declare frame_geometry")

    def envmaps(self, centers: torch.Tensor, time: float, height: int) -> torch.Tensor:
        """Linear HDR env maps [N, height, 2 height, 3] seen from `centers` [N, 3] (world metres)
        at `time` (seconds from the first frame) (capabilities.envmaps)."""
        raise PriorError(f"prior {self.name!r} cannot answer env maps (capabilities.envmaps is False)")

    def view_radiance(self, frame_index: int) -> torch.Tensor:
        """Linear HDR radiance [H, W, 3] arriving at frame `frame_index`'s camera along its pixel
        rays, at the bound capture's resolution (capabilities.view_radiance)."""
        raise PriorError(f"prior {self.name!r} does not declare view_radiance")
