"""`lightfield preview OUT --input INPUT -o FILE.png|.mp4`: virtual object insertion."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "Composite chrome balls and diffuse spheres lit by an estimated light field into the input frames (PNG or MP4)."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("artefact", help="artefact directory written by `lightfield estimate`")
    p.add_argument(
        "--input", required=True, help="the image, video or capture directory the artefact was estimated from"
    )
    p.add_argument("--depth", default=None, help="the depth file given to `estimate`, if any")
    p.add_argument(
        "--points",
        default=None,
        help="'u,v[,depth];...': u, v fractions of width/height, depth planar metres (default: two points, lower "
             "third)",
    )
    p.add_argument("--frame", type=int, default=0, help="frame to render for PNG output")
    p.add_argument("--env-height", type=int, default=32, help="env map resolution used for lighting the objects")
    p.add_argument("-o", "--output", required=True, help="FILE.png (one frame) or FILE.mp4 (every frame)")


def render_preview(artefact_dir, input_path, output, depth=None, points=None, frame=0, env_height=32) -> Path:
    import warnings

    import numpy as np

    from core.capture.reload import reload_capture
    from core.fields.stored.artefact import LightFieldArtefact
    from core.insertion import insert_objects, parse_points
    from core.io import write_png, write_video

    art = LightFieldArtefact.load(artefact_dir)
    pts = parse_points(points)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the defaults were already reported by `estimate`
        capture = reload_capture(input_path, depth, art.meta.get("capture", {}))  # as the job saw it

    def envmaps_at(xs, t):
        return art.envmaps(xs, t, env_height)[0]  # a scalar t applies to every position

    def render(i: int) -> np.ndarray:
        t = float(capture.times[i]) if art.uses_time else None
        out = insert_objects(capture.frames[i], capture.depth[i], capture.camera(i), envmaps_at, t, pts,
                             ev=float(capture.frame_ev[i]))
        return out.numpy()

    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    if output.suffix.lower() == ".mp4":
        return write_video(output, np.stack([render(i) for i in range(capture.num_frames)]), capture.fps)
    if output.suffix.lower() != ".png":
        raise ValueError(f"output must end in .png or .mp4, got {output.name!r}")
    if not (0 <= frame < capture.num_frames):
        raise ValueError(f"--frame {frame} is outside 0..{capture.num_frames - 1}")
    return write_png(output, render(frame))


def run(args: argparse.Namespace) -> int:
    from core.capture.base import CaptureError
    from core.fields.stored.artefact import ArtefactError
    from core.insertion import InsertionError
    from core.io import MediaError

    try:
        path = render_preview(
            args.artefact, args.input, args.output, args.depth, args.points, args.frame, args.env_height
        )
    except (ArtefactError, CaptureError, MediaError, InsertionError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(path)
    return 0
