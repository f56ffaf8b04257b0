"""`lightfield usd OUT --x X,Y,Z -o probe.usdz|probe.usda`: a USD DomeLight with its EXR."""
from __future__ import annotations

import argparse
from pathlib import Path

from cli.probe_args import Probe, add_probe_arguments, print_json, run_guarded, warn_extrapolated

HELP = "Write a USD stage with a DomeLight lit by the probe's env map: one .usdz, or a .usda next to its .exr."


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_probe_arguments(p)
    p.add_argument("--height", type=int, default=256, help="rows of the dome's latlong EXR (width = 2 x height)")
    p.add_argument("-o", "--output", required=True, metavar="FILE.usdz|FILE.usda",
                   help=".usdz (one package) or .usda (the texture is written beside it as FILE.exr)")


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        from core.export.products import probe_usdz
        from core.export.usd import dome_light_usda, dome_texture_exr
        from core.io.exr import atomic_write

        out = Path(args.output)
        kind = out.suffix.lower().lstrip(".")
        if kind not in ("usdz", "usda"):
            raise ValueError(f"-o {out}: the name must end in .usdz or .usda")
        probe = Probe(args.artefact, args.fast)
        hdr, flags = probe.envmap(args.x, args.t, args.height)
        env = hdr.cpu().numpy()
        if kind == "usdz":
            atomic_write(out, probe_usdz(env, args.x, args.t, probe.id, probe.grade))
        else:
            texture = out.with_suffix(".exr")
            atomic_write(texture, dome_texture_exr(env, args.x, args.t, probe.id))
            atomic_write(out, dome_light_usda(texture.name, args.x, args.t, probe.id, grade=probe.grade).encode())
        warn_extrapolated(flags)
        print_json({"output": str(out), "format": kind, "x": list(args.x), "t": args.t, **flags})
        return 0

    return run_guarded(body)
