"""Time of one distillation step of the diffusion prior (the pseudo-target), and of one
fine-tuning step, on this machine's CPU.

* `--arch tiny`: the tiny random model of core.priors.diffusion.tiny, loaded through the
  same local loader as real weights (what the tests use).
* `--arch sd2`: randomly initialised networks with the exact architecture of an SD-2
  inpainting UNet (865 M parameters), an SD-2.1 depth ControlNet and the SD VAE, built in
  memory (no weights needed), so the compute per step is the real model's. The text
  encoder is a 1-layer stand-in of the right width: it runs once at load, not per step.

For each tau: wall time of `prior(request)` (k = ceil(10 tau) DDIM steps, CFG batched into
one UNet call per step, VAE encode + decode), the UNet+ControlNet share, and the parameter
counts (fp16 weight memory = 2 bytes each). Prints one JSON document.

    python bench/diffusion_step.py --arch tiny --threads 1
    python bench/diffusion_step.py --arch sd2 --taus 0.1 --repeats 1 --threads 2
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import torch  # noqa: E402

from core.camera import Camera, Intrinsics, identity_pose  # noqa: E402
from core.priors.base import PriorRequest, ProbeGeometry  # noqa: E402
from core.priors.diffusion.card import ModelCard  # noqa: E402
from core.priors.diffusion.loading import PriorComponents, load_components  # noqa: E402
from core.priors.diffusion.prior import DiffusionPrior  # noqa: E402
from core.priors.diffusion.tiny import TinyConfig, build_tiny_model, tiny_scheduler, write_byte_level_tokenizer  # noqa: E402


def sd2_components(tmp: Path, resolution: int) -> PriorComponents:
    """SD-2 inpainting UNet + SD-2.1 depth ControlNet + SD VAE architectures, random weights."""
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    arch = dict(attention_head_dim=(5, 10, 20, 20), cross_attention_dim=1024, use_linear_projection=True)
    unet = UNet2DConditionModel(in_channels=9, sample_size=resolution // 8, **arch)
    controlnet = ControlNetModel(in_channels=4, **arch)
    vae = AutoencoderKL(
        down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
        block_out_channels=(128, 256, 512, 512), layers_per_block=2, sample_size=resolution,
    )
    write_byte_level_tokenizer(tmp / "tokenizer")
    tokenizer = CLIPTokenizer.from_pretrained(tmp / "tokenizer", local_files_only=True)
    text = CLIPTextModel(CLIPTextConfig(vocab_size=len(tokenizer), hidden_size=1024, intermediate_size=1024,
                                        num_hidden_layers=1, num_attention_heads=16, max_position_embeddings=77,
                                        bos_token_id=len(tokenizer) - 2, eos_token_id=len(tokenizer) - 1))
    for m in (unet, controlnet, vae, text):
        m.eval().requires_grad_(False)
    card = ModelCard(resolution=(resolution, resolution))
    return PriorComponents(
        unet, controlnet, vae, text, tokenizer, tiny_scheduler(), card, tmp, torch.device("cpu"), torch.float32
    )


def request(height: int, width: int, tau: float, seed: int) -> PriorRequest:
    """Nine balls (the paper's N) on a 3 x 3 grid, each 1/4 of the frame's short side... clipped to fit."""
    yy, xx = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    r = 0.08 * min(height, width)
    masks = torch.stack([
        (((yy - (i + 0.5) * height / 3) ** 2 + (xx - (j + 0.5) * width / 3) ** 2) < r * r).float()
        for i in range(3) for j in range(3)
    ])
    cam = Camera(Intrinsics.from_hfov(width, height), identity_pose())
    probes = ProbeGeometry(torch.zeros(9, 3), torch.ones(9), torch.zeros(9, 2), cam, 0, 0.0)
    return PriorRequest(
        image=torch.rand(3, height, width, generator=torch.Generator().manual_seed(seed)), ball_masks=masks,
        depth=torch.full((height, width), 2.0), ev=-2.0, tau=tau, steps=math.ceil(10 * tau), guidance_scale=3.0,
        probes=probes, generator=torch.Generator().manual_seed(seed),
    )


def time_network(prior: DiffusionPrior) -> tuple[list[float], callable]:
    """Accumulate wall time spent inside ControlNet + UNet forward calls."""
    spent: list[float] = []
    start: dict[int, float] = {}
    handles = []
    for m in (prior.components.controlnet, prior.components.unet):
        handles.append(m.register_forward_pre_hook(lambda mod, a: start.__setitem__(id(mod), time.perf_counter())))
        handles.append(m.register_forward_hook(lambda mod, a, o: spent.append(time.perf_counter() - start[id(mod)])))
    return spent, lambda: [h.remove() for h in handles]


def train_step_seconds(comps: PriorComponents, size: tuple[int, int], repeats: int) -> float:
    """One fine-tuning forward + backward at micro-batch 1 (median of `repeats`)."""
    from core.priors.diffusion.network import InpaintNetwork

    net = InpaintNetwork(comps.unet, comps.controlnet).requires_grad_(True).train()
    f = 2 ** (len(comps.vae.config.block_out_channels) - 1)
    h, w = size[0] // f, size[1] // f
    hidden = comps.text_encoder.config.hidden_size
    times = []
    for _ in range(repeats):
        x = torch.randn(1, 4, h, w)
        t0 = time.perf_counter()
        out = net(
            x, torch.tensor([500]), torch.randn(1, 77, hidden), torch.ones(1, 1, h, w), x, torch.rand(1, 3, *size)
        )
        out.square().mean().backward()
        times.append(time.perf_counter() - t0)
    net.zero_grad(set_to_none=True)
    net.requires_grad_(False).eval()
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", choices=["tiny", "sd2"], default="tiny")
    ap.add_argument("--height", type=int, default=96, help="frame height (the engine's draft work height is 96)")
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--resolution", type=int, default=None, help="model resolution (tiny: 64, sd2: 512)")
    ap.add_argument("--taus", default="0.1,0.5,1.0")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--train", action="store_true", help="also time one fine-tuning step")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        if args.arch == "tiny":
            res = args.resolution or 64
            comps = load_components(build_tiny_model(Path(tmp), TinyConfig(resolution=(res, res))))
        else:
            comps = sd2_components(Path(tmp), args.resolution or 512)
        prior = DiffusionPrior(comps)
        load_s = time.perf_counter() - t0
        params = {n: sum(p.numel() for p in getattr(comps, n).parameters()) for n in ("unet", "controlnet", "vae")}
        size = prior.model_size(args.height, args.width)
        rows = []
        for tau in [float(t) for t in args.taus.split(",")]:
            prior(request(args.height, args.width, tau, 0))  # warm-up (allocator, kernels)
            walls, nets = [], []
            for r in range(args.repeats):
                spent, stop = time_network(prior)
                t1 = time.perf_counter()
                prior(request(args.height, args.width, tau, r))
                walls.append(time.perf_counter() - t1)
                nets.append(sum(spent))
                stop()
            steps = math.ceil(10 * tau)
            rows.append({"tau": tau, "ddim_steps": steps, "seconds_median": round(statistics.median(walls), 4),
                         "seconds_per_ddim_step": round(statistics.median(walls) / steps, 4),
                         "unet_controlnet_share": round(statistics.median(nets) / statistics.median(walls), 3)})
        result = {
            "arch": args.arch, "frame": [args.height, args.width], "model_size": list(size), "balls": 9,
            "guidance_scale": 3.0, "threads": args.threads, "setup_seconds": round(load_s, 2),
            "params": params, "fp16_weight_gib": round(2 * sum(params.values()) / 2**30, 3),
            "peak_rss_gib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 3),
            "per_tau": rows,
        }
        if args.train:
            result["train_step_seconds_micro_batch_1"] = round(train_step_seconds(comps, size, args.repeats), 4)
        result["machine"] = {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                             "load_avg": [round(x, 2) for x in os.getloadavg()], "torch": torch.__version__}
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
