"""The job entry point, `run_job`, used by the CLI and the Celery worker, in three stages:
capture preparation (core.capture.prepare: load, the one decode of the job, which `on_capture`
lets the caller reuse; track the camera when several frames came without poses, in a
`tracking` stage of its own; paint out transients; estimate exposure), distillation (decide
whether the lighting changes over time, build and bind the prior, distil the field:
core.engine.distill) and the artefact (saved with what the job simulated and what it cost,
`job_metadata`). The result carries the saved artefact in memory, so callers query or bake it
without reading it back."""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import torch

from core.capture.base import Capture
from core.capture.prepare import prepare_capture
from core.capture.temporal import TemporalDecision, decide_temporal
from core.device import resolve_device
from core.engine.checkpoints import clear_checkpoint
from core.engine.config import EngineConfig
from core.engine.distill import DistillResult, distill, torch_threads
from core.engine.fallback import apply_fallback
from core.engine.params import JobParams, ResolvedJob, job_prior_settings, resolve_job  # noqa: F401 (job_prior_settings: re-exported)
from core.engine.progress import CancelCheck, Progress, ProgressCallback, Reporter, StageTimer
from core.engine.scene import distinct_geometry, scene_bounds
from core.engine.self_check import self_check
from core.fields.stored.artefact import LightFieldArtefact, save_artefact
from core.priors.base import Prior
from core.priors.registry import build_prior

LOSS_CURVE_MAX_POINTS = 1000
PriorFactory = Callable[[str, dict, torch.device], Prior]


@dataclass(frozen=True)
class JobResult:
    artefact: LightFieldArtefact  # the saved artefact, in memory (field, lightfield.json, path)

    @property
    def path(self) -> Path:
        return self.artefact.path


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
    config: EngineConfig | None = None,
    overrides: Mapping[str, Any] | None = None,
    prior_factory: PriorFactory = build_prior,
    on_capture: Callable[[Capture], None] | None = None,
    init_state: Mapping[str, torch.Tensor] | None = None,
) -> JobResult:
    """Prepare the capture, decide time, distil, save the artefact to `out_dir`.

    `prior` overrides params.prior (tests, the oracle); `config` overrides the preset
    params.preset, `overrides` changes it (core.engine.params.resolve_job);
    `prior_factory(name, settings, device)` builds the job's prior (the worker's keeps
    weight-loading priors across jobs); `on_capture(capture)` receives the decoded capture at
    full resolution after loading and tracking (the worker's UI preview); `init_state` (an
    earlier field's state_dict) warm-starts the distillation (core.engine.warm_start)."""
    t_start = time.perf_counter()
    timings = StageTimer()
    reporter = Reporter(progress, should_cancel)
    job = resolve_job(params, overrides, config)
    device = resolve_device(job.config.distill.device)  # an unavailable device fails before any work

    # the whole job at distill.threads, tracking included: on a 2-core box a room scan's job took
    # 79 s of CPU with two threads against 49 s with one (docs/engine.md, "Device")
    with torch_threads(job.config.distill.threads):
        capture = _capture_stage(input_path, depth_path, params, limits, reporter, timings, on_capture, job.config)
        run = _distillation_stage(capture, job, prior, prior_factory, device, reporter, timings, checkpoint_dir,
                                  init_state)

    with timings("self_check"):
        quality = self_check(run.result.field, run.work, run.decision.uses_time)
        field, quality = (apply_fallback(run.result.field, quality) if job.config.distill.fallback
                          else (run.result.field, {**quality, "fallback": None}))
    if quality["fallback"]:
        warnings.warn(f"the job's answer is the capture's constant map: {quality['fallback']['reason']}", stacklevel=2)
    reporter.stage("saving", 0.98, "writing artefact")
    meta = job_metadata(capture, run, params, job.config, timings, wall_time_s=time.perf_counter() - t_start)
    meta["quality"] = quality
    meta["time"]["uses_time"] = field.uses_time
    with timings("saving"):
        artefact = save_artefact(out_dir, field, meta)
    if checkpoint_dir is not None:
        clear_checkpoint(Path(checkpoint_dir))
    if progress is not None:
        progress(Progress("done", run.result.iterations, run.result.iterations, meta["training"]["final_loss"], 1.0,
                          0.0, str(artefact.path)))
    return JobResult(artefact)


# progress fraction at which each capture preparation stage starts
CAPTURE_STAGE_PROGRESS = {"loading": 0.0, "tracking": 0.02}


