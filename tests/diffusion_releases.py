"""Tiny random stand-ins laid out EXACTLY as the real releases are, for the importer's tests (test code:
it lives here, not in the engine, because only tests/test_diffusion_import.py writes these folders).

* `write_authors_release`: ORionTMT/Sig25_4DLighting's `Multi_Inpaint` -- a diffusers SD-2
  inpainting pipeline folder (model_index.json, 9-channel UNet, pickled `*.bin` weights,
  a PNDM scheduler config as SD-2 inpainting ships, a feature extractor the import ignores,
  a VAE with the deprecated attention key names of 2022 checkpoints) and, separately, a
  depth ControlNet folder named like `thibaud/controlnet-sd21-depth-diffusers`.
* `write_diffusionlight_sdxl_release`: SDXL base (4-channel UNet, two text encoders,
  fp16-variant safetensors only), the fp16-fix VAE folder, `controlnet-depth-sdxl-1.0`
  (fp16 variant) and the LoRA checkpoint folder (`pytorch_lora_weights.safetensors` in the
  old diffusers "lora.down/lora.up" key format, beside the optimizer / RNG pickles that the
  training script leaves there and the import must never open).
* `write_diffusionlight_sd2_release`: SD-2 inpainting + `controlnet-sd21-normalbae-diffusers`.

The models are the tiny architectures of tiny.py (noise-like outputs); only layout,
formats, names and shapes matter here.
"""
from __future__ import annotations

import json
from pathlib import Path

import torch

from core.priors.diffusion.loading import quiet_loading
from core.priors.diffusion.tiny import (
    TinyConfig,
    tiny_controlnet,
    tiny_text_encoder,
    tiny_unet,
    tiny_vae,
    write_byte_level_tokenizer,
)

SD2_PNDM = {"_class_name": "PNDMScheduler", "_diffusers_version": "0.8.0", "beta_end": 0.012,
            "beta_schedule": "scaled_linear", "beta_start": 0.00085, "clip_sample": False, "num_train_timesteps": 1000,
            "set_alpha_to_one": False, "skip_prk_steps": True, "steps_offset": 1, "trained_betas": None}
SDXL_EULER = {"_class_name": "EulerDiscreteScheduler", "beta_end": 0.012, "beta_schedule": "scaled_linear",
              "beta_start": 0.00085, "interpolation_type": "linear", "num_train_timesteps": 1000,
              "prediction_type": "epsilon", "steps_offset": 1, "timestep_spacing": "leading", "trained_betas": None,
              "use_karras_sigmas": False}


def _vocab_size(tok_dir: Path) -> int:
    return len(json.loads((tok_dir / "vocab.json").read_text(encoding="utf-8")))


def _save_diffusers(model, folder: Path, fmt: str) -> None:
    """fmt: "bin" (pickled), "safetensors", or "fp16" (the fp16 variant only)."""
    if fmt == "fp16":
        model.half().save_pretrained(folder, variant="fp16", safe_serialization=True)
    else:
        model.save_pretrained(folder, safe_serialization=(fmt == "safetensors"))


def _save_transformers(model, folder: Path, fmt: str) -> None:
    from safetensors.torch import load_file, save_file  # noqa: PLC0415 — safetensors is heavy: imported when used

    model.save_pretrained(folder)
    st = folder / "model.safetensors"
    state = load_file(str(st))
    if fmt == "bin":
        torch.save(state, folder / "pytorch_model.bin")
        st.unlink()
    elif fmt == "fp16":
        save_file(
            {k: v.half() for k, v in state.items()}, str(folder / "model.fp16.safetensors"), metadata={"format": "pt"}
        )
        st.unlink()


def _deprecate_vae_attention_keys(folder: Path) -> None:
    """Rewrite the VAE's .bin with the pre-2023 attention names (query/key/value/proj_attn)."""
    path = folder / "diffusion_pytorch_model.bin"
    state = torch.load(path, weights_only=True)
    renamed = {}
    for k, v in state.items():
        for new, old in (("to_q", "query"), ("to_k", "key"), ("to_v", "value"), ("to_out.0", "proj_attn")):
            if "mid_block.attentions.0." in k and f".{new}." in k:
                k = k.replace(f".{new}.", f".{old}.")
        renamed[k] = v
    torch.save(renamed, path)


def _model_index(folder: Path, cls: str, parts: dict[str, list[str]]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "model_index.json").write_text(
        json.dumps({"_class_name": cls, "_diffusers_version": "0.21.4", **parts}, indent=2)
    )


