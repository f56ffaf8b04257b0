"""The methods compared by `lightfield bench`, and how each one answers the held-out queries.

Families (all read the same capture directory through the engine's `load_capture`):
* global     one env map for the whole scene: the prior's estimate at a single centre probe
             (DiffusionLight-style); with the oracle prior it is the TRUE map at that point,
             i.e. the best any single env map can do.
* per-probe  the prior's estimate at each held-out probe independently, no distillation
             (the paper's "Ours-sampling" analogue). Only for priors that declare the envmaps
             capability (core.priors.base.PriorCapabilities; the reprojection prior); with the
             oracle it would be the ground truth itself, so it is not run.
* field      a light field distilled by the engine's `run_job` (mlp = the paper's, grid = the
             paper's "w/o MLP" 3x3x3 ablation, trunk = the engine's faster field), queried
             exactly (`LightFieldArtefact.envmaps`) or through the baked lattice (`core.fields.stored.bake`).

With DiffusionLight's weights (`--diffusionlight-weights`, imported by `lightfield prior
import`; the diffusion prior with the card's `diffusionlight` profile): "diffusionlight"
(global family: DiffusionLight's own direct sampling, one ball at the frame centre, EV
brackets 0/-2.5/-5 merged -- the paper's "DiffusionLight" row) and
"diffusionlight-distilled" (an MLP field distilled from it -- "DiffusionLight-Distilled").

Budgets and ablations are overrides of the draft preset's EngineConfig (dotted keys, e.g.
"distill.n_probes" or "field.mlp.width"): uniform exposure sampling is the engine's
`distill.ev_schedule="uniform"` (ev drawn uniformly in [ev_min, 0] per step instead of the
0 -> ev_min sweep).
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from bench.overrides import knobs_of
from bench.suite.measure import Measurement, measured
from bench.suite.simulated import SERIES_HEIGHT, SuiteData
from core.engine.config import EngineConfig
from core.envmap import resize_envmap

Family = Literal["global", "per-probe", "field"]


@dataclass(frozen=True)
class Method:
    name: str
    family: Family
    group: str  # baseline | paper | budget | ablation | query | upper-bound
    description: str
    prior: str = "reprojection"  # a registered prior (core.priors.registry)
    prior_weights: str | None = None  # local model directory (diffusion prior only)
    field: str | None = None
    overrides: tuple[tuple[str, Any], ...] = ()  # EngineConfig overrides by dotted key
    exposure: Literal["sweep", "uniform"] = "sweep"
    query: Literal["exact", "baked"] = "exact"

    def config(self, base: EngineConfig) -> EngineConfig:
        cfg = base.with_overrides({**dict(self.overrides), "name": self.name, "distill.ev_schedule": self.exposure})
        return cfg.with_field_kind(self.field)

    @property
    def training_key(self) -> tuple:
        """Methods that differ only in the query mode share one distillation."""
        return (self.family, self.prior, self.prior_weights, self.field, self.overrides, self.exposure)

    def describe(self, base: EngineConfig) -> dict:
        summary = config_summary(self.config(base))
        out = {"family": self.family, "group": self.group, "prior": self.prior, "description": self.description}
        if self.family == "field":
            out.update(
                {
                    "field": summary["field_kind"],
                    "iterations": summary["iterations"],
                    "n_probes": summary["n_probes"],
                    "work_height": summary["work_height"],
                    "field_width": summary["field_width"],
                    "field_layers": summary["field_layers"],
                    "exposure": self.exposure,
                    "query": self.query,
                }
            )
        else:
            out.update({"work_height": summary["work_height"], "prior_env_height": summary["prior_env_height"]})
        return out


# width / depth settings of the network field kinds, for the reports
NETWORK_SIZE_KEYS = {"mlp": ("width", "layers"), "trunk": ("trunk_width", "trunk_layers")}


def config_summary(cfg: EngineConfig) -> dict:
    """The flat facts reports show about a distillation config."""
    size = NETWORK_SIZE_KEYS.get(cfg.field.kind)
    section = cfg.field.section()
    return {
        "name": cfg.name,
        "field_kind": cfg.field.kind,
        "field_width": getattr(section, size[0]) if size else None,
        "field_layers": getattr(section, size[1]) if size else None,
        "iterations": cfg.distill.iterations,
        "n_probes": cfg.distill.n_probes,
        "work_height": cfg.distill.work_height,
        "prior_env_height": cfg.prior_settings("reprojection").get("env_height"),
    }


@dataclass(frozen=True)
class Budget:
    """The distillation budgets of one bench mode. `base` is the reference MLP run."""

    base: EngineConfig
    iterations: tuple[int, ...]
    widths: tuple[tuple[int, int], ...]  # (width, layers)
    work_heights: tuple[int, ...]
    probes: tuple[int, ...]


# The paper's ball-render loop, whatever the prior can answer (core.engine.config `supervision`)
_BALLS = (("distill.supervision", "balls"),)


def core_methods(diffusion_weights: str | None = None, diffusionlight_weights: str | None = None) -> list[Method]:
    """Run on every suite: baselines, the paper's field, its grid ablation, the trunk, the
    baked query mode and the oracle upper bounds of the key methods (plus the diffusion
    prior's distilled fields, and DiffusionLight's two rows, when local weights are given)."""
    extra = (
        []
        if diffusion_weights is None
        else [
            Method(
                "mlp-diffusion",
                "field",
                "paper",
                "MLP distilled from the diffusion prior (the paper's full method)",
                field="mlp",
                prior="diffusion",
                prior_weights=str(diffusion_weights),
            ),
            Method(
                "grid-diffusion",
                "field",
                "paper",
                "grid distilled from the diffusion prior",
                field="grid",
                prior="diffusion",
                prior_weights=str(diffusion_weights),
            ),
        ]
    )
    if diffusionlight_weights is not None:
        dl = str(diffusionlight_weights)
        extra += [
            Method(
                "diffusionlight",
                "global",
                "baseline",
                "DiffusionLight direct sampling: one centre ball, EVs 0/-2.5/-5 merged",
                prior="diffusion",
                prior_weights=dl,
            ),
            Method(
                "diffusionlight-distilled",
                "field",
                "baseline",
                "MLP distilled from DiffusionLight (DiffusionLight-Distilled)",
                field="mlp",
                prior="diffusion",
                prior_weights=dl,
            ),
        ]
    return [
        Method(
            "global", "global", "baseline", "one env map: reprojection prior at the scene centre (DiffusionLight-style)"
        ),
        Method(
            "global-oracle",
            "global",
            "upper-bound",
            "one env map: the TRUE map at the scene centre (best single map)",
            prior="oracle",
        ),
        Method(
            "per-probe",
            "per-probe",
            "baseline",
            "reprojection prior at each held-out probe, no distillation (Ours-sampling analogue)",
        ),
        Method("grid", "field", "paper", "3x3x3 grid of env maps distilled (paper's w/o-MLP ablation)", field="grid"),
        Method(
            "mlp",
            "field",
            "paper",
            "MLP field distilled (draft preset: radiance supervision from the prior's env maps)",
            field="mlp",
        ),
        Method(
            "mlp-balls",
            "field",
            "paper",
            "MLP distilled through the paper's ball loop (the path of priors that only paint balls)",
            field="mlp",
            overrides=_BALLS,
        ),
        Method(
            "mlp-baked",
            "field",
            "query",
            "same MLP, queried through the baked 5x5x5(x4) lattice",
            field="mlp",
            query="baked",
        ),
        Method("trunk", "field", "paper", "trunk+head field distilled (engine's faster field)", field="trunk"),
        Method(
            "mlp-oracle",
            "field",
            "upper-bound",
            "MLP distilled from the oracle prior (upper bound of distillation)",
            field="mlp",
            prior="oracle",
        ),
        Method(
            "grid-oracle", "field", "upper-bound", "grid distilled from the oracle prior", field="grid", prior="oracle"
        ),
    ] + extra


def sweep_methods(budget: Budget) -> list[Method]:
    """Budgets of the MLP field and the paper's ablations (reprojection prior)."""
    b = budget.base
    out: list[Method] = []
    mlp = b.field.section("mlp")
    for it in budget.iterations:
        if it != b.distill.iterations:
            out.append(Method(f"mlp-it{it}", "field", "budget", f"MLP, {it} iterations", field="mlp",
                              overrides=(("distill.iterations", it),)))
    for width, layers in budget.widths:
        if (width, layers) != (mlp.width, mlp.layers):
            out.append(
                Method(
                    f"mlp-w{width}x{layers}",
                    "field",
                    "budget",
                    f"MLP {width} wide x {layers} layers",
                    field="mlp",
                    overrides=(("field.mlp.width", width), ("field.mlp.layers", layers)),
                )
            )
    for wh in budget.work_heights:
        if wh != b.distill.work_height:
            out.append(
                Method(
                    f"mlp-res{wh}",
                    "field",
                    "budget",
                    f"MLP, frames at {wh} rows (ball ~{wh // 4} px)",
                    field="mlp",
                    overrides=(("distill.work_height", wh),),
                )
            )
    for n in budget.probes:
        if n != b.distill.n_probes and n != 1:
            out.append(Method(f"mlp-probes{n}", "field", "budget", f"MLP, ball loop, {n} probes per step", field="mlp",
                              overrides=(("distill.n_probes", n),) + _BALLS))
    # The paper's ablations change the ball loop only, so they (and the probe budget) run it
    out.append(
        Method(
            "abl-1probe",
            "field",
            "ablation",
            "MLP, ball loop, one probe per step instead of nine (paper's ablation)",
            field="mlp",
            overrides=(("distill.n_probes", 1),) + _BALLS,
        )
    )
    out.append(Method("abl-uniform-ev", "field", "ablation",
                      "MLP, ball loop, uniform exposure sampling instead of the sweep (paper's ablation)",
                      field="mlp", exposure="uniform", overrides=_BALLS))
    # The draft's own choices on the radiance path (issue 12), each turned off: what each costs
    # and buys at the draft's budget
    out.append(
        Method(
            "abl-no-lattice",
            "field",
            "ablation",
            "MLP, draft without its room lattice (core.fields.components.lattice)",
            field="mlp",
            overrides=(("field.room_lattice", ()),),
        )
    )
    out.append(Method("abl-no-free-probes", "field", "ablation",
                      "MLP, draft without free-space probes (a second surface probe per frame instead)",
                      field="mlp", overrides=(("distill.envmap_free_probes", 0), ("distill.envmap_surface_probes", 2))))
    out.append(
        Method(
            "abl-no-view-fit",
            "field",
            "ablation",
            "MLP, draft without the fit to the photo's pixels at the camera (no view directions, no view detail)",
            field="mlp",
            overrides=(("distill.envmap_view_directions", 0), ("field.view_detail_heights", ())),
        )
    )
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


