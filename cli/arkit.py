"""`lightfield arkit OUT --x X,Y,Z -o probe.json`: the ARKit hand-off (Metal cube slices, SH planes, main
light) as JSON: core.export.schema.ArkitProbe, as the API's /arkit."""
from __future__ import annotations

import argparse
from pathlib import Path

from cli.probe_args import Probe, add_probe_arguments, flags_model, print_json, run_guarded, warn_extrapolated

HELP = ("Write the ARKit/RealityKit/SceneKit hand-off: Metal cube slices (rgba16Float or sRGB 8-bit), SH planes, "
        "main light.")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_probe_arguments(p)
    p.add_argument("--size", type=int, default=64, help="cube face edge in texels")
    p.add_argument("--pixel-format", choices=("rgba16Float", "rgba8Unorm_srgb"), default="rgba16Float",
                   help="rgba16Float: linear HDR (EnvironmentResource, lightingEnvironment); rgba8Unorm_srgb: what "
                        "AREnvironmentProbeAnchor.environmentTexture holds (tone-mapped at --ev)")
    p.add_argument("--ev", type=float, default=0.0, help="exposure of the sRGB slices (2^ev before the clip)")
    p.add_argument("-o", "--output", required=True, metavar="FILE.json", help="file to write")


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        from core.export.arkit import arkit_probe
        from core.export.products import cube_source_height
        from core.io.exr import atomic_write

        if not 1 <= args.size <= 2048:
            raise ValueError(f"--size must be in 1..2048, got {args.size}")
        probe = Probe(args.artefact, args.fast)
        hdr, flags = probe.envmap(args.x, args.t, cube_source_height(args.size))
        doc = arkit_probe(hdr.cpu().numpy(), args.x, args.t, flags_model(flags), args.size, args.pixel_format, args.ev)
        atomic_write(Path(args.output), doc.model_dump_json().encode())
        warn_extrapolated(flags)
        print_json(
            {"output": args.output, "format": "arkit", "size": args.size, "x": list(args.x), "t": args.t, **flags}
        )
        return 0

    return run_guarded(body)
