"""Load a diffusion prior from a LOCAL diffusers-format directory, never from the network.

Layout (see docs/diffusion-prior.md):

    MODEL_DIR/
      lightfield_prior.json     model card (core.priors.diffusion.card)
      unet/                     UNet2DConditionModel, in_channels = 9 (inpainting)
      controlnet/               ControlNetModel fed the depth map, in_channels = 4
      vae/                      AutoencoderKL
      text_encoder/             CLIPTextModel or CLIPTextModelWithProjection
      tokenizer/                CLIPTokenizer (vocab.json + merges.txt or tokenizer.json)
      scheduler/                scheduler_config.json (loaded as DDIMScheduler)
      text_encoder_2/, tokenizer_2/   SDXL only (card base_family "sdxl")
      lora/                     optional LoRA named by the card, fused into the UNet at load

Weights must be safetensors: pickled .bin checkpoints are refused (they execute code);
`lightfield prior import` converts released folders into this layout once.
"""
from __future__ import annotations

import contextlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from core.device import DeviceError, resolve_device as core_resolve_device
from core.priors.base import PriorError
from core.priors.diffusion.card import ModelCard

SUBFOLDERS = {
    "unet": "config.json",
    "controlnet": "config.json",
    "vae": "config.json",
    "text_encoder": "config.json",
    "tokenizer": None,  # vocab.json + merges.txt, or tokenizer.json
    "scheduler": "scheduler_config.json",
}

SDXL_SUBFOLDERS = {"text_encoder_2": "config.json", "tokenizer_2": None}

_DTYPES = {
    "float32": torch.float32, "fp32": torch.float32,
    "float16": torch.float16, "fp16": torch.float16, "half": torch.float16,
    "bfloat16": torch.bfloat16, "bf16": torch.bfloat16,
}


@dataclass
class PriorComponents:
    """The diffusers / transformers models of one prior, on one device and dtype, in eval mode."""

    unet: Any  # UNet2DConditionModel
    controlnet: Any  # ControlNetModel
    vae: Any  # AutoencoderKL
    text_encoder: Any  # CLIPTextModel | CLIPTextModelWithProjection
    tokenizer: Any  # CLIPTokenizer
    scheduler: Any  # DDIMScheduler
    card: ModelCard
    model_dir: Path
    device: torch.device
    dtype: torch.dtype
    text_encoder_2: Any = None  # SDXL: CLIPTextModelWithProjection
    tokenizer_2: Any = None

    @property
    def is_sdxl(self) -> bool:
        return self.card.base_family == "sdxl"

    @property
    def concat_inpaint(self) -> bool:
        """True for a 9-channel inpainting UNet (mask + masked-image latent concatenated);
        False for a base UNet that inpaints only by masked latent blending (DiffusionLight SDXL)."""
        return self.unet.config.in_channels != self.vae.config.latent_channels

    @property
    def vae_scale_factor(self) -> int:
        return 2 ** (len(self.vae.config.block_out_channels) - 1)

    @property
    def size_multiple(self) -> int:
        """Image sides must be multiples of this: VAE downsampling times UNet downsampling."""
        return self.vae_scale_factor * 2 ** (len(self.unet.config.block_out_channels) - 1)


def resolve_device(device: str | torch.device | None) -> torch.device:
    """The engine's rule (core.device): LIGHTFIELD_DEVICE overrides, None means 'auto'."""
    try:
        return core_resolve_device("auto" if device is None else str(device), source="prior device")
    except DeviceError as exc:
        raise PriorError(f"device: {exc}") from None


def resolve_dtype(dtype: str | torch.dtype | None, device: torch.device) -> torch.dtype:
    """CUDA defaults to bfloat16 where supported (no fp16 overflow in the VAE), else float16; CPU to float32."""
    if dtype is None:
        if device.type == "cuda":
            return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
        return torch.float32
    if isinstance(dtype, str):
        if dtype.lower() not in _DTYPES:
            raise PriorError(f"dtype: unknown {dtype!r}; use one of {sorted(set(_DTYPES))}")
        dtype = _DTYPES[dtype.lower()]
    if dtype not in (torch.float32, torch.float16, torch.bfloat16):
        raise PriorError(f"dtype: {dtype} is not a supported floating type")
    if device.type == "cpu" and dtype == torch.float16:
        raise PriorError("dtype: float16 is not supported on CPU; use float32 or bfloat16")
    return dtype


