"""The named engine presets, each a whole EngineConfig (draft / standard / paper).

`paper` is the paper's §3.2 setup (GPU): MLP 6x256, N = 9 probes, ev 0 -> -5, tau_min
annealed 1 -> 0, k = ceil(10 tau), guidance 12.5, Adam + warm-up + cosine LR, grad clipping.
`draft` and `standard` keep the same loop but cut what CPU time pays for: the working frame
resolution (the ball is 1/4 of the frame, so this is the ball resolution), iterations, and a
narrower network (same encodings; the MLP 96 x 4 for draft, 128 x 4 for standard, and the
trunk field equally narrowed when a job picks it). At equal steps a narrow MLP recovered a
known field about as well as the 6 x 256 one and clearly better than the trunk+head field
(see docs/engine.md). Wall times are measured by `bench/presets.py`.
"""
from __future__ import annotations

from core.engine.config import DistillConfig, EngineConfig
from core.fields import FieldConfig


def _narrow(width: int, layers: int) -> FieldConfig:
    """The MLP (default kind) and the trunk at `width` x `layers`; the grid as the paper's."""
    return FieldConfig(kind="mlp", mlp={"width": width, "layers": layers},
                       trunk={"trunk_width": width, "trunk_layers": layers})


PRESETS: dict[str, EngineConfig] = {
    # CPU: ~1 min for a 20-frame 192x144 clip on 2 cores (bench/presets.py)
    "draft": EngineConfig(
        name="draft",
        distill=DistillConfig(iterations=400, n_probes=9, work_height=72, lr=5e-3, warmup_steps=15, checkpoint_every=50),
        field=_narrow(96, 4),
        priors={"reprojection": {"env_height": 24}},
    ),
    # CPU: a 100-frame 320x240 clip in a few minutes
    "standard": EngineConfig(
        name="standard",
        distill=DistillConfig(iterations=1000, n_probes=9, work_height=120, lr=5e-3, warmup_steps=30, checkpoint_every=100),
        field=_narrow(128, 4),
        priors={"reprojection": {"env_height": 32}},
    ),
    # The paper's settings (GPU): full resolution ball crops, MLP 6 x 256
    "paper": EngineConfig(
        name="paper",
        distill=DistillConfig(iterations=3000, n_probes=9, work_height=512, supersample=2, lr=1e-3, warmup_steps=100,
                              checkpoint_every=250, threads=None),
        field=FieldConfig(kind="mlp"),
        priors={"reprojection": {"env_height": 64}},
    ),
}


def preset_names() -> tuple[str, ...]:
    return tuple(PRESETS)


def preset(name: str) -> EngineConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return PRESETS[name]