def _capture_stage(input_path, depth_path, params: JobParams, limits, reporter: Reporter, timings: StageTimer,
                   on_capture: Callable[[Capture], None] | None, config) -> Capture:
    """Capture preparation (core.capture.prepare) with the job's tracking and capture settings
    (EngineConfig.tracking, .capture: an override is applied, not just recorded), its warnings
    shown to run_job's caller."""
    prepared = prepare_capture(
        input_path,
        depth_path,
        params,
        limits,
        timed=timings,
        on_stage=lambda name, message: reporter.stage(name, CAPTURE_STAGE_PROGRESS[name], message),
        tracking=config.tracking,
        knobs=config.capture,
    )
    capture = prepared.capture
    for w in capture.warnings:  # after tracking, which may replace assumptions (FOV, room)
        warnings.warn(w, stacklevel=3)
    if on_capture is not None:  # the preview shows the frames as the user took them, passers-by and all
        on_capture(prepared.preview())
    return capture


@dataclass(frozen=True)
class Distillation:
    """What the distillation stage decided and produced."""

    decision: TemporalDecision  # does the lighting change over time
    work: Capture  # the capture at the working resolution
    prior: Prior  # bound to `work`
    result: DistillResult


def _distillation_stage(capture: Capture, job: ResolvedJob, prior: Prior | None, prior_factory: PriorFactory,
                        device: torch.device, reporter: Reporter, timings: StageTimer, checkpoint_dir,
                        init_state: Mapping[str, torch.Tensor] | None = None) -> Distillation:
    """Decide time, build and bind the prior (its geometry built here, so its cost is reported
    as point_cloud), distil the field."""
    params, config = job.params, job.config
    cfg = config.distill
    reporter.stage("temporal", 0.04, "detecting lighting changes")
    with timings("temporal"):
        decision: TemporalDecision = decide_temporal(capture, params.temporal)
    with timings("loading"):
        work = capture.resized(cfg.work_height)

    reporter.stage("point_cloud", 0.07, "building the prior")
    with timings("point_cloud"):
        if prior is None:
            prior = prior_factory(params.prior, job.prior_settings, device)
        prior.bind(work, lighting_changes=decision.uses_time)
        bounds = scene_bounds(work, cfg.time_normalisation_frames)
        if prior.capabilities.frame_geometry:  # build the geometry now so its cost is reported here
            for i in distinct_geometry(work):
                prior.prepare_frame(i)

    reporter.stage("distill", 0.1, f"{cfg.iterations} steps")
    result = distill(work, prior, config, decision.uses_time, seed=params.seed, reporter=reporter,
                     checkpoint_dir=Path(checkpoint_dir) if checkpoint_dir else None, timings=timings, bounds=bounds,
                     init_state=dict(init_state) if init_state is not None else None)
    return Distillation(decision, work, prior, result)


def job_metadata(capture: Capture, run: Distillation, params: JobParams, config: EngineConfig, timings: StageTimer,
                 wall_time_s: float) -> dict:
    """The artefact's lightfield.json metadata: the capture, the working resolution, the prior,
    the temporal decision, the job's parameters and config, the training's record and cost
    (`wall_time_s` up to saving) and what the job simulated."""
    decision, work, result = run.decision, run.work, run.result
    prior_description = run.prior.describe()
    return {
        "time": {
            "t0": float(capture.times[0]),
            "t1": float(capture.times[-1]),
            "fps": capture.fps,
            "uses_time": decision.uses_time,
        },
        "capture": capture.summary(),
        "working_resolution": {"width": work.width, "height": work.height, "intrinsics": work.intrinsics.as_dict()},
        "prior": prior_description,
        "temporal": decision.as_dict(),
        "params": params.model_dump(),
        "engine_config": config.model_dump(mode="json"),
        "training": {
            "iterations": result.iterations,
            "resumed_from": result.resumed_from,
            "loss_curve": _decimate(result.losses, LOSS_CURVE_MAX_POINTS),
            "final_loss": result.losses[-1] if result.losses else None,
            "wall_time_s": round(wall_time_s, 3),
            "device": result.stats["device"],
            "threads": config.distill.threads or torch.get_num_threads(),
            "perceptual": result.stats["perceptual"],
            "supervision": result.stats["supervision"],
            "emitters": result.stats.get("emitters", []),
            "surfaces": result.stats.get("surfaces"),
            "warm_start": result.stats.get("warm_start"),
            "stage_timings": timings.as_dict(),
        },
        "simulated": {
            "time_input": decision.uses_time,
            "point_cloud_builds": prior_description.get("point_cloud_builds"),
            "camera": "static" if capture.static_camera else "moving",
            "rendered": (
                "ball pixels only (field evaluated at ball centres for reflected directions)"
                if result.stats["supervision"] == "balls"
                else "no balls: the prior's HDR env maps at probe centres, random directions (radiance supervision)"
            ),
        },
    }
