"""Distil a light field L(x, t, d) from a prior over chrome balls (the paper's §3.2).

Each step: pick a frame; sample N stratified probe pixels; place balls in front of the scene
depth there; render ONLY the ball pixels under the current field (field queried at the ball
centre for each reflected direction, at the frame's time); composite into the linear frame;
tone map at ev (sweeping 0 -> ev_min); ask the prior for a stop-gradient pseudo-target;
loss = masked L2 (saturation hinge) + perceptual (LPIPS if configured, else SSIM); Adam with
warm-up + cosine LR and gradient clipping. One torch.Generator drives every random choice
(frames, probes, tau, the prior's noise), so a seed reproduces a run and a checkpoint (which
stores the generator state) resumes it exactly.

`run_job(...)` is the single entry point for the CLI and the Celery worker.
"""
from __future__ import annotations

import hashlib
import json
import math
import time
from contextlib import contextmanager
from dataclasses import dataclass, field as dc_field
from pathlib import Path

import torch

from core.chrome_ball import ball_reflection_rays, composite, composite_depth, place_probe, render_balls
from core.conventions import inverse_tonemap, tonemap, tonemap_unclipped, valid_depth_mask
from core.engine.capture import Capture, load_capture, median_valid_depth
from core.engine.config import DistillConfig, preset, resolve_device
from core.engine.losses import PerceptualLoss, masked_l2, perceptual_description
from core.engine.params import JobParams
from core.engine.progress import Cancelled, CancelCheck, ProgressCallback, Reporter, StageTimer
from core.engine.temporal import TemporalDecision, decide_temporal
from core.fields import FieldConfig, LightField, SceneBounds, build_field, field_preset
from core.priors.base import Prior, PriorRequest, ProbeGeometry

CHECKPOINT_FILE = "checkpoint.safetensors"
CHECKPOINT_META = "checkpoint.json"
BOUNDS_MAX_POINTS = 200_000
LOSS_CURVE_MAX_POINTS = 1000
REPROJECTION_MERGE_VIEWS = 4

__all__ = ["Cancelled", "DistillResult", "distill", "run_job", "sample_probes", "build_field_config"]


@dataclass
class DistillResult:
    field: LightField
    losses: list[float]
    timings: StageTimer
    iterations: int
    resumed_from: int = 0
    stats: dict = dc_field(default_factory=dict)