def write_authors_release(root: str | Path, config: TinyConfig = TinyConfig(resolution=(32, 32))) -> tuple[Path, Path]:
    """(pipeline folder, ControlNet folder) in the authors' release layout, all weights pickled .bin."""
    root = Path(root)
    pipe, cn = root / "Multi_Inpaint", root / "controlnet-sd21-depth-diffusers"
    with torch.random.fork_rng(devices=[]), _quiet():
        torch.manual_seed(config.seed)
        _model_index(
            pipe,
            "StableDiffusionInpaintPipeline",
            {
                "unet": ["diffusers", "UNet2DConditionModel"],
                "vae": ["diffusers", "AutoencoderKL"],
                "text_encoder": ["transformers", "CLIPTextModel"],
                "tokenizer": ["transformers", "CLIPTokenizer"],
                "scheduler": ["diffusers", "PNDMScheduler"],
                "feature_extractor": [None, None],
                "safety_checker": [None, None],
            },
        )
        write_byte_level_tokenizer(pipe / "tokenizer")
        unet = tiny_unet(config)
        _save_diffusers(tiny_controlnet(unet, config), cn, "bin")
        _save_diffusers(unet, pipe / "unet", "bin")
        _save_diffusers(tiny_vae(config), pipe / "vae", "bin")
        _deprecate_vae_attention_keys(pipe / "vae")
        _save_transformers(tiny_text_encoder(config, _vocab_size(pipe / "tokenizer")), pipe / "text_encoder", "bin")
        (pipe / "scheduler").mkdir()
        (pipe / "scheduler" / "scheduler_config.json").write_text(json.dumps(SD2_PNDM))
        (pipe / "feature_extractor").mkdir()
        (pipe / "feature_extractor" / "preprocessor_config.json").write_text("{}")
    return pipe, cn


def tiny_sdxl_unet(config: TinyConfig, text_hidden: int = 32, projection: int = 32, time_embed: int = 8):
    """An SDXL-shaped UNet: 4 input channels, 'text_time' added conditioning, two encoders' width."""
    from diffusers import UNet2DConditionModel  # noqa: PLC0415 — diffusers is heavy: imported when used

    return UNet2DConditionModel(
        sample_size=config.resolution[0] // 8, in_channels=4, out_channels=4,
        down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"), up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"),
        block_out_channels=config.unet_channels, layers_per_block=1, cross_attention_dim=2 * text_hidden,
        attention_head_dim=(2, 4), use_linear_projection=True, addition_embed_type="text_time",
        addition_time_embed_dim=time_embed, projection_class_embeddings_input_dim=6 * time_embed + projection,
        norm_num_groups=8,
    )


def tiny_text_encoder_2(config: TinyConfig, vocab_size: int, projection: int = 32):
    from transformers import CLIPTextConfig, CLIPTextModelWithProjection  # noqa: PLC0415 — transformers is heavy: imported when used

    return CLIPTextModelWithProjection(CLIPTextConfig(
        vocab_size=vocab_size, hidden_size=config.text_hidden, intermediate_size=2 * config.text_hidden,
        num_hidden_layers=2, num_attention_heads=2, max_position_embeddings=77, projection_dim=projection,
        bos_token_id=vocab_size - 2, eos_token_id=vocab_size - 1, pad_token_id=vocab_size - 1))


