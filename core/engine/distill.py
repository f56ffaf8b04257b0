"""The distillation loop: optimise a light field L(x, t, d) against a prior over chrome balls
(the paper's §3.2), one `Trainer.step` at a time, with checkpoints, progress and cancellation.

One torch.Generator drives every random choice (frames, probes, tau, the prior's noise), so a
seed reproduces a run and a checkpoint (which stores the generator state) resumes it exactly.
"""
from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass, field as dc_field
from pathlib import Path

import torch

from core.camera import Camera
from core.capture.base import Capture
from core.device import resolve_device
from core.engine.checkpoints import fingerprint, load_checkpoint, save_checkpoint
from core.engine.config import EngineConfig
from core.engine.emitter_detection import EmitterSources, find_emitters
from core.engine.free_space import FreeSpaceSampler
from core.engine.losses import PerceptualLoss, perceptual_description
from core.engine.progress import Reporter, StageTimer
from core.engine.radiance import frame_floors
from core.engine.scene import scene_bounds
from core.engine.surface_extraction import SurfacePoints, observed_surfaces
from core.engine.trainer import Trainer
from core.engine.warm_start import warm_start
from core.fields import FieldConfig, LightField, SceneBounds, build_field
from core.fields.kinds.base import EMITTER_PIXEL_SIGMA
from core.priors.base import Prior

MAX_TIME_KNOTS = 256
MAX_VIEW_ANCHORS = 64  # camera centres kept as view-detail anchors (evenly over the frames)


@dataclass
class DistillResult:
    field: LightField
    losses: list[float]
    timings: StageTimer
    iterations: int
    resumed_from: int = 0
    stats: dict = dc_field(default_factory=dict)


def distill(
    capture: Capture,
    prior: Prior,
    config: EngineConfig,
    uses_time: bool,
    *,
    seed: int = 0,
    reporter: Reporter | None = None,
    checkpoint_dir: Path | None = None,
    timings: StageTimer | None = None,
    bounds: SceneBounds | None = None,
    init_state: dict[str, torch.Tensor] | None = None,
) -> DistillResult:
    """Optimise a field of `config.field` on `capture` (already at working resolution; prior
    already bound) with the loop settings `config.distill`.

    The field, the frames and the per-step tensors live on `resolve_device(cfg.device)`; the
    random choices (one CPU generator) and the field's initialisation stay on CPU, so a seed
    gives the same run on any device up to floating-point differences of the device's kernels.
    `init_state`: an earlier field's state_dict to start from (core.engine.warm_start: a live
    session's next version) instead of the fresh initialisation."""
    cfg = config.distill
    reporter = reporter or Reporter(None, None)
    timings = timings or StageTimer()
    device = resolve_device(cfg.device)
    torch.manual_seed(seed)  # field initialisation (on CPU, then moved)
    gen = torch.Generator().manual_seed(seed)
    field_cfg = with_view_detail(
        with_time_knots(lattice_for_time(config.field.with_time(uses_time), cfg), capture.num_frames), capture
    )
    bounds = bounds or scene_bounds(capture, cfg.time_normalisation_frames)
    use_envmaps = cfg.uses_envmaps(prior.capabilities.envmaps)
    sources = emitter_sources(capture, prior, cfg, bounds, uses_time) if use_envmaps else None
    if sources is not None:
        field_cfg = field_cfg.model_copy(update={
            "emitter_count": sources.count, "emitter_knots": sources.intensity.shape[1],
            "emitter_sigma_floor": EMITTER_PIXEL_SIGMA * math.pi / cfg.envmap_height})
    with timings("surfaces"):
        surfaces = surface_points(capture, prior, cfg, bounds, uses_time, sources) if use_envmaps else None
    if surfaces is not None:
        field_cfg = field_cfg.model_copy(
            update={
                "surface_points": surfaces.count,
                "surface_knots": surfaces.knots,
                "surface_height": cfg.observed_surfaces_height or cfg.envmap_height,
            }
        )
    if cfg.time_gain and field_cfg.uses_time and use_envmaps:  # the ball loop (the paper's path) keeps its field
        field_cfg = field_cfg.model_copy(update={"time_gain_knots": time_knots(capture.num_frames),
                                                 "time_gain_channels": cfg.time_gain_channels})
    field = build_field(field_cfg, bounds)
    if sources is not None:
        field.emitters.set_sources(sources.centres, sources.radii, sources.intensity)
    warm = warm_start(field, init_state) if init_state is not None else None
    field = field.to(device)
    opt = torch.optim.Adam(parameter_groups(field, cfg.time_gain_lr_scale), lr=cfg.lr, betas=cfg.adam_betas)
    run_fingerprint = fingerprint(capture, cfg, field_cfg, seed, prior)

    start, losses = 0, []
    if checkpoint_dir is not None:
        restored = load_checkpoint(Path(checkpoint_dir), field, opt, gen, run_fingerprint)
        if restored is not None:
            start, losses = restored
    frames_lin = capture.linear()  # one radiance scale: each frame's stated exposure removed
    trainer = Trainer(capture, frames_lin.to(device), capture.depth.to(device), prior, field, opt,
                      cfg, gen, PerceptualLoss(cfg.perceptual_net), timings, device,
                      use_envmaps=use_envmaps, floors=frame_floors(frames_lin, cfg.log_floor_fraction),
                      view_rays=view_rays(capture, cfg, prior) if use_envmaps else None,
                      free_space=free_space_sampler(capture, bounds, cfg, prior) if use_envmaps else None)
    lattice_from = lattice_start_step(field_cfg, cfg)
    reporter.begin(start)
    reporter.check_cancel()  # then once per step, in reporter.step (a store query in the worker)
    with torch_threads(cfg.threads):
        for step in range(start, cfg.iterations):
            if field.room_lattice is not None:  # from the step alone, so a resumed run repeats it
                field.room_lattice.requires_grad_(step >= lattice_from)
            if field.time_gain is not None:
                field.time_gain.requires_grad_(step >= math.ceil(cfg.time_gain_start * cfg.iterations))
            losses.append(trainer.step(step))
            if checkpoint_dir is not None and (step + 1) % cfg.checkpoint_every == 0 and step + 1 < cfg.iterations:
                with timings("checkpoint"):
                    save_checkpoint(Path(checkpoint_dir), field, opt, gen, step + 1, losses, run_fingerprint)
            reporter.step(step + 1, cfg.iterations, losses[-1])
    field.eval()
    if surfaces is not None:  # only now: during the distillation the network learns every direction
        with timings("surfaces"):
            field.surfaces.set_surfaces(surfaces.points, surfaces.colors)
    return DistillResult(
        field.cpu(),
        losses,
        timings,
        cfg.iterations,
        resumed_from=start,
        stats={
            "field_config": field_cfg.model_dump(),
            "perceptual": perceptual_description(cfg.perceptual_net),
            "device": str(device),
            "supervision": "envmaps" if use_envmaps else "balls",
            "emitters": sources.describe() if sources is not None else [],
            "surfaces": surfaces.describe() if surfaces is not None else None,
            "warm_start": warm.describe() if warm is not None else None,
        },
    )