def _bound_prior(suite: SuiteData, cfg: EngineConfig):
    """The reprojection prior bound to the capture at the working resolution as run_job binds
    it: with the job's temporal decision, so under static lighting a moving camera's requests
    merge viewpoints and a static camera's frames share their exposure evidence (binding it as
    for changing lighting scored a different prior than the one the field is distilled from:
    on `moving-camera` a worse one)."""
    from core.capture.prepare import load_prepared_capture
    from core.capture.temporal import decide_temporal
    from core.engine.params import JobParams
    from core.priors.registry import build_prior

    params = JobParams(**suite.params)
    capture = load_prepared_capture(suite.capture_dir, params=params)
    decision = decide_temporal(capture, params.temporal)
    work = capture.resized(cfg.distill.work_height)
    prior = build_prior("reprojection", cfg.prior_settings("reprojection"))
    prior.bind(work, lighting_changes=decision.uses_time)
    return prior


def run_global(method: Method, suite: SuiteData, base: EngineConfig) -> MethodRun:
    from core.sim.render import render_envmap

    run = MethodRun(method)
    cfg = method.config(base)
    h = suite.eval_height
    with measured() as m:
        if method.prior == "oracle":
            env = render_envmap(suite.scene, suite.global_point, suite.global_time, h)
        elif method.prior == "diffusion":
            env = diffusion_centre_envmap(method, suite, cfg, h)
        else:
            prior = _bound_prior(suite, cfg)
            env = prior.envmaps(torch.tensor([suite.global_point], dtype=torch.float32), suite.global_time,
                                prior.env_height)[0]
    run.prepare = m
    maps = _timed_queries(run, lambda: resize_envmap(env, h), [()] * len(suite.probes))
    run.envmaps = torch.stack(maps)
    small = resize_envmap(env, SERIES_HEIGHT)
    run.series = [small.expand(len(s.times), *small.shape).clone() for s in suite.series]
    if method.prior == "oracle":
        run.extra["note"] = "prepare time is the simulator's ray tracing, not an estimator's cost"
    return run