def tiny_lora_state(unet, rank: int = 4, seed: int = 1) -> dict[str, torch.Tensor]:
    """A LoRA on every attention projection, in diffusers' pre-peft key format
    ('unet.<module>.lora.down.weight' / '.lora.up.weight'), as 2023 training scripts saved it."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for name, mod in unet.named_modules():
        if (
            isinstance(mod, torch.nn.Linear)
            and name.split(".")[-1] in ("to_q", "to_k", "to_v")
            and "attentions" in name
        ):
            out[f"unet.{name}.lora.down.weight"] = 0.1 * torch.randn(rank, mod.in_features, generator=g)
            out[f"unet.{name}.lora.up.weight"] = 0.1 * torch.randn(mod.out_features, rank, generator=g)
    return out


def write_diffusionlight_sdxl_release(root: str | Path, config: TinyConfig = TinyConfig(resolution=(64, 64))):
    """(SDXL folder, ControlNet folder, VAE folder, LoRA folder) in DiffusionLight's layout."""
    from diffusers import ControlNetModel  # noqa: PLC0415 — diffusers is heavy: imported when used
    from safetensors.torch import save_file  # noqa: PLC0415 — safetensors is heavy: imported when used

    root = Path(root)
    sdxl, cn, vae_dir = (
        root / "stable-diffusion-xl-base-1.0",
        root / "controlnet-depth-sdxl-1.0",
        root / "sdxl-vae-fp16-fix",
    )
    lora_dir = root / "ThisIsTheFinal-lora-hdr-continuous-largeT@900" / "0_-5" / "checkpoint-2500"
    with torch.random.fork_rng(devices=[]), _quiet():
        torch.manual_seed(config.seed)
        _model_index(
            sdxl,
            "StableDiffusionXLPipeline",
            {
                "unet": ["diffusers", "UNet2DConditionModel"],
                "vae": ["diffusers", "AutoencoderKL"],
                "text_encoder": ["transformers", "CLIPTextModel"],
                "text_encoder_2": ["transformers", "CLIPTextModelWithProjection"],
                "tokenizer": ["transformers", "CLIPTokenizer"],
                "tokenizer_2": ["transformers", "CLIPTokenizer"],
                "scheduler": ["diffusers", "EulerDiscreteScheduler"],
                "force_zeros_for_empty_prompt": True,
            },
        )
        write_byte_level_tokenizer(sdxl / "tokenizer")
        write_byte_level_tokenizer(sdxl / "tokenizer_2")
        vocab = _vocab_size(sdxl / "tokenizer")
        unet = tiny_sdxl_unet(config)
        save_file(
            tiny_lora_state(unet), str(_mkdir(lora_dir) / "pytorch_lora_weights.safetensors"), metadata={"format": "pt"}
        )
        for junk in ("optimizer.bin", "scheduler.bin", "random_states_0.pkl"):  # the training script's pickles
            (lora_dir / junk).write_bytes(b"\x80\x04not-a-weights-file")
        _save_diffusers(ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(4, 8, 8, 16)), cn, "fp16")
        _save_diffusers(unet, sdxl / "unet", "fp16")
        _save_diffusers(tiny_vae(config), sdxl / "vae", "fp16")
        _save_diffusers(tiny_vae(config), vae_dir, "safetensors")
        _save_transformers(tiny_text_encoder(config, vocab), sdxl / "text_encoder", "fp16")
        _save_transformers(tiny_text_encoder_2(config, vocab), sdxl / "text_encoder_2", "fp16")
        (sdxl / "scheduler").mkdir()
        (sdxl / "scheduler" / "scheduler_config.json").write_text(json.dumps(SDXL_EULER))
    return sdxl, cn, vae_dir, lora_dir


def write_diffusionlight_sd2_release(root: str | Path, config: TinyConfig = TinyConfig(resolution=(32, 32))):
    """(SD-2 inpainting folder, normal-map ControlNet folder), safetensors as the hub serves them."""
    root = Path(root)
    pipe, cn = root / "stable-diffusion-2-inpainting", root / "controlnet-sd21-normalbae-diffusers"
    with torch.random.fork_rng(devices=[]), _quiet():
        torch.manual_seed(config.seed + 7)
        _model_index(pipe, "StableDiffusionInpaintPipeline", {
            "unet": ["diffusers", "UNet2DConditionModel"], "vae": ["diffusers", "AutoencoderKL"],
            "text_encoder": ["transformers", "CLIPTextModel"], "tokenizer": ["transformers", "CLIPTokenizer"],
            "scheduler": ["diffusers", "PNDMScheduler"]})
        write_byte_level_tokenizer(pipe / "tokenizer")
        unet = tiny_unet(config)
        _save_diffusers(tiny_controlnet(unet, config), cn, "safetensors")
        _save_diffusers(unet, pipe / "unet", "safetensors")
        _save_diffusers(tiny_vae(config), pipe / "vae", "safetensors")
        _save_transformers(
            tiny_text_encoder(config, _vocab_size(pipe / "tokenizer")), pipe / "text_encoder", "safetensors"
        )
        (pipe / "scheduler").mkdir()
        (pipe / "scheduler" / "scheduler_config.json").write_text(json.dumps(SD2_PNDM))
    return pipe, cn


def _quiet():
    return quiet_loading()


def _mkdir(p: Path) -> Path:
    p.mkdir(parents=True, exist_ok=True)
    return p
