"""`lightfield cubemap OUT --x X,Y,Z -o cube.ktx2|cube.npy|DIR`: cube map faces, prefiltered mips in KTX2."""
from __future__ import annotations

import argparse
from pathlib import Path

from cli.probe_args import Probe, add_probe_arguments, check_output, print_json, run_guarded, warn_extrapolated

HELP = "Write the cube map at a probe: KTX2 with GGX roughness mips, a float32 .npy, or one EXR per face."
FORMATS = ("ktx2", "npy", "exr")
FACE_NAMES = ("px", "nx", "py", "ny", "pz", "nz")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_probe_arguments(p)
    p.add_argument("--size", type=int, default=64, help="face edge in texels (a power of two for ktx2)")
    p.add_argument("--levels", type=int, default=None,
                   help="ktx2 mip levels, roughness i / (levels - 1) (default: down to size/32; 1 = mirror only)")
    p.add_argument("--format", choices=FORMATS, default=None,
                   help="ktx2 (one file), npy ([6, S, S, 3]) or exr (a directory of px.exr ... nz.exr); default: "
                        "the -o extension, exr for a name without one")
    p.add_argument("--layout", choices=("gl", "threejs"), default="gl",
                   help="gl: the OpenGL/Vulkan/Metal face table; threejs: mirrored in x for a three.js CubeTexture")
    p.add_argument("-o", "--output", required=True, metavar="FILE|DIR", help="file (ktx2, npy) or directory (exr)")


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        import numpy as np

        from core.cubemap import equirect_to_cubemap
        from core.export.products import cube_for, cube_ktx2, cube_source_height, envmap_exr_attributes
        from core.io.exr import atomic_write, encode_exr

        out = Path(args.output)
        fmt = args.format or (out.suffix.lower().lstrip(".") or "exr")
        if fmt not in FORMATS:
            raise ValueError(f"cannot tell the format of -o {out}: use a .ktx2/.npy name, a directory, or --format")
        if fmt != "exr":
            problem = check_output(out, fmt, FORMATS)
            if problem:
                raise ValueError(problem)
        probe = Probe(args.artefact, args.fast)
        hdr, flags = probe.envmap(args.x, args.t, cube_source_height(args.size))
        if fmt == "ktx2":
            atomic_write(out, cube_ktx2(hdr, args.size, args.levels, args.layout))
        else:
            faces = equirect_to_cubemap(cube_for(hdr, args.layout), args.size).numpy()
            if fmt == "npy":
                np.save(out, faces.astype(np.float32), allow_pickle=False)
            else:
                out.mkdir(parents=True, exist_ok=True)
                attrs = envmap_exr_attributes(args.x, args.t, probe.id)
                for name, face in zip(FACE_NAMES, faces):
                    attrs["lightfield:layout"] = (
                        f"cube face {name}: OpenGL GL_TEXTURE_CUBE_MAP orientation (docs/conventions.md)"
                    )
                    atomic_write(out / f"{name}.exr", encode_exr(face, attributes=attrs))
        warn_extrapolated(flags)
        print_json({"output": str(out), "format": fmt, "size": args.size, "x": list(args.x), "t": args.t, **flags})
        return 0

    return run_guarded(body)
