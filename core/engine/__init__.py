"""The estimation engine: the distillation loop and the job entry point `run_job`.

    probes.py       where a step's chrome balls go          scene.py     field bounds, distinct frames
    trainer.py      one optimisation step                   distill.py   the loop (checkpoints, progress)
    checkpoints.py  resumable state                         job.py       run_job: capture -> artefact
    config.py       EngineConfig / DistillConfig            presets.py   draft / standard / paper
    params.py       JobParams, resolve_job (its config)     losses.py, progress.py
"""
from core.engine.job import JobResult, run_job

__all__ = ["JobResult", "run_job"]