def check_model_dir(weights_dir: str | os.PathLike, sdxl: bool = False) -> Path:
    """Raise PriorError unless `weights_dir` is a local directory with every sub-model present."""
    path = Path(weights_dir).expanduser()
    if not path.is_dir():
        hint = (
            " It looks like a Hugging Face hub id; download the weights yourself and pass the local directory"
            if "/" in str(weights_dir) and not path.is_absolute() and not path.exists()
            else ""
        )
        raise PriorError(
            f"prior weights {str(weights_dir)!r} is not an existing local directory.{hint} "
            "(nothing is ever downloaded; see docs/diffusion-prior.md)"
        )
    missing = []
    subfolders = {**SUBFOLDERS, **(SDXL_SUBFOLDERS if sdxl else {})}
    for sub, marker in subfolders.items():
        d = path / sub
        if marker is not None and not (d / marker).is_file():
            missing.append(f"{sub}/{marker}")
        elif marker is None and not ((d / "tokenizer.json").is_file() or (d / "vocab.json").is_file()):
            missing.append(f"{sub}/vocab.json (or tokenizer.json)")
    if missing:
        raise PriorError(f"prior weights {str(path)!r} is missing: {', '.join(missing)}")
    return path


def _text_encoder_class(path: Path):
    from transformers import CLIPTextModel, CLIPTextModelWithProjection  # noqa: PLC0415 — transformers is heavy: imported when used

    archs = json.loads((path / "text_encoder" / "config.json").read_text()).get("architectures") or []
    return CLIPTextModelWithProjection if "CLIPTextModelWithProjection" in archs else CLIPTextModel


def load_components(
    weights_dir: str | os.PathLike, device: str | torch.device | None = None, dtype: str | torch.dtype | None = None
) -> PriorComponents:
    """Load every sub-model from disk (local_files_only, safetensors only) and validate that they fit together."""
    os.environ["HF_HUB_OFFLINE"] = "1"  # belt and braces: local_files_only below already forbids downloads
    path = check_model_dir(weights_dir)
    card = ModelCard.load(path)
    if card.base_family == "sdxl":
        check_model_dir(path, sdxl=True)
    dev = resolve_device(device)
    dt = resolve_dtype(dtype, dev)

    from diffusers import AutoencoderKL, ControlNetModel, DDIMScheduler, UNet2DConditionModel  # noqa: PLC0415 — diffusers is heavy: imported when used
    from transformers import CLIPTokenizer  # noqa: PLC0415 — transformers is heavy: imported when used

    common = dict(local_files_only=True, use_safetensors=True, torch_dtype=dt)
    try:
        with quiet_loading():
            unet = UNet2DConditionModel.from_pretrained(path, subfolder="unet", **common)
            controlnet = ControlNetModel.from_pretrained(path, subfolder="controlnet", **common)
            vae = AutoencoderKL.from_pretrained(path, subfolder="vae", **common)
            text_encoder = _text_encoder_class(path).from_pretrained(
                path / "text_encoder", local_files_only=True, use_safetensors=True, dtype=dt
            )
            tokenizer = CLIPTokenizer.from_pretrained(path / "tokenizer", local_files_only=True)
            scheduler = DDIMScheduler.from_pretrained(path, subfolder="scheduler", local_files_only=True)
            text_encoder_2 = tokenizer_2 = None
            if card.base_family == "sdxl":
                from transformers import CLIPTextModelWithProjection  # noqa: PLC0415 — transformers is heavy: imported when used

                text_encoder_2 = CLIPTextModelWithProjection.from_pretrained(
                    path / "text_encoder_2", local_files_only=True, use_safetensors=True, dtype=dt
                )
                tokenizer_2 = CLIPTokenizer.from_pretrained(path / "tokenizer_2", local_files_only=True)
    except (OSError, ValueError, EnvironmentError) as exc:
        raise PriorError(f"cannot load prior weights from {str(path)!r}: {exc}") from exc

    comps = PriorComponents(unet, controlnet, vae, text_encoder, tokenizer, scheduler, card, path, dev, dt,
                            text_encoder_2, tokenizer_2)
    _check_compatible(comps)
    if card.lora is not None:
        fuse_lora(unet, path / card.lora.file, card.lora.scale, sdxl=comps.is_sdxl)
    if text_encoder_2 is not None:
        text_encoder_2.to(dev).eval().requires_grad_(False)
    for m in (unet, controlnet, vae, text_encoder):
        m.to(dev).eval().requires_grad_(False)
    return comps


