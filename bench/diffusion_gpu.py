"""GPU readiness of the diffusion prior: the `paper` preset's distillation target at real SD-2
sizes (random weights, exact architectures), timed on a CUDA device.

Builds the SD-2 inpainting UNet (866 M), SD-2.1 ControlNet (364 M) and SD VAE (84 M) with
random weights (bench/diffusion_step.sd2_components), moves them to the device in fp16 or
bf16, optionally `torch.compile`s the UNet and ControlNet, and runs `--steps` prior calls
exactly as the engine's `paper` preset issues them (N = 9 balls, guidance 12.5 batched CFG,
tau from the preset's annealed schedule, k = ceil(10 tau) DDIM steps, VAE encode + decode).

Reports seconds per prior call (= per distillation step; the field's own update is
milliseconds), seconds per DDIM step, peak GPU memory, the attention backend, and a
projection: preset iterations x mean seconds per step, next to the paper's 40 min for a
100-frame video on an A6000 (the paper's iteration budget does not grow with frames; the
projection assumes the preset's `iterations`, printed with it).

    python bench/diffusion_gpu.py --dtype bf16 --steps 30 [--compile] [--attention sdpa|math]
    python bench/diffusion_gpu.py --tiny --device cpu --steps 2    # smoke test, any machine

Nothing here is measured on this project's CI machines (no GPU); the script prints JSON.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import torch  # noqa: E402

PAPER_MINUTES_A6000_100_FRAMES = 40.0


def build(tiny: bool, tmp: Path, device: str, dtype: torch.dtype):
    from dataclasses import replace

    from core.priors.diffusion.loading import load_components
    from core.priors.diffusion.tiny import TinyConfig, build_tiny_model

    if tiny:
        comps = load_components(
            build_tiny_model(tmp, TinyConfig(resolution=(64, 64))), device="cpu", dtype=torch.float32
        )
    else:
        from bench.diffusion_step import sd2_components

        comps = sd2_components(tmp, 512)
    for m in (comps.unet, comps.controlnet, comps.vae, comps.text_encoder):
        m.to(device=device, dtype=dtype)
    return replace(comps, device=torch.device(device), dtype=dtype)


def main(argv=None) -> dict:
    from core.engine.presets import preset
    from core.priors.diffusion.prior import DiffusionPrior

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--dtype", choices=["fp16", "bf16", "fp32"], default="bf16")
    ap.add_argument("--steps", type=int, default=30, help="distillation steps timed (after --warmup)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--compile", action="store_true", help="torch.compile the UNet and ControlNet")
    ap.add_argument("--attention", choices=["sdpa", "math", "default"], default="default",
                    help="force a scaled-dot-product-attention backend (sdpa: flash / memory-efficient)")
    ap.add_argument("--frame", default="512x512", help="frame HxW (the paper preset's work height is 512)")
    ap.add_argument("--tiny", action="store_true", help="the tiny random model (smoke test on CPU)")
    args = ap.parse_args(argv)
    dtype = {"fp16": torch.float16, "bf16": torch.bfloat16, "fp32": torch.float32}[args.dtype]
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("no CUDA device: run with --tiny --device cpu for a smoke test")
    h, w = (int(v) for v in args.frame.lower().split("x"))
    cfg = preset("paper").distill
    cuda = args.device.startswith("cuda")
    with tempfile.TemporaryDirectory() as tmp:
        comps = build(args.tiny, Path(tmp), args.device, dtype)
        if args.compile:
            comps.unet = torch.compile(comps.unet)
            comps.controlnet = torch.compile(comps.controlnet)
        prior = DiffusionPrior(comps, profile="paper")
        from bench.diffusion_step import request

        backend = _attention_context(args.attention)
        gen = torch.Generator().manual_seed(0)
        taus = [float(cfg.tau_min_at(s) + (cfg.tau_max - cfg.tau_min_at(s)) * torch.rand(1, generator=gen))
                for s in torch.linspace(0, cfg.iterations - 1, args.warmup + args.steps).long().tolist()]
        if cuda:
            torch.cuda.reset_peak_memory_stats()
        times, ddim = [], []
        with backend, torch.inference_mode():
            for i, tau in enumerate(taus):
                req = request(h, w, tau, i)
                req.guidance_scale = cfg.guidance_scale
                if cuda:
                    torch.cuda.synchronize()
                t0 = time.perf_counter()
                prior(req)
                if cuda:
                    torch.cuda.synchronize()
                if i >= args.warmup:
                    times.append(time.perf_counter() - t0)
                    ddim.append(math.ceil(10 * tau))
        mean = statistics.fmean(times)
        out = {
            "model": "tiny" if args.tiny else "SD-2 inpainting UNet + SD-2.1 ControlNet + SD VAE (random weights)",
            "device": torch.cuda.get_device_name() if cuda else args.device, "dtype": args.dtype,
            "compile": args.compile, "attention": args.attention, "frame": [h, w],
            "model_size": list(prior.model_size(h, w)), "balls": 9, "guidance_scale": cfg.guidance_scale,
            "steps_timed": len(times), "seconds_per_step_mean": round(mean, 4),
            "seconds_per_step_median": round(statistics.median(times), 4),
            "seconds_per_ddim_step": round(sum(times) / max(1, sum(ddim)), 4),
            "peak_gpu_memory_gib": round(torch.cuda.max_memory_allocated() / 2**30, 3) if cuda else None,
            "projection": {"iterations": cfg.iterations, "minutes": round(cfg.iterations * mean / 60, 1),
                           "paper_minutes_a6000_100_frames": PAPER_MINUTES_A6000_100_FRAMES,
                           "assumes": "paper preset iterations x mean prior step; field update and I/O excluded"},
            "torch": torch.__version__,
        }
    print(json.dumps(out, indent=2))
    return out


def _attention_context(kind: str):
    import contextlib

    if kind == "default":
        return contextlib.nullcontext()
    from torch.nn.attention import SDPBackend, sdpa_kernel

    if kind == "math":
        return sdpa_kernel([SDPBackend.MATH])
    return sdpa_kernel([SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.MATH])


if __name__ == "__main__":
    main()
