"""`lightfield estimate INPUT -o OUT`: distil a light field from an image, video or capture
(a nerfstudio directory or zip with transforms.json, or a simulator capture directory)."""
from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from cli import choices

HELP = ("Estimate a spatiotemporal HDR light field from an image, a video, a nerfstudio capture (directory or "
        "zip with transforms.json) or a simulator capture directory.")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", help="image, video, nerfstudio capture (directory or zip with transforms.json), "
                                 "or simulator capture directory (capture.json)")
    p.add_argument("-o", "--output", required=True, help="artefact directory to write")
    p.add_argument(
        "--depth", default=None, help="planar depth in metres: .npz ('depth' [T,H,W] or [H,W]), .exr, 16-bit PNG (mm)"
    )
    p.add_argument(
        "--params", default=None, help="job parameters as a JSON string or file (same schema as the service)"
    )
    p.add_argument(
        "--preset",
        choices=choices.PRESETS,
        metavar="PRESET",
        default=None,
        help="one of %(choices)s (seed = the authors' released loop, with the diffusion prior's seed profile)",
    )
    p.add_argument("--prior", choices=choices.PRIORS, metavar="PRIOR", default=None, help="one of %(choices)s")
    p.add_argument("--prior-weights", default=None, help="local model directory of the diffusion prior")
    p.add_argument(
        "--prior-profile",
        choices=choices.PRIOR_PROFILES,
        metavar="PROFILE",
        default=None,
        help="diffusion prior's inference profile, one of %(choices)s (default: the preset's, else the model card's)",
    )
    p.add_argument(
        "--temporal", choices=choices.TEMPORAL_MODES, metavar="MODE", default=None, help="one of %(choices)s"
    )
    p.add_argument("--frame-ev", default=None, metavar="EVS",
                   help="each frame's exposure in stops, comma-separated (an auto-exposure video's metadata); "
                        "'estimate' when the camera adjusted it without recording it; 'locked' when it did not "
                        "(unset: a moving camera's auto-exposure is looked for; docs/captures.md, Exposure)")
    p.add_argument("--field", choices=choices.FIELDS, metavar="KIND", default=None,
                   help="field kind, one of %(choices)s (default: the preset's)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--iterations", type=int, default=None, help="override the preset's step count")
    p.add_argument("--resume", dest="resume", action="store_true", default=True,
                   help="resume from OUT.checkpoint if present (default)")
    p.add_argument("--no-resume", dest="resume", action="store_false", help="discard any checkpoint and start over")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def parse_frame_ev(text: str | None):
    """`--frame-ev`: None, "estimate", "locked", or comma-separated numbers (a ValueError names a bad one)."""
    if text is None or text.strip() in ("estimate", "locked"):
        return None if text is None else text.strip()
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--frame-ev must be 'estimate', 'locked' or comma-separated numbers, got {text!r}") from None


def checkpoint_dir_for(out: Path) -> Path:
    """Checkpoints live next to OUT (not inside: writing the artefact replaces OUT atomically)."""
    return out.parent / f"{out.name}.checkpoint"


class ProgressBar:
    """One self-overwriting stderr line: stage, iteration, loss, ETA."""

    def __init__(self, stream=sys.stderr, min_interval_s: float = 0.2):
        self.stream, self.min_interval_s, self._last = stream, min_interval_s, 0.0

    def __call__(self, p) -> None:
        now = time.monotonic()
        final = p.stage == "done" or (p.total and p.iteration >= p.total)
        if not final and now - self._last < self.min_interval_s and p.stage == "distill":
            return
        self._last = now
        width = 24
        filled = int(round(width * min(max(p.fraction, 0.0), 1.0)))
        bar = "#" * filled + "-" * (width - filled)
        parts = [f"[{bar}] {p.fraction * 100:5.1f}% {p.stage:<11}"]
        if p.total:
            parts.append(f"{p.iteration}/{p.total}")
        if p.loss is not None:
            parts.append(f"loss {p.loss:.4g}")
        if p.eta_s is not None and p.stage == "distill":
            parts.append(f"ETA {p.eta_s:4.0f}s")
        if p.message and p.stage != "distill":
            parts.append(p.message[:60])
        line = "  ".join(parts)
        self.stream.write("\r" + line.ljust(100)[:120])
        if p.stage == "done":
            self.stream.write("\n")
        self.stream.flush()


def run(args: argparse.Namespace) -> int:
    import json
    import warnings

    from pydantic import ValidationError

    from core.capture.base import CaptureError
    from core.engine import run_job
    from core.engine.params import parse_job_params
    from core.engine.progress import Cancelled
    from core.io import MediaError
    from core.priors.base import PriorError

    out = Path(args.output)
    try:
        params = parse_job_params(
            args.params,
            preset=args.preset,
            prior=args.prior,
            prior_weights=args.prior_weights,
            prior_profile=args.prior_profile,
            temporal=args.temporal,
            field=args.field,
            seed=args.seed,
            frame_ev=parse_frame_ev(args.frame_ev),
        )
    except (ValidationError, ValueError) as exc:
        print(f"error: invalid parameters: {exc}", file=sys.stderr)
        return 2
    overrides = {"distill.iterations": args.iterations} if args.iterations else None
    ckpt = checkpoint_dir_for(out)
    if not args.resume:
        shutil.rmtree(ckpt, ignore_errors=True)
    bar = None if args.quiet else ProgressBar()
    try:
        with warnings.catch_warnings():  # restores showwarning afterwards
            warnings.simplefilter("always")
            warnings.showwarning = lambda message, *_a, **_k: print(f"warning: {message}", file=sys.stderr)
            result = run_job(
                args.input, args.depth, params, out, progress=bar, checkpoint_dir=ckpt, overrides=overrides
            )
    except (CaptureError, MediaError, PriorError, ValidationError) as exc:
        print(f"\nerror: {exc}", file=sys.stderr)
        return 2
    except Cancelled:
        print(f"\ncancelled; resume with the same command (checkpoint in {ckpt})", file=sys.stderr)
        return 130
    shutil.rmtree(ckpt, ignore_errors=True)
    meta = result.artefact.meta
    tr = meta.get("training", {})
    print(
        json.dumps(
            {
                "artefact": str(result.path),
                "uses_time": meta.get("temporal", {}).get("uses_time"),
                "iterations": tr.get("iterations"),
                "final_loss": tr.get("final_loss"),
                "wall_time_s": tr.get("wall_time_s"),
                "depth_source": meta.get("capture", {}).get("depth_source"),
            }
        )
    )
    return 0
