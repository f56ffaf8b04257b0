"""`lightfield train-prior --data DIR --base MODEL_DIR -o OUT`: fine-tune the diffusion prior."""
from __future__ import annotations

import argparse
import json
import sys

HELP = "Fine-tune the chrome-ball diffusion prior (UNet + depth ControlNet) on lightfield-balls training data."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--data", required=True, help="training data directory (dataset.json + samples/, docs/training-data.md)"
    )
    p.add_argument("--base", required=True, help="local model directory to start from (docs/diffusion-prior.md)")
    p.add_argument(
        "-o", "--output", required=True, help="output directory: checkpoints/, train_log.jsonl and the final model"
    )
    p.add_argument("--iterations", type=int, default=15_000, help="optimizer steps (default 15000)")
    p.add_argument("--lr", type=float, default=1e-5, help="AdamW learning rate (default 1e-5)")
    p.add_argument("--batch", type=int, default=16, help="effective batch size (default 16)")
    p.add_argument("--micro-batch", type=int, default=1, help="samples per forward pass per process (default 1)")
    p.add_argument(
        "--grad-accum",
        type=int,
        default=None,
        help="gradient accumulation steps (default: batch / (micro-batch x processes))",
    )
    p.add_argument(
        "--checkpoint-every", type=int, default=500, help="optimizer steps between checkpoints (default 500)"
    )
    p.add_argument("--keep-checkpoints", type=int, default=2)
    p.add_argument("--log-every", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--mixed-precision", choices=["no", "fp16", "bf16"], default="no")
    p.add_argument("--gradient-checkpointing", action="store_true", help="trade compute for activation memory")
    p.add_argument("--num-workers", type=int, default=0, help="data-loading worker processes")
    p.add_argument("--resume", action="store_true", help="continue from the newest checkpoint in OUT/checkpoints")


def run(args: argparse.Namespace) -> int:
    import logging

    from pydantic import ValidationError

    from core.priors.base import PriorError
    from core.training.diffusion.data import TrainingDataError
    from core.training.diffusion.train import TrainConfig, TrainConfigError, train_prior

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    try:
        cfg = TrainConfig(
            iterations=args.iterations, lr=args.lr, batch=args.batch, micro_batch=args.micro_batch,
            grad_accum=args.grad_accum, checkpoint_every=args.checkpoint_every, keep_checkpoints=args.keep_checkpoints,
            log_every=args.log_every, seed=args.seed, mixed_precision=args.mixed_precision,
            gradient_checkpointing=args.gradient_checkpointing, num_workers=args.num_workers,
        )
        result = train_prior(args.data, args.base, args.output, cfg, resume=args.resume)
    except (ValidationError, TrainConfigError, TrainingDataError, PriorError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not result.main_process:
        return 0
    print(json.dumps({
        "output": str(result.out_dir), "from_step": result.start_step, "to_step": result.final_step,
        "final_loss": result.losses[-1] if result.losses else None, "seconds": round(result.seconds, 2),
    }))
    return 0
