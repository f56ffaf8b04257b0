"""The methods compared by `lightfield bench`, and how each one answers the held-out queries.

Families (all read the same capture directory through the engine's `load_capture`):
* global     one env map for the whole scene: the prior's estimate at a single centre probe
             (DiffusionLight-style); with the oracle prior it is the TRUE map at that point,
             i.e. the best any single env map can do.
* per-probe  the prior's estimate at each held-out probe independently, no distillation
             (the paper's "Ours-sampling" analogue). Only for priors that can answer at an
             arbitrary point directly (the reprojection prior's `envmaps`); with the oracle it
             would be the ground truth itself, so it is not run.
* field      a light field distilled by the engine's `run_job` (mlp = the paper's, grid = the
             paper's "w/o MLP" 3x3x3 ablation, trunk = the engine's faster field), queried
             exactly (`LightFieldArtefact.envmaps`) or through the baked lattice (`core.engine.bake`).

With DiffusionLight's weights (`--diffusionlight-weights`, imported by `lightfield prior
import`): "diffusionlight" (global family: DiffusionLight's own direct sampling, one ball at
the frame centre, EV brackets 0/-2.5/-5 merged -- the paper's "DiffusionLight" row) and
"diffusionlight-distilled" (an MLP field distilled from it -- "DiffusionLight-Distilled").

Ablations are `DistillConfig` overrides: e.g. uniform exposure sampling is the engine's
`ev_schedule="uniform"` (ev drawn uniformly in [ev_min, 0] per step instead of the
0 -> ev_min sweep).
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from bench.suite.measure import Measurement, measured
from bench.suite.simulated import SERIES_HEIGHT, SuiteData, nearest_frame
from core.engine.config import DistillConfig
from core.envmap import resize_envmap

Family = Literal["global", "per-probe", "field"]


@dataclass(frozen=True)
class Method:
    name: str
    family: Family
    group: str  # baseline | paper | budget | ablation | query | upper-bound
    description: str
    prior: Literal["reprojection", "oracle", "diffusion", "diffusionlight"] = "reprojection"
    prior_weights: str | None = None  # local model directory (diffusion prior only)
    field: str | None = None
    overrides: tuple[tuple[str, Any], ...] = ()  # DistillConfig overrides
    exposure: Literal["sweep", "uniform"] = "sweep"
    query: Literal["exact", "baked"] = "exact"

    def config(self, base: DistillConfig) -> DistillConfig:
        data = {**base.model_dump(), **dict(self.overrides), "name": self.name}
        if self.field is not None:
            data["field_kind"] = self.field
        data["ev_schedule"] = self.exposure
        return DistillConfig.model_validate(data)

    @property
    def training_key(self) -> tuple:
        """Methods that differ only in the query mode share one distillation."""
        return (self.family, self.prior, self.prior_weights, self.field, self.overrides, self.exposure)

    def describe(self, base: DistillConfig) -> dict:
        cfg = self.config(base)
        out = {"family": self.family, "group": self.group, "prior": self.prior, "description": self.description}
        if self.family == "field":
            out.update({"field": cfg.field_kind, "iterations": cfg.iterations, "n_probes": cfg.n_probes,
                        "work_height": cfg.work_height, "field_width": cfg.field_width, "field_layers": cfg.field_layers,
                        "exposure": self.exposure, "query": self.query})
        else:
            out.update({"work_height": cfg.work_height, "prior_env_height": cfg.prior_env_height})
        return out


@dataclass(frozen=True)
class Budget:
    """The distillation budgets of one bench mode. `base` is the reference MLP run."""

    base: DistillConfig
    iterations: tuple[int, ...]
    widths: tuple[tuple[int, int], ...]  # (width, layers)
    work_heights: tuple[int, ...]
    probes: tuple[int, ...]


def core_methods(diffusion_weights: str | None = None, diffusionlight_weights: str | None = None) -> list[Method]:
    """Run on every suite: baselines, the paper's field, its grid ablation, the trunk, the
    baked query mode and the oracle upper bounds of the key methods (plus the diffusion
    prior's distilled fields when local weights are given)."""
    extra = [] if diffusion_weights is None else [
        Method("mlp-diffusion", "field", "paper", "MLP distilled from the diffusion prior (the paper's full method)", field="mlp",
               prior="diffusion", prior_weights=str(diffusion_weights)),
        Method("grid-diffusion", "field", "paper", "grid distilled from the diffusion prior", field="grid",
               prior="diffusion", prior_weights=str(diffusion_weights)),
    ]
    if diffusionlight_weights is not None:
        dl = str(diffusionlight_weights)
        extra += [
            Method("diffusionlight", "global", "baseline", "DiffusionLight direct sampling: one centre ball, EVs 0/-2.5/-5 merged",
                   prior="diffusionlight", prior_weights=dl),
            Method("diffusionlight-distilled", "field", "baseline", "MLP distilled from DiffusionLight (DiffusionLight-Distilled)",
                   field="mlp", prior="diffusionlight", prior_weights=dl),
        ]
    return [
        Method("global", "global", "baseline", "one env map: reprojection prior at the scene centre (DiffusionLight-style)"),
        Method("global-oracle", "global", "upper-bound", "one env map: the TRUE map at the scene centre (best single map)", prior="oracle"),
        Method("per-probe", "per-probe", "baseline", "reprojection prior at each held-out probe, no distillation (Ours-sampling analogue)"),
        Method("grid", "field", "paper", "3x3x3 grid of env maps distilled (paper's w/o-MLP ablation)", field="grid"),
        Method("mlp", "field", "paper", "MLP field distilled (the paper's method, CPU budget)", field="mlp"),
        Method("mlp-baked", "field", "query", "same MLP, queried through the baked 5x5x5(x4) lattice", field="mlp", query="baked"),
        Method("trunk", "field", "paper", "trunk+head field distilled (engine's faster field)", field="trunk"),
        Method("mlp-oracle", "field", "upper-bound", "MLP distilled from the oracle prior (upper bound of distillation)", field="mlp", prior="oracle"),
        Method("grid-oracle", "field", "upper-bound", "grid distilled from the oracle prior", field="grid", prior="oracle"),
    ] + extra


def sweep_methods(budget: Budget) -> list[Method]:
    """Budgets of the MLP field and the paper's ablations (reprojection prior)."""
    b = budget.base
    out: list[Method] = []
    for it in budget.iterations:
        if it != b.iterations:
            out.append(Method(f"mlp-it{it}", "field", "budget", f"MLP, {it} iterations", field="mlp", overrides=(("iterations", it),)))
    for width, layers in budget.widths:
        if (width, layers) != (b.field_width, b.field_layers):
            out.append(Method(f"mlp-w{width}x{layers}", "field", "budget", f"MLP {width} wide x {layers} layers", field="mlp",
                              overrides=(("field_width", width), ("field_layers", layers))))
    for wh in budget.work_heights:
        if wh != b.work_height:
            out.append(Method(f"mlp-res{wh}", "field", "budget", f"MLP, frames at {wh} rows (ball ~{wh // 4} px)", field="mlp",
                              overrides=(("work_height", wh),)))
    for n in budget.probes:
        if n != b.n_probes and n != 1:
            out.append(Method(f"mlp-probes{n}", "field", "budget", f"MLP, {n} probes per step", field="mlp", overrides=(("n_probes", n),)))
    out.append(Method("abl-1probe", "field", "ablation", "MLP, one probe per step instead of nine (paper's ablation)", field="mlp",
                      overrides=(("n_probes", 1),)))
    out.append(Method("abl-uniform-ev", "field", "ablation", "MLP, uniform exposure sampling instead of the sweep (paper's ablation)",
                      field="mlp", exposure="uniform"))
    return out


# ---------------------------------------------------------------------------------------
# Running a method
# ---------------------------------------------------------------------------------------
@dataclass
class MethodRun:
    method: Method
    envmaps: torch.Tensor | None = None  # [P, H, 2H, 3] at the held-out probes
    series: list[torch.Tensor] = field(default_factory=list)  # aligned with SuiteData.series
    prepare: Measurement = field(default_factory=Measurement)  # distillation / prior set-up
    query_ms: float | None = None  # median wall latency of one held-out env map query
    query_cpu_ms: float | None = None  # median CPU time of the same
    extra: dict = field(default_factory=dict)
    error: str | None = None


def _timed_queries(run: "MethodRun", fn, calls) -> list:
    """Call fn(*args) for each args; record the median wall and CPU milliseconds in `run`."""
    out, wall, cpu = [], [], []
    for args in calls:
        t0, c0 = time.perf_counter(), time.process_time()
        out.append(fn(*args))
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    run.query_ms = 1000.0 * statistics.median(wall) if wall else 0.0
    run.query_cpu_ms = 1000.0 * statistics.median(cpu) if cpu else 0.0
    return out


def _bound_prior(suite: SuiteData, cfg: DistillConfig):
    """The reprojection prior bound to the capture at the working resolution (as run_job does)."""
    from core.engine.capture import load_capture
    from core.priors.reprojection import ReprojectionPrior

    work = load_capture(suite.capture_dir).resized(cfg.work_height)
    prior = ReprojectionPrior(env_height=cfg.prior_env_height)
    prior.bind(work)
    return prior, work


def run_global(method: Method, suite: SuiteData, base: DistillConfig) -> MethodRun:
    from core.sim.render import render_envmap

    run = MethodRun(method)
    cfg = method.config(base)
    h = suite.eval_height
    with measured() as m:
        if method.prior == "oracle":
            env = render_envmap(suite.scene, suite.global_point, suite.global_time, h)
        elif method.prior == "diffusionlight":
            env = diffusionlight_centre_envmap(method, suite, cfg, h)
        else:
            prior, work = _bound_prior(suite, cfg)
            frame = nearest_frame(suite.global_time, work.fps, work.num_frames)
            env = prior.envmaps(torch.tensor([suite.global_point], dtype=torch.float32), frame)[0]
    run.prepare = m
    maps = _timed_queries(run, lambda: resize_envmap(env, h), [()] * len(suite.probes))
    run.envmaps = torch.stack(maps)
    small = resize_envmap(env, SERIES_HEIGHT)
    run.series = [small.expand(len(s.times), *small.shape).clone() for s in suite.series]
    if method.prior == "oracle":
        run.extra["note"] = "prepare time is the simulator's ray tracing, not an estimator's cost"
    return run


def diffusionlight_centre_envmap(method: Method, suite: SuiteData, cfg: DistillConfig, height: int) -> torch.Tensor:
    """DiffusionLight's native setting: one chrome ball at the centre of the frame nearest the
    suite's global time, placed in front of the scene like the engine's probes, inpainted at
    each EV of the bracket and merged to HDR (DiffusionPrior.sample_balls)."""
    from core.chrome_ball import composite_depth, place_probe, render_balls
    from core.engine.capture import load_capture, median_valid_depth
    from core.priors.base import ProbeGeometry
    from core.priors.diffusion import DiffusionPrior

    prior = DiffusionPrior.from_pretrained(method.prior_weights)
    work = load_capture(suite.capture_dir).resized(cfg.work_height)
    i = nearest_frame(suite.global_time, work.fps, work.num_frames)
    cam = work.camera(i)
    pixel = torch.tensor([work.width / 2.0, work.height / 2.0], dtype=torch.float64)
    d = work.depth[i][work.height // 2, work.width // 2]
    d = float(d) if torch.isfinite(d) and d > 0 else median_valid_depth(work.depth[i])
    centre, radius = place_probe(cam, pixel, 0.7 * d, cfg.ball_diameter_fraction)
    centres, radii = centre[None].float(), torch.tensor([radius], dtype=torch.float32)
    layer = render_balls(cam, centres, radii, lambda dirs, idx: torch.zeros(dirs.shape[0], 3))
    probes = ProbeGeometry(centres, radii, pixel[None].float(), cam, i, float(work.times[i]))
    out = prior.sample_balls(work.frames[i].permute(2, 0, 1), layer.coverage, composite_depth(work.depth[i], layer), probes,
                             env_height=height, background_depth=work.depth[i])
    return out.envmaps[0]


def run_per_probe(method: Method, suite: SuiteData, base: DistillConfig) -> MethodRun:
    run = MethodRun(method)
    cfg = method.config(base)
    with measured() as m:
        prior, work = _bound_prior(suite, cfg)
    run.prepare = m

    def estimate(x, t, height):
        frame = nearest_frame(float(t), work.fps, work.num_frames)
        env = prior.envmaps(torch.tensor([x], dtype=torch.float32), frame)[0]
        return resize_envmap(env, height)

    maps = _timed_queries(run, estimate, [(p.x, p.t, suite.eval_height) for p in suite.probes])
    run.envmaps = torch.stack(maps)
    run.series = [torch.stack([estimate(s.x, t, SERIES_HEIGHT) for t in s.times]) for s in suite.series]
    return run


def distill_artefact(method: Method, suite: SuiteData, base: DistillConfig, out_dir: Path) -> tuple[Path, Measurement, dict]:
    """run_job on the suite's capture directory; returns (artefact dir, measurement, training info)."""
    import json

    from core.engine.distill import run_job
    from core.engine.params import JobParams

    cfg = method.config(base)
    prior = None
    if method.prior == "oracle":
        from core.sim.oracle import OracleSimPrior

        prior = OracleSimPrior(suite.scene)
    if method.prior in ("diffusion", "diffusionlight"):
        params = JobParams(preset="draft", prior="diffusion", prior_weights=method.prior_weights, field=cfg.field_kind, seed=0)
    else:
        params = JobParams(preset="draft", prior="reprojection", field=cfg.field_kind, seed=0)
    with measured() as m:
        path = run_job(suite.capture_dir, None, params, out_dir, prior=prior, config=cfg)
    meta = json.loads((Path(path) / "lightfield.json").read_text())
    training = meta.get("training", {})
    info = {
        "uses_time": meta.get("time", {}).get("uses_time"),
        "temporal_decision": meta.get("temporal"),
        "final_loss": training.get("final_loss"),
        "stage_timings": training.get("stage_timings"),
        "weights_bytes": meta.get("weights", {}).get("bytes"),
    }
    return Path(path), m, info


def query_field(run: MethodRun, artefact_dir: Path, suite: SuiteData) -> None:
    """Fill run.envmaps / series / query_ms from an artefact, exactly or through a bake."""
    from core.engine.artefact import LightFieldArtefact

    art = LightFieldArtefact.load(artefact_dir)
    source = art
    if run.method.query == "baked":
        from core.engine.bake import bake

        with measured() as mb:
            source = bake(art)
        run.extra["bake"] = {**mb.as_dict(), "grid": list(source.grid), "times": source.times, "height": source.height}
    ts_ok = art.uses_time

    def one(x, t, height):
        return source.envmaps(torch.tensor([x], dtype=torch.float32), [t] if ts_ok else None, height)[0][0]

    maps = _timed_queries(run, one, [(p.x, p.t, suite.eval_height) for p in suite.probes])
    run.envmaps = torch.stack(maps)
    run.series = []
    for s in suite.series:
        xs = torch.tensor([s.x], dtype=torch.float32).expand(len(s.times), 3)
        ts = s.times.to(torch.float32) if ts_ok else None
        run.series.append(source.envmaps(xs, ts, SERIES_HEIGHT)[0])


def run_method(method: Method, suite: SuiteData, base: DistillConfig, workdir: Path, artefacts: dict) -> MethodRun:
    """Run one method on one suite; exceptions become `run.error` (reported, never hidden).

    `artefacts` maps training keys to (artefact dir, measurement, info) so a baked query
    reuses the exact query's distillation (its prepare time then counts the bake only)."""
    try:
        if method.family == "global":
            return run_global(method, suite, base)
        if method.family == "per-probe":
            return run_per_probe(method, suite, base)
        run = MethodRun(method)
        key = method.training_key
        if key not in artefacts:
            artefacts[key] = distill_artefact(method, suite, base, workdir / f"{suite.name}-{method.name}")
        path, m, info = artefacts[key]
        run.prepare, run.extra = m, dict(info)
        query_field(run, path, suite)
        return run
    except Exception as exc:  # noqa: BLE001 - a failing method is a result, not a crash of the bench
        return MethodRun(method, error=f"{type(exc).__name__}: {exc}")
