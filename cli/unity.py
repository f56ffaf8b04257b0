"""`lightfield unity OUT --grid NX,NY,NZ -o probes.json`: a Unity light-probe grid (positions +
SphericalHarmonicsL2, each probe flagged when extrapolated): core.export.schema.UnityProbeGrid, as the API's /unity."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cli.probe_args import Probe, parse_position, print_json, run_guarded
from core.export.probe_queries import UNITY_GRID_DEFAULT, UNITY_SH_HEIGHT, parse_grid

HELP = "Write a Unity light-probe grid: probe positions on Unity axes and SphericalHarmonicsL2 values for each."


def _counts(text: str) -> tuple[int, int, int]:
    try:
        return parse_grid(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--{exc}") from None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("artefact", metavar="OUT", help="artefact directory written by `lightfield estimate -o OUT`")
    p.add_argument("--grid", type=_counts, default=UNITY_GRID_DEFAULT, metavar="NX,NY,NZ", help="probes per axis")
    p.add_argument("--lo", type=parse_position, default=None, metavar="X,Y,Z",
                   help="grid corner, our world metres (default: the probes sit at the cell centres of the region "
                        "the captures cover)")
    p.add_argument("--hi", type=parse_position, default=None, metavar="X,Y,Z",
                   help="opposite corner (default: that region's)")
    p.add_argument("--t", type=float, default=None, metavar="SEC", help="seconds from the first frame")
    p.add_argument("--fast", action="store_true", help="answer from the baked grid (approximate)")
    p.add_argument("-o", "--output", required=True, metavar="FILE.json", help="file to write")


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        from core.export.schema import AnswerGrade
        from core.export.unity import unity_probe_grid
        from core.io.exr import atomic_write

        probe = Probe(args.artefact, args.fast)

        def evaluate(x):
            hdr, flags = probe.envmap(x, args.t, UNITY_SH_HEIGHT)
            return hdr.cpu().numpy(), {"x": flags["extrapolated_x"], "t": flags["extrapolated_t"]}

        doc = unity_probe_grid(evaluate, probe.artefact.bounds, args.grid, args.t, probe.id, args.lo, args.hi,
                               AnswerGrade.of(probe.artefact.meta))
        atomic_write(Path(args.output), doc.model_dump_json().encode())
        if doc.extrapolated_probes:
            print(f"warning: {doc.extrapolated_probes} of {len(doc.probes)} probes lie outside the region the captures "
                  f"cover (or the time range); probes[i].extrapolated says which", file=sys.stderr)
        print_json({"output": args.output, "probes": len(doc.probes), "grid": list(args.grid),
                    "extrapolated_probes": doc.extrapolated_probes})
        return 0

    return run_guarded(body)
