"""`lightfield simulate SPEC.json|SUITE -o DIR`: render a simulated capture with ground truth."""
from __future__ import annotations

import argparse
import json
import sys

HELP = (
    "Render a simulated indoor scene (a spec JSON or a suite name) into a capture directory with ground-truth env maps."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", help="scene spec JSON file, or a suite name: static, spatial, temporal, moving-camera, hard")
    p.add_argument("-o", "--output", required=True, help="capture directory to write")
    p.add_argument(
        "--probes", default=None, help='ground-truth probes "x,y,z@t;..." (metres, seconds); default: the scene\'s own'
    )
    p.add_argument("--height", type=int, default=64, help="ground-truth env map height (width = 2 x height)")
    p.add_argument("--no-video", action="store_true", help="skip video.mp4")
    p.add_argument(
        "--curve", default=None, choices=("drawn", "srgb", "rec709", "filmic", "hlg10", "gamma2.4"),
        help="the camera curve the frames are encoded with and declare (core.sim.camera_curves; default: the spec's "
             "`sensor.curve`, 'drawn' by the scene's name unless it names one; gamma2.4 is the reference, the curve "
             "the product used to assume)",
    )
    p.add_argument(
        "--training-export",
        metavar="DIR",
        default=None,
        help="also write diffusion-prior training samples (docs/training-data.md)",
    )
    p.add_argument(
        "--views", type=int, default=8, help="training samples (viewpoints) to export with --training-export"
    )


def load_spec(text: str):
    from pathlib import Path

    from core.sim.spec import SceneSpec
    from core.sim.suites import SUITES, suite

    if text in SUITES:
        return suite(text)
    path = Path(text)
    if not path.is_file():
        from core.sim.spec import SceneSpecError

        raise SceneSpecError(f"spec {text!r} is neither a file nor a suite ({', '.join(sorted(SUITES))})")
    return SceneSpec.model_validate_json(path.read_text())


def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from core.sim.capture import parse_probes, write_capture
    from core.sim.spec import SceneSpecError
    from core.sim.training import write_training_export

    try:
        scene = load_spec(args.spec)
        if getattr(args, "curve", None):
            scene = scene.model_copy(update={"sensor": scene.sensor.model_copy(update={"curve": args.curve})})
        probes = parse_probes(args.probes) if args.probes else None
        doc = write_capture(scene, args.output, probes=probes, envmap_height=args.height, video=not args.no_video)
        summary = {
            "capture": args.output,
            "frames": doc["frame_count"],
            "probes": len(doc["probes"]),
            "effects": sorted(scene.effects),
            "camera_curve": doc["camera_curve"],
            "cost": doc["cost"],
        }
        if args.training_export:
            ds = write_training_export(scene, args.training_export, args.views)
            summary["training_export"] = {"dir": args.training_export, "count": ds["count"]}
    except (SceneSpecError, ValidationError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary))
    return 0
