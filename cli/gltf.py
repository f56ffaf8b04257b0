"""`lightfield gltf OUT --x X,Y,Z -o probe.glb`: glTF image-based light (EXT_lights_image_based)."""
from __future__ import annotations

import argparse
from pathlib import Path

from cli.probe_args import Probe, add_probe_arguments, check_output, print_json, run_guarded, warn_extrapolated

HELP = (
    "Write a glTF binary (.glb) whose EXT_lights_image_based light is the probe's irradiance SH and prefiltered cube."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_probe_arguments(p)
    p.add_argument("--size", type=int, default=64, help="specular cube face edge (a power of two)")
    p.add_argument("--levels", type=int, default=None, help="specular mips, roughness 0..1 (default: down to size/32)")
    p.add_argument("--no-main-light", dest="main_light", action="store_false",
                   help="no KHR_lights_punctual main light: the whole map's SH as irradiance")
    p.add_argument("-o", "--output", required=True, metavar="FILE.glb", help="file to write")


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        from core.export.products import cube_source_height, probe_glb
        from core.io.exr import atomic_write

        out = Path(args.output)
        problem = check_output(out, "glb", ("glb",))
        if problem:
            raise ValueError(problem)
        probe = Probe(args.artefact, args.fast)
        hdr, flags = probe.envmap(args.x, args.t, cube_source_height(args.size))
        atomic_write(out, probe_glb(hdr, args.x, args.t, args.size, args.levels, probe.id, args.main_light,
                                        probe.grade))
        warn_extrapolated(flags)
        print_json({"output": str(out), "format": "glb", "size": args.size, "x": list(args.x), "t": args.t, **flags})
        return 0

    return run_guarded(body)
