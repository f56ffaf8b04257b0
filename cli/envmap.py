"""`lightfield envmap OUT --x X,Y,Z [--t SEC] -o FILE`: one env map from a stored light field."""
from __future__ import annotations

import argparse
from pathlib import Path

from cli.probe_args import (
    Probe,
    add_probe_arguments,
    check_output,
    parse_position,
    print_json,
    run_guarded,
    warn_extrapolated,
)

HELP = "Write the HDR environment map seen from a world position (and time) of an estimated light field."
FORMATS = ("exr", "hdr", "png", "npy")
__all__ = ["HELP", "add_arguments", "run", "parse_position", "output_format"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_probe_arguments(p)
    p.add_argument("--height", type=int, default=64, help="rows of the equirect map (width = 2 x height)")
    p.add_argument("--format", choices=FORMATS, default=None,
                   help="file format; without it the -o extension decides (.exr, .hdr, .png, .npy)")
    p.add_argument("--ev", type=float, default=0.0, help="exposure of the PNG preview (2^ev before the tone map)")
    p.add_argument("-o", "--output", required=True, metavar="FILE", help="file to write")


def output_format(path: Path, explicit: str | None) -> str:
    """--format, else the extension; ValueError when they disagree or neither names a format."""
    suffix = path.suffix.lower().lstrip(".")
    fmt = explicit or suffix
    if fmt not in FORMATS:
        raise ValueError(f"cannot tell the format of -o {path}: use a .exr/.hdr/.png/.npy name or --format")
    problem = check_output(path, fmt, FORMATS)
    if problem:
        raise ValueError(problem)
    return fmt


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        from core.export.products import envmap_exr_attributes
        from core.io.envmap_io import save_envmap

        out = Path(args.output)
        fmt = output_format(out, args.format)
        probe = Probe(args.artefact, args.fast)
        hdr, flags = probe.envmap(args.x, args.t, args.height)
        attrs = envmap_exr_attributes(args.x, args.t, probe.id) if fmt == "exr" else None
        save_envmap(out, hdr.cpu().numpy(), fmt, ev=args.ev, attributes=attrs)
        warn_extrapolated(flags)
        print_json({"output": str(out), "format": fmt, "height": args.height, "x": list(args.x), "t": args.t,
                    "quality": "baked" if args.fast else "exact", **flags})
        return 0

    return run_guarded(body)