def diffusion_centre_envmap(method: Method, suite: SuiteData, cfg: EngineConfig, height: int) -> torch.Tensor:
    """DiffusionLight's native setting: one chrome ball at the centre of the frame nearest the
    suite's global time, placed in front of the scene like the engine's probes, inpainted at
    each EV of the bracket and merged to HDR (DiffusionPrior.sample_balls)."""
    from core.capture.prepare import load_prepared_capture
    from core.chrome_ball import composite_depth, place_probe, render_balls
    from core.conventions import median_valid_depth
    from core.device import resolve_device
    from core.priors.base import ProbeGeometry
    from core.priors.registry import build_prior

    prior = build_prior("diffusion", {**cfg.prior_settings("diffusion"), "weights": method.prior_weights},
                        resolve_device(cfg.distill.device))
    work = load_prepared_capture(suite.capture_dir).resized(cfg.distill.work_height)
    i = int(torch.argmin((work.times - suite.global_time).abs()))
    cam = work.camera(i)
    pixel = torch.tensor([work.width / 2.0, work.height / 2.0], dtype=torch.float64)
    d = work.depth[i][work.height // 2, work.width // 2]
    d = float(d) if torch.isfinite(d) and d > 0 else median_valid_depth(work.depth[i])
    centre, radius = place_probe(cam, pixel, 0.7 * d, cfg.distill.ball_diameter_fraction)
    centres, radii = centre[None].float(), torch.tensor([radius], dtype=torch.float32)
    layer = render_balls(cam, centres, radii, lambda dirs, idx: torch.zeros(dirs.shape[0], 3))
    probes = ProbeGeometry(centres, radii, pixel[None].float(), cam, i, float(work.times[i]))
    out = prior.sample_balls(
        work.frames[i].permute(2, 0, 1),
        layer.coverage,
        composite_depth(work.depth[i], layer),
        probes,
        env_height=height,
        background_depth=work.depth[i],
    )
    return out.envmaps[0]


def run_per_probe(method: Method, suite: SuiteData, base: EngineConfig) -> MethodRun:
    run = MethodRun(method)
    cfg = method.config(base)
    with measured() as m:
        prior = _bound_prior(suite, cfg)
    run.prepare = m

    def estimate(x, t, height):
        return prior.envmaps(torch.tensor([x], dtype=torch.float32), float(t), height)[0]

    maps = _timed_queries(run, estimate, [(p.x, p.t, suite.eval_height) for p in suite.probes])
    run.envmaps = torch.stack(maps)
    run.series = [torch.stack([estimate(s.x, t, SERIES_HEIGHT) for t in s.times]) for s in suite.series]
    return run


def distill_artefact(
    method: Method, suite: SuiteData, base: EngineConfig, out_dir: Path
) -> tuple[Path, Measurement, dict]:
    """run_job on the suite's capture directory; returns (artefact dir, measurement, training info)."""

    from core.engine import run_job
    from core.engine.params import JobParams

    cfg = method.config(base)
    prior = None
    if method.prior == "oracle":
        from core.sim.oracle import OracleSimPrior

        prior = OracleSimPrior(suite.scene)
    if method.prior == "diffusion":
        params = JobParams(
            preset="draft", prior="diffusion", prior_weights=method.prior_weights, field=cfg.field.kind, seed=0
        )
    else:
        params = JobParams(preset="draft", prior="reprojection", field=cfg.field.kind, seed=0)
    with measured() as m, knobs_of(cfg):
        result = run_job(suite.capture_dir, None, params, out_dir, prior=prior, config=cfg)
    meta = result.artefact.meta
    training = meta.get("training", {})
    info = {
        "uses_time": meta.get("time", {}).get("uses_time"),
        "temporal_decision": meta.get("temporal"),
        "final_loss": training.get("final_loss"),
        "stage_timings": training.get("stage_timings"),
        "weights_bytes": meta.get("weights", {}).get("bytes"),
    }
    return result.path, m, info


def query_field(run: MethodRun, artefact_dir: Path, suite: SuiteData) -> None:
    """Fill run.envmaps / series / query_ms from an artefact, exactly or through a bake."""
    from core.fields.stored.artefact import LightFieldArtefact

    art = LightFieldArtefact.load(artefact_dir)
    source = art
    if run.method.query == "baked":
        from core.fields.stored.bake import bake

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


def run_method(method: Method, suite: SuiteData, base: EngineConfig, workdir: Path, artefacts: dict) -> MethodRun:
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
