"""`lightfield unity OUT --grid NX,NY,NZ -o probes.json`: a Unity light-probe grid (positions + SphericalHarmonicsL2)."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from cli.probe_args import Probe, parse_position, print_json, run_guarded

HELP = "Write a Unity light-probe grid: probe positions on Unity axes and SphericalHarmonicsL2 values for each."
SH_HEIGHT = 32  # band-2 SH need little resolution


def _counts(text: str) -> tuple[int, int, int]:
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(1 <= v <= 64 for v in values):
        raise argparse.ArgumentTypeError(f"--grid must be three integers in 1..64 'NX,NY,NZ', got {text!r}")
    return values  # type: ignore[return-value]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("artefact", metavar="OUT", help="artefact directory written by `lightfield estimate -o OUT`")
    p.add_argument("--grid", type=_counts, default=(3, 2, 3), metavar="NX,NY,NZ", help="probes per axis")
    p.add_argument("--lo", type=parse_position, default=None, metavar="X,Y,Z",
                   help="grid corner, our world metres (default: the scene box the field was trained on)")
    p.add_argument("--hi", type=parse_position, default=None, metavar="X,Y,Z", help="opposite corner (default: the scene box)")
    p.add_argument("--t", type=float, default=None, metavar="SEC", help="seconds from the first frame")
    p.add_argument("--fast", action="store_true", help="answer from the baked grid (approximate)")
    p.add_argument("-o", "--output", required=True, metavar="FILE.json", help="file to write")


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        from core.export.unity import probe_grid, to_unity, unity_sh

        probe = Probe(args.artefact, args.fast)
        bounds = probe.artefact.bounds
        lo, hi = args.lo or bounds.lo, args.hi or bounds.hi
        positions = probe_grid(lo, hi, args.grid)
        sh = [unity_sh(probe.envmap(tuple(float(v) for v in x), args.t, SH_HEIGHT)[0].cpu().numpy()) for x in positions]
        doc = {
            "about": "Unity light probes: positions_unity are Unity coordinates (z flipped from ours); sh[i] is "
                     "SphericalHarmonicsL2 [channel][k] in Unity's convention (docs/integrations.md)",
            "t": args.t, "grid": list(args.grid), "positions": positions.tolist(),
            "positions_unity": to_unity(positions).tolist(), "sh": sh, "artefact": probe.id,
        }
        Path(args.output).write_text(json.dumps(doc))
        print_json({"output": args.output, "probes": len(positions), "grid": list(args.grid)})
        return 0

    return run_guarded(body)