@contextlib.contextmanager
def quiet_loading():
    """Silence diffusers' / transformers' per-file loading bars (they clutter CLI and worker logs)."""
    import diffusers.utils.logging as dlog  # noqa: PLC0415 — diffusers is heavy: imported when used
    import transformers.utils.logging as tlog  # noqa: PLC0415 — transformers is heavy: imported when used

    saved = (dlog.is_progress_bar_enabled(), tlog.is_progress_bar_enabled())
    dlog.disable_progress_bar()
    tlog.disable_progress_bar()
    try:
        yield
    finally:
        if saved[0]:
            dlog.enable_progress_bar()
        if saved[1]:
            tlog.enable_progress_bar()


def fuse_lora(unet, lora_file: Path, scale: float, sdxl: bool) -> None:
    """Fuse a LoRA (any format diffusers reads: diffusers, peft or kohya keys) into the UNet's
    weights, w <- w + scale * dW, then drop the adapter layers so the UNet is plain again
    (what DiffusionLight's `pipe.fuse_lora(lora_scale=0.75)` leaves). Needs peft."""
    from safetensors.torch import load_file  # noqa: PLC0415 — safetensors is heavy: imported when used

    if not lora_file.is_file():
        raise PriorError(f"model card names LoRA {str(lora_file)!r}, which does not exist")
    try:
        import peft  # noqa: F401, PLC0415 — optional: probed here
    except ImportError as exc:
        raise PriorError(f"this prior has a LoRA; loading it needs the peft package ({exc})") from None
    from diffusers.loaders.lora_pipeline import StableDiffusionLoraLoaderMixin, StableDiffusionXLLoraLoaderMixin  # noqa: PLC0415 — diffusers is heavy: imported when used

    mixin = StableDiffusionXLLoraLoaderMixin if sdxl else StableDiffusionLoraLoaderMixin
    try:
        state, alphas = mixin.lora_state_dict(load_file(str(lora_file)), unet_config=unet.config)
        if any(not k.startswith("unet.") for k in state):
            bad = sorted(k for k in state if not k.startswith("unet."))[:3]
            raise PriorError(f"{lora_file}: only UNet LoRAs are supported, found keys such as {bad}")
        with quiet_loading():
            mixin.load_lora_into_unet(state, alphas, unet, adapter_name="lightfield")
        unet.fuse_lora(lora_scale=float(scale))
        unet.unload_lora()
    except PriorError:
        raise
    except (ValueError, KeyError, RuntimeError) as exc:
        raise PriorError(f"cannot apply LoRA {str(lora_file)!r} to the UNet: {exc}") from exc


def _check_compatible(c: PriorComponents) -> None:
    latent = c.vae.config.latent_channels
    in_ch, card = c.unet.config.in_channels, c.card
    if in_ch != card.unet_in_channels:
        raise PriorError(
            f"unet.in_channels is {in_ch} but the model card declares unet_in_channels={card.unet_in_channels}"
        )
    if in_ch not in (2 * latent + 1, latent):
        raise PriorError(
            f"unet.in_channels is {in_ch}, expected {2 * latent + 1} (inpainting UNet: noisy latent + mask + "
            f"masked-image latent) or {latent} (base UNet inpainting by latent blending)"
        )
    if c.controlnet.config.in_channels != latent:
        raise PriorError(f"controlnet.in_channels is {c.controlnet.config.in_channels}, expected {latent}")
    addition = getattr(c.unet.config, "addition_embed_type", None)
    if c.is_sdxl != (addition == "text_time"):
        raise PriorError(
            f"unet.addition_embed_type={addition!r} does not fit the model card's base_family={card.base_family!r} "
            "(SDXL UNets have 'text_time', SD 1.x/2.x none)"
        )
    hidden = c.text_encoder.config.hidden_size + (c.text_encoder_2.config.hidden_size if c.is_sdxl else 0)
    if c.unet.config.cross_attention_dim != hidden:
        raise PriorError(
            f"unet.cross_attention_dim={c.unet.config.cross_attention_dim} does not match "
            f"the text encoder width {hidden}"
        )
    m = c.size_multiple
    h, w = c.card.resolution
    if h % m or w % m:
        raise PriorError(f"model card resolution {[h, w]} must be multiples of {m} for this UNet/VAE")
