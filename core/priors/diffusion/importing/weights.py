"""Find one sub-model's weight files in a released folder, convert them to one safetensors
file, and check every tensor's name and shape against what its config builds.

Released folders hold any of: `*.safetensors`, pickled `*.bin`, fp16 variants
(`diffusion_pytorch_model.fp16.safetensors`, `model.fp16.safetensors`), shards with an
`*.index.json`. Output is always a single `diffusion_pytorch_model.safetensors` (diffusers
models) or `model.safetensors` (text encoders) in the tensors' own dtype.
"""
from __future__ import annotations

import json
import re
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from core.priors.base import PriorError
from core.priors.diffusion.importing.safe_convert import ConvertError, ConvertLimits, convert_bins

DIFFUSERS_STEM, TRANSFORMERS_STEMS = "diffusion_pytorch_model", ("model", "pytorch_model")
_DEPRECATED_ATTN = re.compile(r"^(.*attentions\.\d+)\.(query|key|value|proj_attn)\.(weight|bias)$")
_RENAMED = {"query": "to_q", "key": "to_k", "value": "to_v", "proj_attn": "to_out.0"}
IGNORED_EXTRA = re.compile(r"(^|\.)position_ids$")  # a buffer older transformers checkpoints carry


@dataclass
class ConvertedWeights:
    path: Path
    source_files: list[str]
    converted_from_pickle: bool
    variant: str | None
    dtypes: list[str]
    tensors: int
    notes: list[str] = field(default_factory=list)


def find_weight_files(folder: Path, transformers: bool, variant: str | None) -> tuple[list[Path], str | None]:
    """The weight files of one sub-model (shards in index order), preferring safetensors and the
    full-precision file; `variant` ("fp16") forces that variant. PriorError names what is there."""
    stems = TRANSFORMERS_STEMS if transformers else (DIFFUSERS_STEM,)
    variants = [variant] if variant else [None, *_present_variants(folder, stems)]
    for v in variants:
        for ext in ("safetensors", "bin"):
            for stem in stems:
                name = f"{stem}.{v}.{ext}" if v else f"{stem}.{ext}"
                if (folder / name).is_file():
                    return [folder / name], v
                index = folder / f"{name}.index.json"
                if index.is_file():
                    return _shards(index), v
    present = sorted(p.name for p in folder.iterdir() if p.is_file()) if folder.is_dir() else []
    want = f" (variant {variant!r})" if variant else ""
    raise PriorError(
        f"{folder}: no weights{want}: expected {stems[0]}[.fp16].safetensors or .bin; found {present or 'nothing'}"
    )


def _present_variants(folder: Path, stems) -> list[str]:
    found = set()
    if folder.is_dir():
        for p in folder.iterdir():
            for stem in stems:
                m = re.fullmatch(rf"{re.escape(stem)}\.([A-Za-z0-9_]+)\.(safetensors|bin)(\.index\.json)?", p.name)
                if m and m.group(1) not in ("safetensors", "bin"):
                    found.add(m.group(1))
    return sorted(found)


