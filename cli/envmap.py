"""`lightfield envmap OUT --x X,Y,Z [--t SEC] -o FILE`: one env map from a stored light field."""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

HELP = "Write the HDR environment map seen from a world position (and time) of an estimated light field."
FORMATS = ("exr", "hdr", "png", "npy")


def parse_position(text: str) -> tuple[float, float, float]:
    """'X,Y,Z' (metres) -> three finite floats; argparse reports the ValueError as a usage error."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"--x must be three finite numbers 'X,Y,Z' in metres, got {text!r}")
    return values  # type: ignore[return-value]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("artefact", metavar="OUT", help="artefact directory written by `lightfield estimate -o OUT`")
    p.add_argument("--x", required=True, type=parse_position, metavar="X,Y,Z", help="probe position, world metres")
    p.add_argument("--t", type=float, default=None, metavar="SEC",
                   help="seconds from the first frame (required when the field varies over time)")
    p.add_argument("--height", type=int, default=64, help="rows of the equirect map (width = 2 x height; default 64)")
    p.add_argument("--format", choices=FORMATS, default=None, help="default: from the -o suffix, else exr")
    p.add_argument("--ev", type=float, default=0.0, help="exposure of the PNG preview (2^ev before the tone map)")
    p.add_argument("--fast", action="store_true",
                   help="answer from the baked grid next to the artefact (baked on first use; approximate)")
    p.add_argument("-o", "--output", required=True, metavar="FILE", help="file to write")


def output_format(path: Path, explicit: str | None) -> str:
    if explicit:
        return explicit
    suffix = path.suffix.lower().lstrip(".")
    return suffix if suffix in FORMATS else "exr"


def run(args: argparse.Namespace) -> int:
    from core.fields.artefact import ArtefactError, LightFieldArtefact, QueryError
    from core.io.envmap_io import save_envmap
    from core.io.limits import MediaError

    out = Path(args.output)
    fmt = output_format(out, args.format)
    try:
        artefact = LightFieldArtefact.load(args.artefact)
        if args.fast:
            from core.fields.bake import load_or_bake

            hdr, flags = load_or_bake(artefact).envmap(args.x, args.t, args.height)
        else:
            hdr, flags = artefact.envmap(args.x, args.t, args.height)
        save_envmap(out, hdr.cpu().numpy(), fmt, ev=args.ev)
    except (ArtefactError, QueryError, MediaError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    extrapolated = [axis for axis, key in (("x", "extrapolated_x"), ("t", "extrapolated_t")) if flags[key]]
    if extrapolated:
        print(f"warning: query outside the estimated {' and '.join(extrapolated)} range; the answer is extrapolated",
              file=sys.stderr)
    print(json.dumps({"output": str(out), "format": fmt, "height": args.height, "x": list(args.x), "t": args.t,
                      "quality": "fast" if args.fast else "exact", **flags}))
    return 0
