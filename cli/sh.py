"""`lightfield sh OUT --x X,Y,Z [--x ...] [--t SEC]`: main light + ambient SH in a consumer's layout, as JSON:
the same model (core.export.schema.SphericalHarmonics) as the API's /sh."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from cli.probe_args import Probe, flags_model, parse_position, print_json, run_guarded
from core.export.probe_queries import SH_ENVMAP_HEIGHT
from core.export.sh_layouts import LAYOUT_NAMES

HELP = "Print the main light and ambient spherical harmonics at one or many probes, in a consumer's SH layout."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("artefact", metavar="OUT", help="artefact directory written by `lightfield estimate -o OUT`")
    p.add_argument("--x", action="append", type=parse_position, metavar="X,Y,Z",
                   help="probe position, world metres; repeat for a batch")
    p.add_argument("--t", type=float, default=None, metavar="SEC", help="seconds from the first frame, for every --x")
    p.add_argument("--queries", type=Path, default=None, metavar="FILE",
                   help='JSON list of {"x": [X, Y, Z], "t": SEC} (a batch; instead of --x)')
    p.add_argument("--layout", choices=LAYOUT_NAMES, default="arcore",
                   help="coefficient layout (core.export.sh_layouts): arcore, threejs (SphericalHarmonics3.fromArray), "
                        "babylon (SphericalHarmonics.FromArray / glTF irradiance), unity (SphericalHarmonicsL2), "
                        "arkit (three planes)")
    p.add_argument("--fast", action="store_true", help="answer from the baked grid (approximate)")


def _queries(args) -> list[tuple[tuple[float, float, float], float | None]]:
    if args.queries is not None:
        doc = json.loads(args.queries.read_text())
        if not isinstance(doc, list) or not doc:
            raise ValueError(f"{args.queries}: expected a non-empty JSON list of {{'x': [X, Y, Z], 't': SEC}}")
        return [(parse_position(",".join(str(v) for v in q["x"])), q.get("t")) for q in doc]
    if not args.x:
        raise ValueError("give --x X,Y,Z (repeatable) or --queries FILE")
    return [(x, args.t) for x in args.x]


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        from core.export.schema import SphericalHarmonics
        from core.lights import extract_dominant_light
        from core.sh import project_sh

        probe = Probe(args.artefact, args.fast)
        out = []
        for x, t in _queries(args):
            hdr, flags = probe.envmap(x, t, SH_ENVMAP_HEIGHT)
            light = extract_dominant_light(hdr)
            out.append(SphericalHarmonics.of(x, t, flags_model(flags), args.layout, light,
                                             project_sh(hdr.double())).model_dump(mode="json"))
        print_json(out if len(out) > 1 or args.queries is not None else out[0])
        return 0

    return run_guarded(body)
