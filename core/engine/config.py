"""Distillation settings and the three presets (draft / standard / paper).

`paper` is the paper's §3.2 setup (GPU): MLP 6x256, N = 9 probes, ev 0 -> -5, tau_min
annealed 1 -> 0, k = ceil(10 tau), guidance 12.5, Adam + warm-up + cosine LR, grad clipping.
`draft` and `standard` keep the same loop but cut what CPU time pays for: the working frame
resolution (the ball is 1/4 of the frame, so this is the ball resolution), iterations, and a
narrower MLP (same encodings, 96 x 4 for draft, 128 x 6 for standard). At equal steps a
narrow MLP recovered a known field about as well as the 6 x 256 one and clearly better than
the trunk+head field (see docs/engine.md). Wall times are measured by `bench/presets.py`.

`seed` is the loop of the authors' released code (ORionTMT/Sig25_4DLighting run_video_demo.py
+ SDS/multiball_sds.py `sds_loop`), to pair with the diffusion prior's `seed` profile: EV
fixed at 0 (their sweep is commented out), loss LPIPS-VGG + 0.05 MSE in [-1, 1] units
(= 0.2 x our [0, 1] masked MSE; SSIM stands in for LPIPS unless LPIPS-VGG weights are
configured, see losses.py), time normalised as if the clip had 30 frames (t_n = 2 f / 29 - 1),
PE degree 6 for time, 20 steps, lr 2e-3 -> 2e-4 with 10 % warm-up, guidance 12.5, and their
`decay_t_min` noise schedule (tau ~ U[max(0.02, (1 - i / (N // 2)) 0.98), 0.98]).
"""
from __future__ import annotations

import math
import random
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from core.conventions import DEFAULT_EV_MIN
from core.device import DEVICE_ENV, DEVICE_PATTERN, DeviceError, resolve_device  # noqa: F401  (re-exported)


class DistillConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = "custom"
    iterations: int = Field(300, ge=1)
    n_probes: int = Field(9, ge=1, le=64)
    work_height: int = Field(96, ge=16, description="frames are area-downsampled to this height")
    supersample: int = Field(1, ge=1, le=8, description="ball samples per pixel side (>= 8 across tiny balls anyway)")
    ball_diameter_fraction: float = Field(0.25, gt=0, le=1.0)
    # Probe depth: uniform in [lo, hi] x scene depth at the pixel, i.e. strictly in front of
    # the surface; see distill.sample_probes for the near-plane guard.
    probe_depth_fraction: tuple[float, float] = (0.5, 0.95)
    ev_min: float = Field(DEFAULT_EV_MIN, le=0.0)
    ev_sweep_fraction: float = Field(1.0, gt=0, le=1.0, description="ev reaches ev_min after this fraction of steps")
    ev_schedule: Literal["sweep", "uniform"] = Field(
        "sweep", description="'sweep' (paper): linear 0 -> ev_min; 'uniform' (the paper's ablation): ev ~ U[ev_min, 0] each step")
    guidance_scale: float = 12.5
    tau_max: float = Field(1.0, gt=0.0, le=1.0)
    tau_schedule: Literal["anneal", "authors"] = Field(
        "anneal", description="'anneal' (paper): tau_min 1 -> 0 over the run; 'authors': their decay_t_min (floor 0.02, half the run)")
    lr: float = Field(5e-3, gt=0)
    lr_min_ratio: float = Field(0.05, ge=0, le=1)
    warmup_steps: int = Field(20, ge=0)
    grad_clip: float = Field(1.0, gt=0)
    adam_betas: tuple[float, float] = (0.9, 0.99)
    l2_weight: float = Field(1.0, ge=0)
    perceptual_weight: float = Field(0.1, ge=0)
    perceptual_net: Literal["alex", "vgg"] = Field("alex", description="LPIPS backbone when LPIPS weights are configured")
    time_normalisation_frames: int | None = Field(
        None, ge=2, description="normalise time as if the clip had this many frames (the authors' release: 30); None: over the capture")
    field_t_freqs: int | None = Field(None, ge=0, le=16, description="override the field's PE frequencies for time")
    field_kind: Literal["mlp", "grid", "trunk"] = "mlp"
    field_width: int | None = Field(None, ge=4, description="override the field's hidden width")
    field_layers: int | None = Field(None, ge=1, description="override the field's depth")
    # Per-step tensors are small (a few thousand ball samples): intra-op threads cost more in
    # synchronisation than they gain, and are disastrous on a shared, oversubscribed machine.
    threads: int | None = Field(1, ge=1, description="torch intra-op threads during distillation (None: leave as is)")
    checkpoint_every: int = Field(100, ge=1)
    device: str = Field("auto", pattern=DEVICE_PATTERN,
                        description="'auto' (CUDA if available, else CPU), 'cpu', 'cuda' or 'cuda:N'; env LIGHTFIELD_DEVICE overrides")
    prior_env_height: int = Field(32, ge=8, description="reprojection prior's splat resolution")

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

    def lr_at(self, step: int) -> float:
        """Linear warm-up then cosine decay to lr * lr_min_ratio."""
        if step < self.warmup_steps:
            return self.lr * (step + 1) / self.warmup_steps
        span = max(1, self.iterations - self.warmup_steps)
        p = min(1.0, (step - self.warmup_steps) / span)
        lo = self.lr * self.lr_min_ratio
        return lo + 0.5 * (self.lr - lo) * (1.0 + math.cos(math.pi * p))


PRESETS: dict[str, DistillConfig] = {
    # CPU: ~1 min for a 20-frame 192x144 clip on 2 cores (bench/presets.py)
    "draft": DistillConfig(name="draft", iterations=400, n_probes=9, work_height=72, lr=5e-3,
                           warmup_steps=15, field_kind="mlp", field_width=96, field_layers=4, checkpoint_every=50,
                           prior_env_height=24),
    # CPU: a 100-frame 320x240 clip in a few minutes
    "standard": DistillConfig(name="standard", iterations=1000, n_probes=9, work_height=120, lr=5e-3,
                              warmup_steps=30, field_kind="mlp", field_width=128, field_layers=4, checkpoint_every=100,
                              prior_env_height=32),
    # The paper's settings (GPU): full resolution ball crops, MLP 6 x 256
    "paper": DistillConfig(name="paper", iterations=3000, n_probes=9, work_height=512, supersample=2,
                           lr=1e-3, warmup_steps=100, field_kind="mlp", checkpoint_every=250,
                           prior_env_height=64, threads=None),
    # The authors' released loop (module docstring); pair with the diffusion prior's `seed` profile
    "seed": DistillConfig(name="seed", iterations=20, n_probes=9, work_height=512, supersample=2,
                          lr=2e-3, lr_min_ratio=0.1, warmup_steps=2, field_kind="mlp", checkpoint_every=250,
                          prior_env_height=64, threads=None, ev_min=0.0, l2_weight=0.2, perceptual_weight=1.0,
                          perceptual_net="vgg", guidance_scale=12.5, tau_max=0.98, tau_schedule="authors",
                          time_normalisation_frames=30, field_t_freqs=6),
}


def preset(name: str, **overrides) -> DistillConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    cfg = PRESETS[name]
    return DistillConfig.model_validate({**cfg.model_dump(), **overrides}) if overrides else cfg