def emitter_sources(capture: Capture, prior: Prior, cfg, bounds: SceneBounds, uses_time: bool) -> EmitterSources | None:
    """The capture's small bright sources (core.engine.emitter_detection) when the config asks for
    emitters and the prior gives its linear view radiance (clip rule applied), else None; one
    intensity knot per frame (MAX_TIME_KNOTS at most) for a field with a time input."""
    if cfg.emitters == 0 or not prior.capabilities.view_radiance:
        return None
    knots = time_knots(capture.num_frames) if uses_time else 1
    return find_emitters(capture, prior.view_radiance, count=cfg.emitters, contrast=cfg.emitter_contrast,
                         max_radius=cfg.emitter_max_radius, bounds=bounds, knots=knots)


def surface_points(capture: Capture, prior: Prior, cfg, bounds: SceneBounds, uses_time: bool,
                   emitters: EmitterSources | None) -> SurfacePoints | None:
    """The observed surfaces the field keeps (core.engine.surface_extraction; without the emitters' lamps)
    when the config asks for them and the prior gives its linear view radiance, else None."""
    if cfg.observed_surfaces == 0 or not prior.capabilities.view_radiance:
        return None
    return observed_surfaces(capture, prior.view_radiance, bounds, max_points=cfg.observed_surfaces,
                             uses_time=uses_time, knots=time_knots(capture.num_frames), emitters=emitters)


# The emitters' few parameters (log intensities, visibility gates) are each fitted by a fraction
# of the steps (one knot per frame): a larger step lets them move the decade or so the prior asks.
EMITTER_LR_SCALE = 10.0


def parameter_groups(field: LightField, time_gain_lr_scale: float = 1.0) -> list[dict]:
    """Adam groups: the emitters' parameters at EMITTER_LR_SCALE x the rate, the time gain at
    `time_gain_lr_scale` x, the rest at 1x (`lr_scale`, applied by Trainer._optimise)."""
    emitter = [p for n, p in field.named_parameters() if n.startswith("emitters.")]
    gain = [p for n, p in field.named_parameters() if n.startswith("time_gain.")]
    rest = [p for n, p in field.named_parameters() if not n.startswith(("emitters.", "time_gain."))]
    return (
        [{"params": rest, "lr_scale": 1.0}]
        + ([{"params": emitter, "lr_scale": EMITTER_LR_SCALE}] if emitter else [])
        + ([{"params": gain, "lr_scale": time_gain_lr_scale}] if gain else [])
    )


