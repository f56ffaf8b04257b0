"""`lightfield prior import`: turn weights as they are released into a local prior directory.

Layouts (docs/diffusion-prior.md, "Importing released weights"):

* `authors` -- the paper's fine-tuned multi-ball model as ORionTMT/Sig25_4DLighting releases
  it (`Multi_Inpaint`): a diffusers SD-2 inpainting pipeline folder (9-channel UNet) that
  their code loads with `from_pretrained`, and the STOCK depth ControlNet
  (`thibaud/controlnet-sd21-depth-diffusers`) as a separate folder (`--controlnet`).
  Card: multi-ball, the paper's prompts, profile `seed`.
* `diffusionlight-sdxl` -- DiffusionLight (Phongthawee et al., CVPR 2024): SDXL base pipeline
  folder (4-channel UNet: it inpaints by latent blending), its exposure LoRA (`--lora`,
  `pytorch_lora_weights.safetensors`, fused at scale 0.75), a depth ControlNet
  (`diffusers/controlnet-depth-sdxl-1.0`, `--controlnet`), optionally the fp16-fix VAE
  (`madebyollin/sdxl-vae-fp16-fix`, `--vae`). Card: single ball, its prompts, profile
  `diffusionlight`, UniPC sampler, 30 steps, guidance 5, ControlNet scale 0.5.
* `diffusionlight-sd2` -- DiffusionLight's SD-2 option: SD-2 inpainting + a NORMAL-map
  ControlNet (`thibaud/controlnet-sd21-normalbae-diffusers`).

Every weight file becomes safetensors (pickled `.bin` through the bounded converter in
safe_convert.py), every tensor's shape is checked against its config, only configs and
tokenizer text files are copied, and the card -- written last -- records the sources,
conversions and SHA-256 of every weight file. Nothing is downloaded.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from core.priors.base import PriorError
from core.priors.diffusion.card import CARD_FILENAME, ExposurePrompts, LoraSpec, ModelCard
from core.priors.diffusion.importing.safe_convert import ConvertLimits
from core.priors.diffusion.importing.weights import (
    convert_pickles,
    convert_weights,
    expected_shapes,
    find_weight_files,
    header_shapes,
)
from core.priors.diffusion.loading import load_components
from core.priors.diffusion.profiles import get_profile

LAYOUTS = ("authors", "diffusionlight-sdxl", "diffusionlight-sd2")
TOKENIZER_FILES = ("vocab.json", "merges.txt", "tokenizer.json", "tokenizer_config.json", "special_tokens_map.json",
                   "added_tokens.json")
MAX_JSON_BYTES = 4 << 20  # configs are a few kB; refuse anything absurd before parsing it
DL_PROMPTS = ExposurePrompts(max="a perfect mirrored reflective chrome ball sphere",
                             min="a perfect black dark mirrored reflective chrome ball sphere")
DL_NEGATIVE = "matte, diffuse, flat, dull"


@dataclass
class ImportReport:
    out_dir: Path
    layout: str
    card: ModelCard
    converted: list[str] = field(default_factory=list)  # sub-models that came from pickled .bin files
    notes: list[str] = field(default_factory=list)


def _read_json(path: Path, what: str) -> dict:
    if not path.is_file():
        raise PriorError(f"{what}: {path} is missing")
    if path.stat().st_size > MAX_JSON_BYTES:
        raise PriorError(f"{what}: {path} is larger than {MAX_JSON_BYTES} bytes; not a config")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PriorError(f"{what}: {path} is not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise PriorError(f"{what}: {path} must hold a JSON object")
    return data


def _sources(source: Path, controlnet: Path | None, vae: Path | None) -> dict[str, Path]:
    if not source.is_dir():
        raise PriorError(f"{source}: not an existing local directory (nothing is downloaded; "
                         "pass the folder you downloaded)")
    if (source / "config.json").is_file() and not (source / "unet").is_dir():
        raise PriorError(f"{source}: this is a single model folder, not a pipeline folder with unet/, vae/, "
                         "text_encoder/, tokenizer/, scheduler/ (a ControlNet folder goes to --controlnet)")
    dirs = {name: source / name for name in ("unet", "vae", "text_encoder", "tokenizer", "scheduler")}
    if (source / "text_encoder_2").is_dir() or (source / "tokenizer_2").is_dir():
        dirs.update(text_encoder_2=source / "text_encoder_2", tokenizer_2=source / "tokenizer_2")
    if vae is not None:
        dirs["vae"] = vae
    cn = controlnet if controlnet is not None else source / "controlnet"
    if not cn.is_dir():
        raise PriorError(
            f"{source}: no ControlNet: the pipeline folder has no controlnet/ and --controlnet was not given "
            "(the authors' release uses the stock thibaud/controlnet-sd21-depth-diffusers; DiffusionLight "
            "diffusers/controlnet-depth-sdxl-1.0 or thibaud/controlnet-sd21-normalbae-diffusers)")
    dirs["controlnet"] = cn
    missing = []
    for name, d in dirs.items():
        marker = (
            "scheduler_config.json" if name == "scheduler" else None if name.startswith("tokenizer") else "config.json"
        )
        if marker and not (d / marker).is_file():
            missing.append(f"{d}/{marker}")
        if name.startswith("tokenizer") and not ((d / "vocab.json").is_file() or (d / "tokenizer.json").is_file()):
            missing.append(f"{d}/vocab.json (or tokenizer.json)")
    if missing:
        raise PriorError(f"{source}: not a diffusers pipeline folder as released: missing {', '.join(missing)}")
    return dirs


def _conditioning(cn_dir: Path, cn_config: dict, given: str | None) -> str:
    """depth | normals: given, else from the ControlNet's folder name or recorded name (the rule both
    the authors' and DiffusionLight's `get_control_signal_type` apply to the hub id)."""
    if given is not None:
        if given not in ("depth", "normals"):
            raise PriorError(f"--conditioning must be depth or normals, got {given!r}")
        return given
    for text in (cn_dir.resolve().name, str(cn_config.get("_name_or_path", ""))):
        low = text.lower()
        if "normal" in low:
            return "normals"
        if "depth" in low:
            return "depth"
    raise PriorError(f"{cn_dir}: cannot tell whether this ControlNet expects depth or normals from its name; "
                     "pass --conditioning depth|normals")


def _family(unet_cfg: dict) -> str:
    if unet_cfg.get("addition_embed_type") == "text_time":
        return "sdxl"
    return "sd1" if unet_cfg.get("cross_attention_dim") == 768 else "sd2"


def _layout(given: str, family: str, in_channels: int, conditioning: str) -> str:
    auto = ("diffusionlight-sdxl" if family == "sdxl" else
            "diffusionlight-sd2" if conditioning == "normals" else "authors")
    layout = auto if given == "auto" else given
    if layout not in LAYOUTS:
        raise PriorError(f"unknown layout {given!r}; choose auto or one of {', '.join(LAYOUTS)}")
    need = {"authors": ("sd2", 9, "depth"), "diffusionlight-sdxl": ("sdxl", 4, "depth"),
            "diffusionlight-sd2": ("sd2", 9, "normals")}[layout]
    have = (family, in_channels, conditioning)
    if have != need:
        raise PriorError(f"layout {layout!r} is a {need[0]} UNet with {need[1]} input channels and a {need[2]} "
                         f"ControlNet; these files are a {family} UNet with {in_channels} input channels and a "
                         f"{conditioning} ControlNet")
    return layout


def _native_resolution(configs: dict) -> tuple[int, int]:
    """The UNet's trained size: sample_size latents x the VAE's downsampling (SD-2: 64 x 8 = 512, SDXL: 1024)."""
    sample = configs["unet"].get("sample_size") or 64
    factor = 2 ** (len(configs["vae"].get("block_out_channels") or [0] * 4) - 1)
    h, w = (sample, sample) if isinstance(sample, int) else tuple(sample)
    return int(h) * factor, int(w) * factor


def _card(layout: str, family: str, in_channels: int, conditioning: str, profile: str | None,
          lora_scale: float | None, has_lora: bool, resolution: tuple[int, int]) -> ModelCard:
    if layout == "authors":
        fields = dict(
            multi_ball=True,
            resolution=resolution,
            controlnet_conditioning_scale=1.0,
            default_guidance_scale=12.5,
            profile="seed",
            sampler="ddim",
            base="ORionTMT/Sig25_4DLighting Multi_Inpaint (SD-2 inpainting, fine-tuned multi-ball) + stock SD-2.1 "
                 "depth ControlNet",
        )
    else:
        fields = dict(
            multi_ball=False,
            prompts=DL_PROMPTS,
            negative_prompt=DL_NEGATIVE,
            controlnet_conditioning_scale=0.5,
            default_guidance_scale=5.0,
            profile="diffusionlight",
            sampler="unipc",
            sampling_steps=30,
            resolution=resolution,
            base=(
                "DiffusionLight: SDXL base + exposure LoRA + SDXL depth ControlNet"
                if family == "sdxl"
                else "DiffusionLight: SD-2 inpainting + SD-2.1 normal-map ControlNet"
            ),
        )
    if has_lora:
        fields["lora"] = LoraSpec(scale=0.75 if lora_scale is None else float(lora_scale))
    if profile is not None:
        fields["profile"] = profile
    return ModelCard(base_family=family, unet_in_channels=in_channels, controlnet_conditioning=conditioning, **fields)


def import_prior(
    source: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    controlnet: str | os.PathLike | None = None,
    vae: str | os.PathLike | None = None,
    lora: str | os.PathLike | None = None,
    layout: str = "auto",
    conditioning: str | None = None,
    profile: str | None = None,
    lora_scale: float | None = None,
    variant: str | None = None,
    limits: ConvertLimits = ConvertLimits(),
) -> ImportReport:
    """Build OUT_DIR from released folders (see the module docstring); PriorError names any problem."""
    os.environ["HF_HUB_OFFLINE"] = "1"
    source, out = Path(source).expanduser(), Path(out_dir).expanduser()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise PriorError(f"{out}: already exists and is not an empty directory; choose a new output directory")
    if profile is not None:
        get_profile(profile)  # PriorError naming the profiles
    dirs = _sources(
        source, Path(controlnet).expanduser() if controlnet else None, Path(vae).expanduser() if vae else None
    )
    configs = {k: _read_json(d / ("scheduler_config.json" if k == "scheduler" else "config.json"), k)
               for k, d in dirs.items() if not k.startswith("tokenizer")}
    unet_cfg = configs["unet"]
    family = _family(unet_cfg)
    in_channels = int(unet_cfg.get("in_channels", 4))
    cond = _conditioning(dirs["controlnet"], configs["controlnet"], conditioning)
    chosen = _layout(layout, family, in_channels, cond)
    lora_file = _lora_file(Path(lora).expanduser()) if lora else None
    if chosen == "diffusionlight-sdxl" and lora_file is None:
        raise PriorError(
            "DiffusionLight's SDXL layout needs its exposure LoRA: --lora DIR (the folder with "
            "pytorch_lora_weights.safetensors, e.g. "
            "models/ThisIsTheFinal-lora-hdr-continuous-largeT@900/0_-5/checkpoint-2500)"
        )
    if family == "sdxl" and "text_encoder_2" not in dirs:
        raise PriorError(f"{source}: an SDXL UNet needs text_encoder_2/ and tokenizer_2/ in the pipeline folder")
    _check_cross_attention(configs, family)
    card = _card(
        chosen, family, in_channels, cond, profile, lora_scale, lora_file is not None, _native_resolution(configs)
    )

    out.mkdir(parents=True, exist_ok=True)
    try:
        report = _write(dirs, configs, out, card, variant, limits, lora_file, chosen)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)  # never leave a half-written prior behind
        raise
    return report


def _lora_file(path: Path) -> Path:
    if path.is_dir():
        for name in ("pytorch_lora_weights.safetensors", "pytorch_lora_weights.bin"):
            if (path / name).is_file():
                return path / name
        raise PriorError(f"{path}: no pytorch_lora_weights.safetensors (or .bin) in the LoRA folder")
    if path.is_file() and path.suffix in (".safetensors", ".bin"):
        return path
    raise PriorError(f"{path}: not a LoRA folder or a .safetensors/.bin LoRA file")


def _check_cross_attention(configs: dict, family: str) -> None:
    width = int(configs["text_encoder"].get("hidden_size", 0))
    if family == "sdxl":
        width += int(configs["text_encoder_2"].get("hidden_size", 0))
    for name in ("unet", "controlnet"):
        cad = configs[name].get("cross_attention_dim")
        if cad != width:
            raise PriorError(
                f"{name}/config.json: cross_attention_dim={cad} does not match the text encoder width {width} "
                "(e.g. an SD-1.5 ControlNet with an SD-2 model)"
            )
    if configs["controlnet"].get("in_channels") != configs["vae"].get("latent_channels", 4):
        raise PriorError(f"controlnet/config.json: in_channels={configs['controlnet'].get('in_channels')} "
                         f"does not match the VAE's latent_channels={configs['vae'].get('latent_channels', 4)}")


def _write(dirs, configs, out: Path, card: ModelCard, variant, limits, lora_file, layout) -> ImportReport:
    report = ImportReport(out, layout, card)
    record = {"layout": layout, "tool": "lightfield prior import", "components": {}}
    models = [n for n in ("unet", "controlnet", "vae", "text_encoder", "text_encoder_2") if n in dirs]
    found = {n: find_weight_files(dirs[n], n.startswith("text_encoder"), variant) for n in models}
    pickles = [f for files, _ in found.values() for f in files] + ([lora_file] if lora_file is not None else [])
    workdir = out / ".import-tmp"
    workdir.mkdir()
    converted = convert_pickles(pickles, workdir, limits)
    for name in models:
        transformers = name.startswith("text_encoder")
        (out / name).mkdir()
        (out / name / "config.json").write_text(json.dumps(configs[name], indent=2) + "\n")
        target = out / name / ("model.safetensors" if transformers else "diffusion_pytorch_model.safetensors")
        kind = "text_encoder" if transformers else name
        files, used_variant = found[name]
        w = convert_weights(files, used_variant, converted, target, expected_shapes(kind, configs[name]),
                            f"{name} ({dirs[name]})")
        if w.converted_from_pickle:
            report.converted.append(name)
        report.notes += w.notes
        record["components"][name] = {"source": str(dirs[name]), "files": [Path(f).name for f in w.source_files],
                                      "from_pickle": w.converted_from_pickle, "variant": w.variant,
                                      "dtypes": w.dtypes, "tensors": w.tensors, "sha256": _sha256(target)}
    for name in ("tokenizer", "tokenizer_2"):
        if name in dirs:
            (out / name).mkdir()
            copied = [f for f in TOKENIZER_FILES if (dirs[name] / f).is_file()]
            for f in copied:
                shutil.copyfile(dirs[name] / f, out / name / f)
            record["components"][name] = {"source": str(dirs[name]), "files": copied}
    (out / "scheduler").mkdir()
    (out / "scheduler" / "scheduler_config.json").write_text(json.dumps(configs["scheduler"], indent=2) + "\n")
    if lora_file is not None:
        record["components"]["lora"] = _import_lora(lora_file, converted, out, report)
    shutil.rmtree(workdir)
    _check_variant_dtypes(record)
    card = card.model_copy(update={"imported": record})
    card.save(out)  # last: a directory with a card is complete
    report.card = card
    _verify_loads(out, report)
    return report


def _import_lora(lora_file: Path, converted: dict[Path, Path], out: Path, report: ImportReport) -> dict:
    (out / "lora").mkdir()
    target = out / "lora" / "pytorch_lora_weights.safetensors"
    if lora_file.suffix == ".bin":
        shutil.move(str(converted[lora_file]), target)
        report.converted.append("lora")
    else:
        shutil.copyfile(lora_file, target)
    keys = header_shapes(target)
    if not keys or not all("lora" in k for k in keys):
        raise PriorError(f"{lora_file}: not a LoRA (its tensor names do not all contain 'lora')")
    return {"source": str(lora_file), "from_pickle": lora_file.suffix == ".bin", "tensors": len(keys),
            "sha256": _sha256(target)}


def _check_variant_dtypes(record: dict) -> None:
    """A variant named fp16 must hold float16 tensors (a mislabelled file would silently change precision)."""
    for name, comp in record["components"].items():
        if comp.get("variant") == "fp16" and any(d not in ("F16", "float16") for d in comp.get("dtypes", [])):
            raise PriorError(f"{name}: the fp16 variant holds {comp['dtypes']} tensors")


def _verify_loads(out: Path, report: ImportReport) -> None:
    """Load the result the way run time does (local, safetensors only): a directory that imports runs."""
    comps = load_components(out, device="cpu", dtype="bfloat16")  # half the memory; nothing is computed
    del comps
    report.notes.append("verified: loads with the run-time loader (local files, safetensors only)")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


__all__ = ["CARD_FILENAME", "ImportReport", "LAYOUTS", "import_prior", "find_weight_files"]
