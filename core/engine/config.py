"""The engine's configuration as one typed tree (nerfstudio's method configs): an
`EngineConfig` holds the distillation loop's settings (`DistillConfig`), the field
(`FieldConfig`: the default kind plus every kind's settings, so a job may pick another kind)
the priors' settings defaults (each validated by that prior's Config), the tracker's knobs
(`TrackingConfig`, core.tracking.config) and the capture stage's (`CaptureConfig`,
core.capture.config). The named
presets are in core.engine.presets; `with_overrides` derives variants (worker overrides,
benchmarks, tests) without flat knobs.
"""
from __future__ import annotations

import math
import random
from typing import Any, Literal, Mapping

from pydantic import BaseModel, ConfigDict, Field, field_validator

from core.capture.config import CaptureConfig
from core.conventions import DEFAULT_EV_MIN
from core.device import DEVICE_PATTERN
from core.fields import FieldConfig
from core.priors.base import PriorError
from core.priors.registry import prior_settings
from core.tracking.config import TrackingConfig


class DistillConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    iterations: int = Field(300, ge=1)
    n_probes: int = Field(9, ge=1, le=64)
    work_height: int = Field(96, ge=16, description="frames are area-downsampled to this height")
    supersample: int = Field(1, ge=1, le=8, description="ball samples per pixel side (>= 8 across tiny balls anyway)")
    ball_diameter_fraction: float = Field(0.25, gt=0, le=1.0)
    # Probe depth: uniform in [lo, hi] x scene depth at the pixel, i.e. strictly in front of
    # the surface; see core.engine.probes.sample_probes for the near-plane guard.
    probe_depth_fraction: tuple[float, float] = (0.5, 0.95)
    ev_min: float = Field(DEFAULT_EV_MIN, le=0.0)
    ev_sweep_fraction: float = Field(1.0, gt=0, le=1.0, description="ev reaches ev_min after this fraction of steps")
    ev_schedule: Literal["sweep", "uniform"] = Field(
        "sweep",
        description="'sweep' (paper): linear 0 -> ev_min; 'uniform' (the paper's ablation): ev ~ U[ev_min, 0] each "
                    "step",
    )
    guidance_scale: float = 12.5
    tau_max: float = Field(1.0, gt=0.0, le=1.0)
    tau_schedule: Literal["anneal", "authors"] = Field(
        "anneal",
        description="'anneal' (paper): tau_min 1 -> 0 over the run; 'authors': their decay_t_min (floor 0.02, half the "
                    "run)",
    )
    lr: float = Field(5e-3, gt=0)
    lr_min_ratio: float = Field(0.05, ge=0, le=1)
    warmup_steps: int = Field(20, ge=0)
    grad_clip: float = Field(1.0, gt=0)
    adam_betas: tuple[float, float] = (0.9, 0.99)
    l2_weight: float = Field(1.0, ge=0)
    perceptual_weight: float = Field(0.1, ge=0)
    perceptual_net: Literal["alex", "vgg"] = Field(
        "alex", description="LPIPS backbone when LPIPS weights are configured"
    )
    # Radiance supervision (docs/engine.md "Radiance supervision"): priors that declare
    # PriorCapabilities.envmaps answer HDR env maps; the field is then fitted to them directly
    # in log radiance at many random directions per probe instead of through LDR balls.
    supervision: Literal["balls", "envmaps", "auto"] = Field(
        "balls", description="'balls' (paper): the ball-render loop; 'envmaps': fit the prior's HDR env maps "
                             "(needs capabilities.envmaps); 'auto': envmaps when the prior answers them, else balls")
    envmap_frames_per_step: int = Field(1, ge=1, le=16, description="frames (each with its probes) per radiance step")
    envmap_surface_probes: int = Field(
        4, ge=0, le=64, description="probes in front of the scene depth (probe_depth_fraction)"
    )
    envmap_room_probes: int = Field(
        4, ge=0, le=64, description="probes anywhere along camera rays (0.05-0.95 of the depth)"
    )
    envmap_free_probes: int = Field(0, ge=0, le=64, description=(
        "probes anywhere in the scene box that no frame shows inside a surface (core.engine.free_space; priors with "
        "capabilities.envmaps_anywhere): off the camera rays, beside and behind the camera"))
    envmap_camera_probe: bool = Field(True, description="also a probe at the camera centre (where users query)")
    envmap_directions: int = Field(640, ge=1, description="random directions per probe and step")
    envmap_bright_fraction: float = Field(
        0.25, ge=0, le=1, description="share of the directions drawn ~ the target's luminance"
    )
    envmap_height: int = Field(24, ge=4, description="height of the env maps asked from the prior")
    envmap_view_directions: int = Field(0, ge=0, description=(
        "per frame and step: pixel rays of the frame fitted at the camera-centre probe to the prior's view radiance "
        "(the photo at its own resolution; priors with capabilities.view_radiance, needs envmap_camera_probe)"))
    emitters: int = Field(0, ge=0, le=16, description=(
        "small bright sources the radiance loop models as explicit spheres (core.engine.emitter_detection; priors with "
        "view_radiance); 0: none"))
    observed_surfaces: int = Field(0, ge=0, le=1 << 16, description=(
        "points of the frames (with their radiance) the field keeps and looks up along each direction away from "
        "the cameras (core.engine.surface_extraction; priors with view_radiance); 0: none"))
    observed_surfaces_height: int = Field(0, ge=0, le=128, description=(
        "rows of the map the observed surfaces are splatted into per probe; 0: envmap_height (the prior's maps)"))
    emitter_contrast: float = Field(
        50.0, gt=1, description="an emitter's pixels are this many times the frame's median luminance"
    )
    emitter_max_radius: float = Field(
        0.3, gt=0, description="metres: brighter blobs wider than this are left to the network"
    )
    log_floor_fraction: float = Field(
        1e-3, gt=0, description="log(L + floor), floor = this x the frame's mean radiance"
    )
    linear_weight: float = Field(0.1, ge=0, description="weight of the relative linear (energy) term")
    chroma_weight: float = Field(0.0, ge=0, description="extra weight of the log error's colour part (radiance loss)")
    time_tv_weight: float = Field(0.01, ge=0, description=(
        "L1 total variation of the field's time curves (if any: codes, view-detail coefficients, emitters, time gain)"))
    time_gain: bool = Field(False, description=(
        "with radiance supervision, a field with a time input gets a learned log gain per knot (and colour channel) "
        "multiplying its network (core.fields TimeGain): a light that dims the whole room is one number per frame"))
    time_gain_start: float = Field(
        0.0, ge=0, le=1, description="the time gain trains from this fraction of the steps on"
    )
    time_gain_lr_scale: float = Field(10.0, gt=0, description="the time gain's learning rate over the network's")
    fallback: bool = Field(True, description=(
        "replace a field the job's self-check finds misread by the capture's constant map (core.engine.fallback); "
        "off: the field is stored whatever its grade (a test of the loop's mechanics at a few steps)"))
    time_gain_channels: Literal[1, 3] = Field(
        3, description="the time gain's values per knot: 3 (RGB) or 1 (brightness)"
    )
    time_lattice_start: float = Field(
        0.5,
        ge=0,
        le=1,
        description="a field with a time input trains its room lattice (if any) from this fraction of the "
        "steps on, after its time codes have learnt the changes; 1: such a field gets no lattice",
    )
    time_normalisation_frames: int | None = Field(
        None,
        ge=2,
        description="normalise time as if the clip had this many frames (the authors' release: 30); None: over the "
                    "capture",
    )
    # Per-step tensors are small (a few thousand ball samples; a tracker's pair a few thousand
    # pixels): intra-op threads cost more in synchronisation than they gain, and are disastrous on
    # a shared, oversubscribed machine. A worker runs one job per core instead.
    threads: int | None = Field(
        1, ge=1, description="torch intra-op threads for the whole job: capture, tracking, distillation (None: as is)"
    )
    checkpoint_every: int = Field(100, ge=1)
    device: str = Field(
        "auto",
        pattern=DEVICE_PATTERN,
        description="'auto' (CUDA if available, else CPU), 'cpu', 'cuda' or 'cuda:N'; env LIGHTFIELD_DEVICE overrides",
    )

    # ------------------------------------------------------------------ schedules
    def ev_at(self, step: int) -> float:
        """Linear sweep 0 -> ev_min over the first ev_sweep_fraction of the steps, or (ablation)
        a uniform draw in [ev_min, 0] that depends only on the step, so a resumed run repeats it."""
        if self.ev_schedule == "uniform":
            return self.ev_min * random.Random(f"uniform-ev:{step}").random()
        span = max(1, round(self.iterations * self.ev_sweep_fraction) - 1)
        return self.ev_min * min(1.0, step / span)

    def tau_min_at(self, step: int) -> float:
        """tau_min annealed linearly 1 -> 0 over training (tau ~ U[tau_min, tau_max]); 'authors':
        their sds_t_sampling 'decay_t_min', max(0.02, (1 - step / (N // 2)) tau_max)."""
        if self.tau_schedule == "authors":
            return min(self.tau_max, max(0.02, (1.0 - step / max(1, self.iterations // 2)) * self.tau_max))
        return max(0.0, 1.0 - step / max(1, self.iterations - 1))

    @staticmethod
    def steps_for_tau(tau: float) -> int:
        return max(1, math.ceil(10.0 * tau))

    @property
    def envmap_probe_count(self) -> int:
        """Probes per frame of a radiance step (at most: free-space draws can come back fewer)."""
        return (
            self.envmap_surface_probes
            + self.envmap_room_probes
            + self.envmap_free_probes
            + int(self.envmap_camera_probe)
        )

    def uses_envmaps(self, prior_answers_envmaps: bool) -> bool:
        """Whether the loop supervises in radiance (see `supervision`)."""
        if self.supervision == "envmaps" and not prior_answers_envmaps:
            raise ValueError("distill.supervision='envmaps' needs a prior that answers env maps (capabilities.envmaps)")
        return self.supervision == "envmaps" or (self.supervision == "auto" and prior_answers_envmaps)

    def lr_at(self, step: int) -> float:
        """Linear warm-up then cosine decay to lr * lr_min_ratio."""
        if step < self.warmup_steps:
            return self.lr * (step + 1) / self.warmup_steps
        span = max(1, self.iterations - self.warmup_steps)
        p = min(1.0, (step - self.warmup_steps) / span)
        lo = self.lr * self.lr_min_ratio
        return lo + 0.5 * (self.lr - lo) * (1.0 + math.cos(math.pi * p))


class EngineConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = "custom"
    distill: DistillConfig = DistillConfig()
    field: FieldConfig = FieldConfig()  # `kind` is the default a job's params.field may replace
    priors: dict[str, dict[str, Any]] = Field(default_factory=dict, description="prior name -> settings defaults")
    # the tracker's knobs (core.tracking.config): `tracking.direct.search_step_deg=4` is an ablation
    tracking: TrackingConfig = TrackingConfig()
    capture: CaptureConfig = CaptureConfig()  # the capture stage's knobs (core.capture.config)

    @field_validator("priors")
    @classmethod
    def _valid_prior_settings(cls, priors: dict) -> dict:
        try:
            return {name: prior_settings(name, settings).model_dump() for name, settings in priors.items()}
        except PriorError as exc:  # a validation error of this config, naming the prior and the key
            raise ValueError(str(exc)) from None

    def with_overrides(self, overrides: Mapping[str, Any]) -> "EngineConfig":
        """A validated copy with `overrides` merged in, as nested mappings ({"distill":
        {"iterations": 50}}) or dotted keys ({"distill.iterations": 50, "field.mlp.width": 64})."""
        return EngineConfig.model_validate(_merged(self.model_dump(), _nested(overrides)))

    def with_field_kind(self, kind: str | None) -> "EngineConfig":
        """The same config training a field of `kind` (None: the default kind)."""
        return self if kind is None else self.model_copy(update={"field": self.field.with_kind(kind)})

    def prior_settings(self, name: str) -> dict[str, Any]:
        """The settings defaults of prior `name` ({} when the config has none)."""
        return dict(self.priors.get(name, {}))


def _nested(overrides: Mapping[str, Any]) -> dict:
    out: dict = {}
    for key, value in overrides.items():
        *path, last = str(key).split(".")
        node = out
        for part in path:
            node = node.setdefault(part, {})
        node[last] = _nested(value) if isinstance(value, Mapping) else value
    return out


def _merged(base: dict, changes: dict) -> dict:
    out = dict(base)
    for key, value in changes.items():
        out[key] = _merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out