def _shards(index: Path) -> list[Path]:
    try:
        weight_map = json.loads(index.read_text())["weight_map"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise PriorError(f"{index}: unreadable shard index ({exc})") from None
    names = list(dict.fromkeys(weight_map.values()))
    for n in names:
        if "/" in n or "\\" in n or n.startswith("."):
            raise PriorError(f"{index}: shard name {n!r} points outside the folder")
        if not (index.parent / n).is_file():
            raise PriorError(f"{index}: shard {n} is missing")
    return [index.parent / n for n in names]


def header_shapes(path: Path) -> dict[str, tuple[tuple[int, ...], str]]:
    """Tensor name -> (shape, dtype) from a safetensors header, without reading the data."""
    from safetensors import safe_open  # noqa: PLC0415 — safetensors is heavy: imported when used

    try:
        with safe_open(str(path), framework="pt") as f:
            out = {}
            for k in f.keys():
                sl = f.get_slice(k)
                out[k] = (tuple(sl.get_shape()), str(sl.get_dtype()))
            return out
    except Exception as exc:  # noqa: BLE001 - a corrupt or truncated file
        raise PriorError(f"{path}: not a readable safetensors file ({exc})") from None


def convert_pickles(files: list[Path], workdir: Path, limits: ConvertLimits) -> dict[Path, Path]:
    """Every `.bin` among `files` -> a safetensors file in `workdir` (one bounded child for all)."""
    pairs = [(f, workdir / f"converted-{i}.safetensors") for i, f in enumerate(x for x in files if x.suffix == ".bin")]
    try:
        convert_bins(pairs, limits)
    except ConvertError as exc:
        raise PriorError(str(exc)) from None
    return dict(pairs)


def convert_weights(files: list[Path], used_variant: str | None, converted: dict[Path, Path], out_file: Path,
                    expected: dict[str, tuple[int, ...]], what: str) -> ConvertedWeights:
    """Write `out_file` (one safetensors) from a sub-model's weight files after checking them against
    `expected`; pickled files are read from their `converted` safetensors."""
    pickled = files[0].suffix == ".bin"
    with tempfile.TemporaryDirectory(dir=out_file.parent):
        parts = [converted[f] if f.suffix == ".bin" else f for f in files]
        shapes: dict[str, tuple[tuple[int, ...], str]] = {}
        for part in parts:
            shapes.update(header_shapes(part))
        renames = {k: _canonical(k) for k in shapes if _canonical(k) != k}
        canonical = {renames.get(k, k): v for k, v in shapes.items()}
        notes = _check_shapes(canonical, expected, what)
        if len(parts) == 1 and not renames and not any(IGNORED_EXTRA.search(k) for k in shapes):
            if pickled:
                shutil.move(str(parts[0]), out_file)
            else:
                shutil.copyfile(parts[0], out_file)
        else:  # merge shards / rename deprecated keys / drop ignored buffers: rewrite
            _rewrite(parts, out_file, renames)
    return ConvertedWeights(out_file, [str(f) for f in files], pickled, used_variant,
                            sorted({d for _, d in canonical.values()}), len(canonical), notes)


def _canonical(key: str) -> str:
    m = _DEPRECATED_ATTN.match(key)
    return f"{m.group(1)}.{_RENAMED[m.group(2)]}.{m.group(3)}" if m else key


def _check_shapes(found: dict, expected: dict[str, tuple[int, ...]], what: str) -> list[str]:
    missing = sorted(set(expected) - set(found))
    extra = sorted(k for k in set(found) - set(expected) if not IGNORED_EXTRA.search(k))
    wrong = sorted(k for k in set(found) & set(expected) if tuple(found[k][0]) != tuple(expected[k]))
    problems = []
    if missing:
        problems.append(f"{len(missing)} tensors missing (e.g. {', '.join(missing[:3])})")
    if extra:
        problems.append(f"{len(extra)} unexpected tensors (e.g. {', '.join(extra[:3])})")
    if wrong:
        k = wrong[0]
        problems.append(f"{len(wrong)} tensors with the wrong shape (e.g. {k}: file {list(found[k][0])}, "
                        f"config {list(expected[k])})")
    if problems:
        raise PriorError(f"{what}: the weights do not match its config.json: " + "; ".join(problems))
    return [f"dropped unused buffers: {k}" for k in sorted(found) if IGNORED_EXTRA.search(k) and k not in expected]


def _rewrite(parts: list[Path], out_file: Path, renames: dict[str, str]) -> None:
    from safetensors.torch import load_file, save_file  # noqa: PLC0415 — safetensors is heavy: imported when used

    tensors = {}
    for part in parts:
        for k, v in load_file(str(part)).items():
            if IGNORED_EXTRA.search(k):
                continue
            tensors[renames.get(k, k)] = v
    save_file(tensors, str(out_file), metadata={"format": "pt"})


def expected_shapes(kind: str, config: dict) -> dict[str, tuple[int, ...]]:
    """Parameter / buffer shapes the sub-model's config builds (on the meta device: no memory)."""
    from accelerate import init_empty_weights  # noqa: PLC0415 — accelerate is heavy: imported when used

    with init_empty_weights(include_buffers=True):
        model = _build(kind, config)
    state = model.state_dict()
    return {k: tuple(v.shape) for k, v in state.items() if not IGNORED_EXTRA.search(k)}


def _build(kind: str, config: dict):
    if kind in ("unet", "controlnet", "vae"):
        from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel  # noqa: PLC0415 — diffusers is heavy: imported when used

        cls = {"unet": UNet2DConditionModel, "controlnet": ControlNetModel, "vae": AutoencoderKL}[kind]
        try:
            return cls.from_config(config)
        except (TypeError, ValueError) as exc:
            raise PriorError(f"{kind}/config.json does not describe a {cls.__name__}: {exc}") from None
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTextModelWithProjection  # noqa: PLC0415 — transformers is heavy: imported when used

    cfg = {k: v for k, v in config.items() if not k.startswith("_")}
    try:
        tc = CLIPTextConfig(**cfg)
    except (TypeError, ValueError) as exc:
        raise PriorError(f"{kind}/config.json is not a CLIP text config: {exc}") from None
    archs = config.get("architectures") or []
    return (CLIPTextModelWithProjection if "CLIPTextModelWithProjection" in archs else CLIPTextModel)(tc)
