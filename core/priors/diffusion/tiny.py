"""Tiny, randomly initialised stand-ins for the real prior, for tests and CPU benchmarks.

`build_tiny_model(out_dir)` writes a complete model directory in exactly the layout real
weights use (diffusers sub-models, safetensors, model card), so tests exercise the same
local loader as production. The models produce noise-like images; only the plumbing
(shapes, conditioning, schedules, masking, determinism, training) is meaningful.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

from core.priors.diffusion.card import ModelCard
from core.priors.diffusion.loading import quiet_loading

# The CLIP tokenizer works on byte-level unicode symbols; without merges every character is a token.
_BOS, _EOS = "<|startoftext|>", "<|endoftext|>"


@dataclass(frozen=True)
class TinyConfig:
    resolution: tuple[int, int] = (64, 64)
    unet_channels: tuple[int, int] = (32, 64)  # ~1 M parameters with the settings below
    text_hidden: int = 32
    vae_channels: tuple[int, ...] = (8, 16, 16, 16)  # four levels: the same 8x downsampling as SD
    multi_ball: bool = True
    seed: int = 0


def _byte_symbols() -> list[str]:
    """GPT-2 / CLIP byte -> printable unicode table (each of the 256 bytes gets one symbol)."""
    printable = (
        list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    )
    codes = printable[:]
    n = 0
    for b in range(256):
        if b not in printable:
            printable.append(b)
            codes.append(256 + n)
            n += 1
    return [chr(c) for c in codes]


def write_byte_level_tokenizer(out_dir: Path, max_length: int = 77) -> None:
    """vocab.json + merges.txt for a CLIP tokenizer with single-byte tokens only (no merges)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    symbols = _byte_symbols()
    vocab = {s: i for i, s in enumerate(symbols)}
    vocab.update({s + "</w>": len(symbols) + i for i, s in enumerate(symbols)})
    vocab[_BOS] = len(vocab)
    vocab[_EOS] = len(vocab)
    (out_dir / "vocab.json").write_text(json.dumps(vocab, ensure_ascii=False))
    (out_dir / "merges.txt").write_text("#version: 0.2\n", encoding="utf-8")
    (out_dir / "tokenizer_config.json").write_text(
        json.dumps(
            {
                "tokenizer_class": "CLIPTokenizer",
                "model_max_length": max_length,
                "bos_token": _BOS,
                "eos_token": _EOS,
                "unk_token": _EOS,
                "pad_token": _EOS,
            }
        )
    )


def tiny_unet(cfg: TinyConfig, in_channels: int = 9):
    from diffusers import UNet2DConditionModel  # noqa: PLC0415 — diffusers is heavy: imported when used

    return UNet2DConditionModel(
        sample_size=cfg.resolution[0] // 8,
        in_channels=in_channels,
        out_channels=4,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        block_out_channels=cfg.unet_channels,
        layers_per_block=1,
        cross_attention_dim=cfg.text_hidden,
        attention_head_dim=8,
        norm_num_groups=8,
    )


def tiny_controlnet(unet, cfg: TinyConfig):
    """A depth ControlNet initialised from the UNet, as ControlNet training does.

    The ControlNet sees the 4-channel noisy latent (diffusers' inpainting pipelines feed it
    that, not the 9-channel UNet input), so it is derived from a 4-channel copy of the UNet
    whose conv_in keeps the UNet's weights for the noisy-latent channels.
    """
    from diffusers import ControlNetModel  # noqa: PLC0415 — diffusers is heavy: imported when used

    unet4 = tiny_unet(cfg, in_channels=4)
    state = unet.state_dict()
    state["conv_in.weight"] = state["conv_in.weight"][:, :4].clone()
    unet4.load_state_dict(state)
    # the conditioning embedding must downsample by the VAE factor (8 = 2^(4-1))
    return ControlNetModel.from_unet(unet4, conditioning_embedding_out_channels=(4, 8, 8, 16))


def tiny_vae(cfg: TinyConfig):
    from diffusers import AutoencoderKL  # noqa: PLC0415 — diffusers is heavy: imported when used

    n = len(cfg.vae_channels)
    return AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * n,
        up_block_types=("UpDecoderBlock2D",) * n,
        block_out_channels=cfg.vae_channels,
        layers_per_block=1,
        latent_channels=4,
        norm_num_groups=4,
        sample_size=cfg.resolution[0],
    )


def tiny_text_encoder(cfg: TinyConfig, vocab_size: int):
    from transformers import CLIPTextConfig, CLIPTextModel  # noqa: PLC0415 — transformers is heavy: imported when used

    config = CLIPTextConfig(
        vocab_size=vocab_size,
        hidden_size=cfg.text_hidden,
        intermediate_size=2 * cfg.text_hidden,
        num_hidden_layers=2,
        num_attention_heads=2,
        max_position_embeddings=77,
        bos_token_id=vocab_size - 2,
        eos_token_id=vocab_size - 1,
        pad_token_id=vocab_size - 1,
    )
    return CLIPTextModel(config)


def tiny_scheduler():
    from diffusers import DDIMScheduler  # noqa: PLC0415 — diffusers is heavy: imported when used

    # Stable Diffusion's training schedule.
    return DDIMScheduler(
        num_train_timesteps=1000,
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="scaled_linear",
        clip_sample=False,
        set_alpha_to_one=False,
        steps_offset=1,
        prediction_type="epsilon",
    )


def build_tiny_model(out_dir: str | Path, config: TinyConfig = TinyConfig()) -> Path:
    """Write a randomly initialised prior (all sub-models + model card) to `out_dir`."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with torch.random.fork_rng(devices=[]), quiet_loading():  # seeded init without touching the caller's RNG
        torch.manual_seed(config.seed)
        _write_models(out, config)
    ModelCard(
        resolution=config.resolution,
        multi_ball=config.multi_ball,
        default_guidance_scale=3.0,
        base="tiny random test model (core.priors.diffusion.tiny)",
    ).save(out)
    return out


def _write_models(out: Path, config: TinyConfig) -> None:
    write_byte_level_tokenizer(out / "tokenizer")
    vocab_size = len(json.loads((out / "tokenizer" / "vocab.json").read_text(encoding="utf-8")))
    unet = tiny_unet(config)
    tiny_controlnet(unet, config).save_pretrained(out / "controlnet", safe_serialization=True)
    unet.save_pretrained(out / "unet", safe_serialization=True)
    tiny_vae(config).save_pretrained(out / "vae", safe_serialization=True)
    tiny_text_encoder(config, vocab_size).save_pretrained(out / "text_encoder", safe_serialization=True)
    tiny_scheduler().save_pretrained(out / "scheduler")
