"""The named engine presets, each a whole EngineConfig (draft / standard / paper / seed).

`paper` is the paper's §3.2 setup (GPU): MLP 6x256, N = 9 probes, ev 0 -> -5, tau_min
annealed 1 -> 0, k = ceil(10 tau), guidance 12.5, Adam + warm-up + cosine LR, grad clipping.
`draft` and `standard` keep the same loop but cut what CPU time pays for: the working frame
resolution (the ball is 1/4 of the frame, so this is the ball resolution), iterations, and a
narrower network (same encodings; the MLP 96 x 4 for draft, 128 x 4 for standard, and the
trunk field equally narrowed when a job picks it). `standard` is the draft with more of each
(1000 steps, a 120-row working frame, the wider network), every mechanism below included: a
preset sold as the better one must not lack what makes the cheaper one accurate. At equal steps a narrow MLP recovered a
known field about as well as the 6 x 256 one and clearly better than the trunk+head field
(see docs/engine.md). Wall times are measured by `bench/presets.py`.

`draft` also supervises in radiance when its prior answers env maps (`supervision="auto"`:
the reprojection, known and oracle priors; the diffusion prior keeps the ball loop): 3 frames
per step, each with 1 probe in front of the depth, 1 along a camera ray, 1 anywhere in the
scene box no frame shows inside a surface (core.engine.free_space) and the camera centre,
256 directions per probe, log-radiance loss, 400 steps (600 scored within 0.01 on the real rooms' photos,
pans and scans, and cost a scan's job 55 s of CPU against 44: docs/engine.md, "Presets"); the camera centre is also
fitted along 256 of the frame's pixel rays to the prior's view radiance, through the field's
view detail (32- and 128-row residual maps anchored at the camera centres, with a rank-4
time part when the lighting changes); small bright sources in view (up to 4 lamps) are explicit
spheres with per-frame intensities (core.engine.emitter_detection); its fields encode time with
learned per-frame codes; and an 8 x 4 x 8 room lattice of 16-row maps (core.fields.components.lattice)
fits the slowly varying colour across the room, which the network alone fits slowly (when the
lighting changes, trained only in the second half of the steps:
core.engine.distill.lattice_start_step). After the distillation the field keeps up to 16384
points of the frames with their radiance (core.engine.surface_extraction, core.fields.components.surfaces) and,
away from the cameras, answers what they cover by splatting them from the probe: parallax
exact, which the network learns slowly. Why and the measurements: docs/engine.md, "Radiance
supervision" (`python -m bench.accuracy_probe`).

`seed` is the loop of the authors' released code (ORionTMT/Sig25_4DLighting run_video_demo.py
+ SDS/multiball_sds.py `sds_loop`), paired with the diffusion prior's `seed` inference profile
(its settings default here; a job's `prior_profile` still wins): EV fixed at 0 (their sweep is
commented out), loss LPIPS-VGG + 0.05 MSE in [-1, 1] units (= 0.2 x our [0, 1] masked MSE;
SSIM stands in for LPIPS unless LPIPS-VGG weights are configured, see losses.py), time
normalised as if the clip had 30 frames (t_n = 2 f / 29 - 1), PE degree 6 for time, 20 steps,
lr 2e-3 -> 2e-4 with 10 % warm-up, guidance 12.5, and their `decay_t_min` noise schedule
(tau ~ U[max(0.02, (1 - i / (N // 2)) 0.98), 0.98]).
"""
from __future__ import annotations

from core.engine.config import DistillConfig, EngineConfig
from core.fields import FieldConfig


def _narrow(width: int, layers: int, view_detail_heights: tuple[int, ...] = (), room_lattice: tuple[int, ...] = (),
            room_lattice_height: int = 8, **encoding) -> FieldConfig:
    """The MLP (default kind) and the trunk at `width` x `layers` (and `encoding` settings); the grid as the paper's."""
    return FieldConfig(kind="mlp", mlp={"width": width, "layers": layers, **encoding},
                       trunk={"trunk_width": width, "trunk_layers": layers, **encoding},
                       view_detail_heights=view_detail_heights, room_lattice=room_lattice,
                       room_lattice_height=room_lattice_height)


def _with_draft_mechanisms(width: int) -> FieldConfig:
    """The draft's field at `width` x 4: view detail, room lattice, learned time codes."""
    return _narrow(width, 4, view_detail_heights=(32, 128), room_lattice=(8, 4, 8), room_lattice_height=16,
                   time_encoding="codes")


DRAFT_DISTILL = DistillConfig(
    iterations=400,
    n_probes=9,
    work_height=72,
    lr=5e-3,
    warmup_steps=15,
    checkpoint_every=50,
    supervision="auto",
    envmap_frames_per_step=3,
    envmap_surface_probes=1,
    envmap_room_probes=1,
    envmap_free_probes=1,
    envmap_directions=256,
    envmap_view_directions=256,
    emitters=4,
    observed_surfaces=16384,
    time_gain=True,
)

PRESETS: dict[str, EngineConfig] = {
    # CPU: ~1 min for a 20-frame 192x144 clip on 2 cores (bench/presets.py)
    "draft": EngineConfig(
        name="draft",
        distill=DRAFT_DISTILL,
        field=_with_draft_mechanisms(96),
        priors={"reprojection": {"env_height": 24}},
    ),
    # the draft's machinery (radiance supervision, emitters, observed surfaces, lattice, view detail)
    # with more steps, a finer working frame and a wider network: what more CPU buys, never less
    "standard": EngineConfig(
        name="standard",
        distill=DRAFT_DISTILL.model_copy(update={"iterations": 1000, "work_height": 120, "warmup_steps": 30,
                                                 "checkpoint_every": 100}),
        field=_with_draft_mechanisms(128),
        priors={"reprojection": {"env_height": 32}},
    ),
    # The paper's settings (GPU): full resolution ball crops, MLP 6 x 256
    "paper": EngineConfig(
        name="paper",
        distill=DistillConfig(
            iterations=3000,
            n_probes=9,
            work_height=512,
            supersample=2,
            lr=1e-3,
            warmup_steps=100,
            checkpoint_every=250,
            threads=None,
        ),
        field=FieldConfig(kind="mlp"),
        priors={"reprojection": {"env_height": 64}},
    ),
    # The authors' released loop (module docstring), at the paper's resolution and field size
    "seed": EngineConfig(
        name="seed",
        distill=DistillConfig(
            iterations=20,
            n_probes=9,
            work_height=512,
            supersample=2,
            lr=2e-3,
            lr_min_ratio=0.1,
            warmup_steps=2,
            checkpoint_every=250,
            threads=None,
            ev_min=0.0,
            l2_weight=0.2,
            perceptual_weight=1.0,
            perceptual_net="vgg",
            guidance_scale=12.5,
            tau_max=0.98,
            tau_schedule="authors",
            time_normalisation_frames=30,
        ),
        field=FieldConfig(kind="mlp", mlp={"t_freqs": 6}, trunk={"t_freqs": 6}),
        priors={"reprojection": {"env_height": 64}, "diffusion": {"profile": "seed"}},
    ),
}


def preset_names() -> tuple[str, ...]:
    return tuple(PRESETS)


def preset(name: str) -> EngineConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return PRESETS[name]
