"""`lightfield prior import SOURCE_DIR [--controlnet DIR] -o OUT_DIR`: make a local prior
directory from weights as they are released (docs/diffusion-prior.md, "Importing")."""
from __future__ import annotations

import sys

from cli import choices

HELP = "manage diffusion prior weights (import released checkpoints into a local prior directory)"


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="prior_command", required=True, metavar="ACTION")
    imp = sub.add_parser(
        "import", help="convert a released pipeline folder (+ ControlNet, VAE, LoRA) into a prior directory"
    )
    imp.add_argument("source", help="the released diffusers pipeline folder (e.g. checkpoints/Multi_Inpaint)")
    imp.add_argument("-o", "--out", required=True, help="new (or empty) output directory")
    imp.add_argument("--controlnet", default=None, help="ControlNet folder when the pipeline has none inside")
    imp.add_argument("--vae", default=None, help="replacement VAE folder (DiffusionLight: sdxl-vae-fp16-fix)")
    imp.add_argument("--lora", default=None, help="LoRA folder or file (DiffusionLight's exposure LoRA checkpoint)")
    imp.add_argument("--lora-scale", type=float, default=None, help="LoRA fuse scale (DiffusionLight: 0.75)")
    imp.add_argument("--layout", default="auto", choices=choices.IMPORT_LAYOUTS, metavar="LAYOUT",
                     help="one of %(choices)s (default: auto, from the UNet and ControlNet)")
    imp.add_argument("--conditioning", default=None, choices=choices.CONTROL_CONDITIONINGS, metavar="KIND",
                     help="what the ControlNet expects, one of %(choices)s (default: from its folder name)")
    imp.add_argument("--profile", default=None, choices=choices.PRIOR_PROFILES, metavar="PROFILE",
                     help="inference profile recorded in the card, one of %(choices)s (default: the layout's)")
    imp.add_argument(
        "--variant", default=None, help="weights variant to take (e.g. fp16; default: full precision if present)"
    )
    imp.add_argument(
        "--max-memory-gb",
        type=float,
        default=None,
        help="memory limit of the .bin converter (default: 3 + 2.5 x file size)",
    )
    imp.add_argument(
        "--timeout-s", type=float, default=None, help="wall-clock limit of the .bin converter (default 1200)"
    )


def run(args) -> int:
    from dataclasses import replace

    from core.priors.base import PriorError
    from core.priors.diffusion.importing import import_prior
    from core.priors.diffusion.importing.safe_convert import GIB, ConvertLimits

    limits = ConvertLimits()
    if args.max_memory_gb is not None:
        limits = replace(limits, base_memory_bytes=int(args.max_memory_gb * GIB), memory_per_checkpoint_byte=0.0)
    if args.timeout_s is not None:
        limits = replace(limits, wall_seconds=float(args.timeout_s), cpu_seconds=int(args.timeout_s))
    try:
        report = import_prior(args.source, args.out, controlnet=args.controlnet, vae=args.vae, lora=args.lora,
                              layout=args.layout, conditioning=args.conditioning, profile=args.profile,
                              lora_scale=args.lora_scale, variant=args.variant, limits=limits)
    except PriorError as exc:
        print(f"lightfield prior import: {exc}", file=sys.stderr)
        return 2
    card = report.card
    print(
        f"wrote {report.out_dir} (layout {report.layout}: {card.base_family}, UNet in_channels "
        f"{card.unet_in_channels}, "
        f"{card.controlnet_conditioning} ControlNet, profile {card.profile}, "
        f"{'multi-ball' if card.multi_ball else 'single ball'}, resolution {list(card.resolution)})"
    )
    if report.converted:
        print(f"converted from pickled .bin (weights-only, bounded child): {', '.join(report.converted)}")
    for note in report.notes:
        print(note)
    return 0