def view_rays(capture: Capture, cfg, prior: Prior) -> torch.Tensor | None:
    """Camera-frame unit rays [H*W, 3] through every pixel centre (one set: all frames share
    the intrinsics; the trainer rotates the rows it draws by the frame's pose) when the
    camera-centre probe is fitted to the prior's view radiance (distill.envmap_view_directions),
    else None."""
    if not (cfg.envmap_view_directions and cfg.envmap_camera_probe and prior.capabilities.view_radiance):
        return None
    return Camera(capture.intrinsics, torch.eye(4, dtype=torch.float64)).pixel_rays()[1].reshape(-1, 3)


def with_view_detail(field_cfg: FieldConfig, capture: Capture) -> FieldConfig:
    """The field's view detail bound to the capture: its distinct camera centres
    (MAX_VIEW_ANCHORS at most, evenly over the frames) as anchors and, for a field with a time
    input, one time knot per frame (MAX_TIME_KNOTS at most) for the detail's time-varying part.
    A field with a time input and `view_detail_time_rank` 0 gets none: a static detail would
    hold the frames' average fine structure where the lighting changes (measured: a bright
    patch in the photo that switched off stayed 8x too bright at the camera; docs/engine.md)."""
    if not field_cfg.view_detail_heights:
        return field_cfg
    if field_cfg.uses_time and field_cfg.view_detail_time_rank == 0:
        return field_cfg.model_copy(update={"view_detail_heights": (), "view_anchors": ()})
    frames = capture.spread_frames(MAX_VIEW_ANCHORS)
    centres = torch.unique(capture.poses[frames, :3, 3].double(), dim=0)  # a static camera: one anchor
    knots = time_knots(capture.num_frames)
    return field_cfg.with_view_anchors(centres.tolist()).model_copy(update={"view_detail_time_knots": knots})


def with_time_knots(field_cfg: FieldConfig, num_frames: int) -> FieldConfig:
    """One time-code knot per frame (MAX_TIME_KNOTS at most) when the field's kind encodes time
    with learned codes; the config unchanged otherwise."""
    section = field_cfg.section()
    if not field_cfg.uses_time or getattr(section, "time_encoding", None) != "codes":
        return field_cfg
    return field_cfg.with_section(time_knots=time_knots(num_frames))


def free_space_sampler(capture: Capture, bounds: SceneBounds, cfg, prior: Prior) -> FreeSpaceSampler | None:
    """The sampler of the probes off the camera rays, when the loop asks for them and the prior
    answers anywhere (`PriorCapabilities.envmaps_anywhere`); else None."""
    if not cfg.envmap_free_probes or not prior.capabilities.envmaps_anywhere:
        return None
    return FreeSpaceSampler.for_capture(capture, bounds)


def lattice_for_time(field_cfg: FieldConfig, cfg) -> FieldConfig:
    """A field with a time input keeps its room lattice unless `cfg.time_lattice_start` is 1.
    The lattice has no time input, so trained from the first step it holds the average of a
    light that switches and the time codes must undo it (a switch's on/off contrast at 200
    steps 3.5 with it vs 8.9 without, one-off runs of tests/test_engine_distill.py's; a static
    stretch at the camera drifted 5 %); `lattice_start_step` trains it only once the codes
    have learnt the changes (measured: docs/engine.md, "The lattice and time")."""
    if field_cfg.uses_time and field_cfg.room_lattice and cfg.time_lattice_start >= 1.0:
        return field_cfg.model_copy(update={"room_lattice": ()})
    return field_cfg


def lattice_start_step(field_cfg: FieldConfig, cfg) -> int:
    """The first step at which the room lattice trains: 0 for a field without a time input,
    else `time_lattice_start` of the steps (before it the lattice is frozen at zero)."""
    return math.ceil(cfg.time_lattice_start * cfg.iterations) if field_cfg.uses_time else 0


def time_knots(num_frames: int) -> int:
    """Knots of every learned time curve (codes, view detail, emitters): one per frame, between 2
    and MAX_TIME_KNOTS."""
    return max(2, min(int(num_frames), MAX_TIME_KNOTS))


@contextmanager
def torch_threads(n: int | None):
    """torch's intra-op threads set to `n` (None: left as is) for the block."""
    old = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)
