"""`lightfield sequence OUT --x X,Y,Z --t0 A --t1 B --frames N -o DIR|shot.zip`: EXR sequence over time."""
from __future__ import annotations

import argparse
from pathlib import Path

from cli.probe_args import Probe, parse_position, print_json, run_guarded

HELP = "Write env maps at one probe over a time range as an EXR sequence (envmap.0001.exr ...), a directory or a zip."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("artefact", metavar="OUT", help="artefact directory written by `lightfield estimate -o OUT`")
    p.add_argument("--x", required=True, type=parse_position, metavar="X,Y,Z", help="probe position, world metres")
    p.add_argument("--t0", type=float, required=True, help="first time, seconds")
    p.add_argument("--t1", type=float, required=True, help="last time, seconds (inclusive)")
    p.add_argument("--frames", type=int, required=True, help="evenly spaced frames from t0 to t1")
    p.add_argument("--height", type=int, default=64, help="rows of each map (width = 2 x height)")
    p.add_argument("--first-frame", type=int, default=1, help="number of the first file")
    p.add_argument("--colour", choices=("rec709", "acescg"), default="rec709",
                   help="pixel colour space: linear Rec. 709 (as estimated) or ACEScg (AP1, for ACES pipelines)")
    p.add_argument("--fast", action="store_true", help="answer from the baked grid (approximate)")
    p.add_argument("-o", "--output", required=True, metavar="DIR|FILE.zip", help="a directory, or a .zip")


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        from core.export.sequence import sequence_fps, sequence_members, sequence_times, zip_stream
        from core.io.exr import atomic_write

        if args.t1 < args.t0:
            raise ValueError(f"--t1 ({args.t1}) must not be before --t0 ({args.t0})")
        out = Path(args.output)
        probe = Probe(args.artefact, args.fast)
        times = sequence_times(args.t0, args.t1, args.frames)
        maps = ((t, probe.envmap(args.x, t, args.height)[0].cpu().numpy()) for t in times)
        members = sequence_members(maps, args.x, probe.id, first_frame=args.first_frame, extra={"height": args.height},
                                   fps=sequence_fps(times), colour=args.colour)
        if out.suffix.lower() == ".zip":
            atomic_write(out, b"".join(zip_stream(members)))
        else:
            out.mkdir(parents=True, exist_ok=True)
            for name, data in members:
                atomic_write(out / name, data)
        print_json({"output": str(out), "frames": len(times), "t0": args.t0, "t1": args.t1, "x": list(args.x)})
        return 0

    return run_guarded(body)