# ---------------------------------------------------------------------------------------
# Probes
# ---------------------------------------------------------------------------------------
def sample_probes(capture: Capture, frame_index: int, cfg: DistillConfig, gen: torch.Generator):
    """N probe pixels stratified over a grid of cells (one jittered sample per chosen cell)
    and planar depths strictly in front of the scene there.

    Depth ~ U[lo, hi'] x scene depth at the pixel, hi' = min(hi, 1 / (1 + R/z)): R/z is the
    ball's radius-to-depth ratio (fixed by intrinsics and the diameter rule), so the ball's
    far side stays in front of the surface along the ray. Invalid depth at a pixel uses the
    frame's median valid depth. Returns (pixels [N, 2] float64 (u, v), depths [N] float64).
    """
    H, W, n = capture.height, capture.width, cfg.n_probes
    gx = max(1, math.ceil(math.sqrt(n * W / H)))
    gy = max(1, math.ceil(n / gx))
    cells = torch.randperm(gx * gy, generator=gen)[:n]
    jitter = torch.rand(n, 2, generator=gen, dtype=torch.float64)
    u = ((cells % gx).double() + jitter[:, 0]) * (W / gx)
    v = ((cells // gx).double() + jitter[:, 1]) * (H / gy)
    u, v = u.clamp(0.5, W - 0.5), v.clamp(0.5, H - 0.5)
    depth = capture.depth[frame_index]
    d = depth[v.long().clamp(0, H - 1), u.long().clamp(0, W - 1)].double()
    d = torch.where(valid_depth_mask(d), d, torch.full_like(d, median_valid_depth(depth)))
    k = capture.intrinsics
    p = 0.5 * cfg.ball_diameter_fraction * min(H, W)
    r_over_z = p / math.sqrt(k.fx * k.fy + p * p)
    lo, hi = cfg.probe_depth_fraction
    hi = min(hi, 1.0 / (1.0 + r_over_z))
    lo = min(lo, hi)
    frac = lo + (hi - lo) * torch.rand(n, generator=gen, dtype=torch.float64)
    return torch.stack((u, v), -1), d * frac


# ---------------------------------------------------------------------------------------
# Field construction
# ---------------------------------------------------------------------------------------
def build_field_config(cfg: DistillConfig, kind: str | None, uses_time: bool) -> FieldConfig:
    base = field_preset(kind or cfg.field_kind, uses_time=uses_time)
    upd: dict = {}
    if cfg.field_t_freqs is not None:  # the authors' release: PE degree 6 for time
        for section in ("mlp", "trunk"):
            base = base.model_copy(update={section: getattr(base, section).model_copy(update={"t_freqs": cfg.field_t_freqs})})
    if base.kind == "mlp" and (cfg.field_width or cfg.field_layers):
        layers = cfg.field_layers or base.mlp.layers
        skip = base.mlp.skip_layer if base.mlp.skip_layer and base.mlp.skip_layer <= layers else None
        upd["mlp"] = base.mlp.model_copy(update={"width": cfg.field_width or base.mlp.width, "layers": layers, "skip_layer": skip})
    if base.kind == "trunk" and (cfg.field_width or cfg.field_layers):
        upd["trunk"] = base.trunk.model_copy(update={
            "trunk_width": cfg.field_width or base.trunk.trunk_width,
            "trunk_layers": cfg.field_layers or base.trunk.trunk_layers})
    return FieldConfig.model_validate({**base.model_dump(), **{k: v.model_dump() for k, v in upd.items()}})


def scene_bounds(capture: Capture) -> SceneBounds:
    pts = torch.cat([capture.camera(i).unproject(capture.depth[i]).reshape(-1, 3) for i in _distinct_geometry(capture)])
    if pts.shape[0] > BOUNDS_MAX_POINTS:
        pts = pts[torch.linspace(0, pts.shape[0] - 1, BOUNDS_MAX_POINTS).long()]
    return SceneBounds.from_points(pts, capture.times, capture.poses[:, :3, 3])


def _distinct_geometry(capture: Capture) -> list[int]:
    return [0] if capture.static_camera and capture.num_frames > 0 and _depth_static(capture) else list(range(capture.num_frames))


def _depth_static(capture: Capture) -> bool:
    d = torch.nan_to_num(capture.depth, nan=-1.0)
    return bool((d == d[:1]).all())


# ---------------------------------------------------------------------------------------
# Checkpoints (safetensors + JSON; never pickle)
# ---------------------------------------------------------------------------------------
def _save_checkpoint(ckpt_dir: Path, field: LightField, opt: torch.optim.Optimizer, gen: torch.Generator,
                     step: int, losses: list[float], fingerprint: str) -> None:
    from safetensors.torch import save_file

    ckpt_dir.mkdir(parents=True, exist_ok=True)
    tensors = {f"field.{k}": v.detach().cpu().contiguous() for k, v in field.state_dict().items()}
    sd = opt.state_dict()
    for idx, st in sd["state"].items():
        for key, val in st.items():
            tensors[f"opt.{idx}.{key}"] = torch.as_tensor(val).detach().cpu().clone().contiguous()
    tensors["rng"] = gen.get_state().clone()
    tensors["losses"] = torch.tensor(losses, dtype=torch.float64)
    tmp = ckpt_dir / (CHECKPOINT_FILE + ".tmp")
    save_file(tensors, str(tmp))
    meta = {"step": step, "fingerprint": fingerprint, "param_groups": sd["param_groups"]}
    tmp_meta = ckpt_dir / (CHECKPOINT_META + ".tmp")
    tmp_meta.write_text(json.dumps(meta))
    tmp.replace(ckpt_dir / CHECKPOINT_FILE)
    tmp_meta.replace(ckpt_dir / CHECKPOINT_META)


def _load_checkpoint(ckpt_dir: Path, field: LightField, opt: torch.optim.Optimizer, gen: torch.Generator,
                     fingerprint: str) -> tuple[int, list[float]] | None:
    """Restore a matching checkpoint; returns (step, losses) or None if absent/mismatched."""
    from safetensors.torch import load_file

    f, m = ckpt_dir / CHECKPOINT_FILE, ckpt_dir / CHECKPOINT_META
    if not (f.is_file() and m.is_file()):
        return None
    try:
        meta = json.loads(m.read_text())
        if meta.get("fingerprint") != fingerprint:
            return None
        tensors = load_file(str(f))
    except Exception:  # a corrupt checkpoint is just not resumed from
        return None
    field.load_state_dict({k[len("field."):]: v for k, v in tensors.items() if k.startswith("field.")})
    state: dict = {}
    for k, v in tensors.items():
        if k.startswith("opt."):
            _, idx, key = k.split(".", 2)
            state.setdefault(int(idx), {})[key] = v
    opt.load_state_dict({"state": state, "param_groups": meta["param_groups"]})
    gen.set_state(tensors["rng"])
    return int(meta["step"]), tensors["losses"].tolist()


def _fingerprint(capture: Capture, cfg: DistillConfig, field_cfg: FieldConfig, seed: int, prior: Prior) -> str:
    h = hashlib.sha256()
    h.update(capture.frames.numpy().tobytes()[:: max(1, capture.frames.numel() // 100_000)])
    # the device is not part of it: a checkpoint written on a GPU resumes on CPU and back
    h.update(json.dumps([cfg.model_dump(exclude={"device"}), field_cfg.model_dump(), seed, getattr(prior, "name", "?")],
                        sort_keys=True, default=str).encode())
    return h.hexdigest()[:32]


# ---------------------------------------------------------------------------------------
# The loop
# ---------------------------------------------------------------------------------------
def distill(
    capture: Capture,
    prior: Prior,
    cfg: DistillConfig,
    uses_time: bool,
    *,
    field_kind: str | None = None,
    seed: int = 0,
    reporter: Reporter | None = None,
    checkpoint_dir: Path | None = None,
    timings: StageTimer | None = None,
    bounds: SceneBounds | None = None,
) -> DistillResult:
    """Optimise a field on `capture` (already at working resolution; prior already bound).

    The field, the frames and the per-step tensors live on `resolve_device(cfg.device)`; the
    random choices (one CPU generator) and the field's initialisation stay on CPU, so a seed
    gives the same run on any device up to floating-point differences of the device's kernels."""
    reporter = reporter or Reporter(None, None)
    timings = timings or StageTimer()
    device = resolve_device(cfg.device)
    torch.manual_seed(seed)  # field initialisation (on CPU, then moved)
    gen = torch.Generator().manual_seed(seed)
    field_cfg = build_field_config(cfg, field_kind, uses_time)
    field = build_field(field_cfg, bounds or scene_bounds(capture)).to(device)
    opt = torch.optim.Adam(field.parameters(), lr=cfg.lr, betas=cfg.adam_betas)
    fingerprint = _fingerprint(capture, cfg, field_cfg, seed, prior)

    start, losses = 0, []
    if checkpoint_dir is not None:
        restored = _load_checkpoint(Path(checkpoint_dir), field, opt, gen, fingerprint)
        if restored is not None:
            start, losses = restored
    trainer = _Trainer(capture, inverse_tonemap(capture.frames).to(device), capture.depth.to(device), prior, field, opt,
                       cfg, gen, PerceptualLoss(cfg.perceptual_net), timings, device)
    reporter.begin(start)
    reporter.check_cancel()  # then once per step, in reporter.step (a store query in the worker)
    with _torch_threads(cfg.threads):
        for step in range(start, cfg.iterations):
            losses.append(trainer.step(step))
            if checkpoint_dir is not None and (step + 1) % cfg.checkpoint_every == 0 and step + 1 < cfg.iterations:
                with timings("checkpoint"):
                    _save_checkpoint(Path(checkpoint_dir), field, opt, gen, step + 1, losses, fingerprint)
            reporter.step(step + 1, cfg.iterations, losses[-1])
    field.eval()
    return DistillResult(field.cpu(), losses, timings, cfg.iterations, resumed_from=start,
                         stats={"field_config": field_cfg.model_dump(), "perceptual": perceptual_description(cfg.perceptual_net),
                                "device": str(device)})


@contextmanager
def _torch_threads(n: int | None):
    old = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


@dataclass
class _Trainer:
    """The state one optimisation step needs; `step(k)` runs step k and returns its loss."""

    capture: Capture  # on CPU: probe sampling and geometry are small, sequential work
    frames_lin: torch.Tensor  # [T, H, W, 3] ball-free background radiance at ev 0 (no clip boost), on `device`
    depth: torch.Tensor  # [T, H, W] capture.depth on `device`
    prior: Prior
    field: LightField
    opt: torch.optim.Optimizer
    cfg: DistillConfig
    gen: torch.Generator
    perceptual: PerceptualLoss
    timings: StageTimer
    device: torch.device

    def step(self, step: int) -> float:
        capture, cfg, gen, timings, field = self.capture, self.cfg, self.gen, self.timings, self.field
        i = int(torch.randint(capture.num_frames, (1,), generator=gen))
        ev = cfg.ev_at(step)
        tau_min = cfg.tau_min_at(step)
        tau = float(tau_min + (cfg.tau_max - tau_min) * torch.rand(1, generator=gen, dtype=torch.float64))
        cam = capture.camera(i)
        t = float(capture.times[i])

        with timings("probe_geometry"):
            pixels, depths = sample_probes(capture, i, cfg, gen)
            placed = [place_probe(cam, pixels[n], float(depths[n]), cfg.ball_diameter_fraction) for n in range(cfg.n_probes)]
            centers = torch.stack([c for c, _ in placed])
            radii = torch.tensor([r for _, r in placed], dtype=torch.float32)
            rays = ball_reflection_rays(cam, centers, radii, supersample=cfg.supersample)

        with timings("field_render"):
            dev = self.device
            centers_dev = centers.to(dev)
            t_probes = torch.full((centers.shape[0],), t, device=dev)

            def radiance(directions: torch.Tensor, ball_index: torch.Tensor) -> torch.Tensor:
                # per-probe work (trunk, encodings of x and t) once per ball, not per ball sample
                return field.probe_radiance(centers_dev, t_probes, ball_index.to(dev), directions.to(dev))

            layer = render_balls(cam, centers, radii, radiance, rays=rays)
            comp = composite(self.frames_lin[i], layer)
            pred = tonemap_unclipped(comp, ev).permute(2, 0, 1)
            image = tonemap(comp.detach(), ev).permute(2, 0, 1)
            mask = layer.total_coverage.detach()

        with timings("prior"):
            pd = _prior_device(self.prior)
            probes = ProbeGeometry(centers, radii, pixels.float(), cam, i, t)
            request = PriorRequest(
                image=image.to(pd), ball_masks=layer.coverage.detach().to(pd),
                depth=composite_depth(self.depth[i], layer).to(pd), ev=ev, tau=tau, steps=cfg.steps_for_tau(tau),
                guidance_scale=cfg.guidance_scale, probes=probes, generator=gen,
                extras={"frame_linear": self.frames_lin[i].to(pd), "ball_rays": rays,
                        "depth_background": self.depth[i].to(pd)},
            )
            target = self.prior(request).detach().to(device=pred.device, dtype=pred.dtype)
            target = torch.nan_to_num(target, nan=0.0).clamp(0.0, 1.0)

        with timings("optimisation"):
            pred, target, mask = _crop_to_mask(pred, target, mask, pad=4)
            loss = cfg.l2_weight * masked_l2(pred, target, mask)
            if cfg.perceptual_weight > 0:
                loss = loss + cfg.perceptual_weight * self.perceptual(pred.clamp(0, 1), target, mask)
            for g in self.opt.param_groups:
                g["lr"] = cfg.lr_at(step)
            self.opt.zero_grad(set_to_none=True)
            if torch.isfinite(loss):
                loss.backward()
                torch.nn.utils.clip_grad_norm_(field.parameters(), cfg.grad_clip)
                self.opt.step()
        return float(loss.detach())


def _prior_device(prior: Prior) -> torch.device:
    """Where a prior wants its request tensors: its own `device` attribute if it declares one,
    else CPU. The geometric priors (reprojection, known) keep their point clouds and ball
    geometry on CPU; the diffusion prior moves inputs to its model's device itself."""
    return torch.device(getattr(prior, "device", None) or "cpu")


def _crop_to_mask(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, pad: int):
    """Crop [3,H,W] images and the [H,W] mask to the balls' bounding box plus `pad` pixels
    (the SSIM window's reach), so the loss never touches pixels no ball covers."""
    rows = torch.nonzero(mask.amax(1) > 0)
    cols = torch.nonzero(mask.amax(0) > 0)
    if rows.numel() == 0:
        return pred, target, mask
    r0, r1 = max(int(rows[0]) - pad, 0), min(int(rows[-1]) + pad + 1, mask.shape[0])
    c0, c1 = max(int(cols[0]) - pad, 0), min(int(cols[-1]) + pad + 1, mask.shape[1])
    return pred[:, r0:r1, c0:c1], target[:, r0:r1, c0:c1], mask[r0:r1, c0:c1]


# ---------------------------------------------------------------------------------------
# Job entry point
# ---------------------------------------------------------------------------------------
def _decimate(values: list[float], n: int) -> list[float]:
    if len(values) <= n:
        return [round(v, 6) for v in values]
    idx = torch.linspace(0, len(values) - 1, n).round().long().tolist()
    return [round(values[j], 6) for j in idx]


def run_job(
    input_path,
    depth_path,
    params: JobParams,
    out_dir,
    progress: ProgressCallback | None = None,
    should_cancel: CancelCheck | None = None,
    checkpoint_dir=None,
    prior: Prior | None = None,
    limits=None,
    config: DistillConfig | None = None,
) -> Path:
    """Load the capture, decide time, distil, save the artefact to `out_dir`; returns its path.

    `prior` overrides params.prior (tests, the oracle); `config` overrides the preset."""
    from core.engine.artefact import save_artefact
    from core.priors.registry import build_prior

    t_start = time.perf_counter()
    timings = StageTimer()
    reporter = Reporter(progress, should_cancel)
    cfg = config or preset(params.preset)
    device = resolve_device(cfg.device)  # an unavailable device fails before any work

    reporter.stage("loading", 0.0, "reading input")
    with timings("loading"):
        capture = load_capture(input_path, depth_path, params, limits)
    reporter.stage("temporal", 0.04, "detecting lighting changes")
    with timings("temporal"):
        decision: TemporalDecision = decide_temporal(capture, params.temporal)
    with timings("loading"):
        work = capture.resized(cfg.work_height)

    reporter.stage("point_cloud", 0.07, "building the prior")
    with timings("point_cloud"):
        if prior is None:
            kw = {}
            if params.prior == "reprojection":  # static light + moving camera: pool the views
                merge = 1 if decision.uses_time or capture.static_camera else REPROJECTION_MERGE_VIEWS
                kw = {"env_height": cfg.prior_env_height, "merge_views": merge}
            elif params.prior == "diffusion":
                kw = {"device": str(device), "profile": prior_profile(params)}
            prior = build_prior(params.prior, weights=params.prior_weights, **kw)
        prior.bind(work)
        bounds = normalised_time(scene_bounds(work), cfg, work.fps)
        if hasattr(prior, "points"):  # build the geometry now so its cost is reported here
            for i in _distinct_geometry(work):
                prior.points(i)

    reporter.stage("distill", 0.1, f"{cfg.iterations} steps")
    result = distill(work, prior, cfg, decision.uses_time, field_kind=params.field, seed=params.seed,
                     reporter=reporter, checkpoint_dir=Path(checkpoint_dir) if checkpoint_dir else None,
                     timings=timings, bounds=bounds)

    reporter.stage("saving", 0.98, "writing artefact")
    wall = time.perf_counter() - t_start
    meta = {
        "time": {"t0": float(capture.times[0]), "t1": float(capture.times[-1]), "fps": capture.fps, "uses_time": decision.uses_time},
        "capture": capture.summary(),
        "working_resolution": {"width": work.width, "height": work.height, "intrinsics": work.intrinsics.as_dict()},
        "prior": prior.describe(),
        "temporal": decision.as_dict(),
        "params": params.model_dump(),
        "distill_config": cfg.model_dump(),
        "training": {
            "iterations": result.iterations,
            "resumed_from": result.resumed_from,
            "loss_curve": _decimate(result.losses, LOSS_CURVE_MAX_POINTS),
            "final_loss": result.losses[-1] if result.losses else None,
            "wall_time_s": round(wall, 3),
            "device": result.stats["device"],
            "threads": cfg.threads or torch.get_num_threads(),
            "perceptual": result.stats["perceptual"],
            "stage_timings": timings.as_dict(),
        },
        "simulated": {
            "time_input": decision.uses_time,
            "point_cloud_builds": getattr(prior, "point_cloud_builds", None),
            "camera": "static" if capture.static_camera else "moving",
            "rendered": "ball pixels only (field evaluated at ball centres for reflected directions)",
        },
    }
    with timings("saving"):
        path = save_artefact(out_dir, result.field, meta)
    if checkpoint_dir is not None:
        _clear_checkpoint(Path(checkpoint_dir))
    if progress is not None:
        from core.engine.progress import Progress

        progress(Progress("done", result.iterations, result.iterations, meta["training"]["final_loss"], 1.0, 0.0, str(path)))
    return Path(path)


def prior_profile(params: JobParams) -> str | None:
    """The diffusion prior's inference profile: the job's, else `seed` with the seed preset, else the card's."""
    return params.prior_profile or ("seed" if params.preset == "seed" else None)


def normalised_time(bounds: SceneBounds, cfg: DistillConfig, fps: float) -> SceneBounds:
    """The authors normalise time as if every clip had 30 frames (t_n = 2 f / 29 - 1): the time range
    becomes [t0, t0 + (F - 1) / fps], whatever the capture's length (later frames extrapolate)."""
    if cfg.time_normalisation_frames is None or not fps or fps <= 0:
        return bounds
    from dataclasses import replace

    return replace(bounds, t1=bounds.t0 + (cfg.time_normalisation_frames - 1) / float(fps))


def _clear_checkpoint(ckpt_dir: Path) -> None:
    for name in (CHECKPOINT_FILE, CHECKPOINT_META):
        (ckpt_dir / name).unlink(missing_ok=True)
