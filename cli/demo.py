"""`lightfield demo`: the main job end to end on an embedded default scene.

Simulates a small room with core.sim (the `spatial` suite: two strong near lamps, so the
lighting visibly varies over space), estimates its light field with the draft preset and the
default (reprojection) prior, and writes estimated vs ground-truth env maps at the scene's
held-out probes plus a virtual-object-insertion preview to ./demo-output/.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HELP = "Run the main job on an embedded simulated scene and write env maps and a preview to ./demo-output/."
SUITE = "spatial"
ENV_HEIGHT = 64


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", default="demo-output", help="output directory (default ./demo-output)")
    p.add_argument("--preset", choices=["draft", "standard", "paper"], default="draft")
    p.add_argument("--iterations", type=int, default=None, help="override the preset's step count")
    p.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    import warnings

    import numpy as np
    import torch

    from cli.estimate import ProgressBar
    from cli.preview import render_preview
    from core.engine.artefact import LightFieldArtefact
    from core.engine.config import preset
    from core.engine.distill import run_job
    from core.engine.params import JobParams
    from core.io import load_envmap, save_envmap, write_png
    from core.io.envmap_io import tonemapped_preview
    from core.sim.capture import write_capture
    from core.sim.suites import suite

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))

    say(f"1/3 simulating the '{SUITE}' scene (core.sim) ...")
    capture_dir = out / "capture"
    doc = write_capture(suite(SUITE), capture_dir, envmap_height=ENV_HEIGHT, video=False)

    say("2/3 estimating the light field (draft preset, reprojection prior) ...")
    params = JobParams(preset=args.preset)
    config = preset(args.preset, iterations=args.iterations) if args.iterations else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        artefact_dir = run_job(capture_dir, None, params, out / "lightfield", config=config,
                               progress=None if args.quiet else ProgressBar(), checkpoint_dir=out / "lightfield.checkpoint")

    say("3/3 writing env maps and the preview ...")
    art = LightFieldArtefact.load(artefact_dir)
    env_dir = out / "envmaps"
    env_dir.mkdir(exist_ok=True)
    rows = []
    for k, probe in enumerate(doc["probes"]):
        est, flags = art.envmap(torch.tensor(probe["x"]), probe["t"] if art.uses_time else None, ENV_HEIGHT)
        est = est.numpy()
        gt = load_envmap(capture_dir / probe["envmap"])
        save_envmap(env_dir / f"probe{k}_estimate.exr", est)
        side = np.concatenate([tonemapped_preview(est), tonemapped_preview(gt)], axis=0)  # estimate over truth
        write_png(env_dir / f"probe{k}_estimate_vs_truth.png", side)
        rows.append({"x": probe["x"], "t": probe["t"], **flags})
    preview = render_preview(artefact_dir, capture_dir, out / "preview.png")
    summary = {
        "artefact": str(artefact_dir),
        "envmaps": str(env_dir),
        "preview": str(preview),
        "probes": rows,
        "wall_time_s": art.meta["training"]["wall_time_s"],
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"demo outputs in {out.resolve()}:\n  light field  {artefact_dir}\n  env maps     {env_dir} "
          f"(top: estimate, bottom: ground truth)\n  preview      {preview}\n  summary      {out / 'summary.json'}")
    return 0
