"""Distillation checkpoints: field, optimiser and generator state in safetensors + JSON (never
pickle), written atomically every `checkpoint_every` steps, resumed only when the run's
fingerprint matches, so a resumed run is bit-identical to an uninterrupted one on CPU."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from core.capture.base import Capture
from core.engine.config import DistillConfig
from core.fields import FieldConfig, LightField
from core.priors.base import Prior

CHECKPOINT_FILE = "checkpoint.safetensors"
CHECKPOINT_META = "checkpoint.json"


def save_checkpoint(ckpt_dir: Path, field: LightField, opt: torch.optim.Optimizer, gen: torch.Generator,
                     step: int, losses: list[float], fingerprint: str) -> None:
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    tensors = {f"field.{k}": v.detach().cpu().contiguous() for k, v in field.state_dict().items()}
    sd = opt.state_dict()
    for idx, st in sd["state"].items():
        for key, val in st.items():
            tensors[f"opt.{idx}.{key}"] = torch.as_tensor(val).detach().cpu().clone().contiguous()
    tensors["rng"] = gen.get_state().clone()
    tensors["losses"] = torch.tensor(losses, dtype=torch.float64)
    tmp = ckpt_dir / (CHECKPOINT_FILE + ".tmp")
    save_file(tensors, str(tmp))
    meta = {"step": step, "fingerprint": fingerprint, "param_groups": sd["param_groups"]}
    tmp_meta = ckpt_dir / (CHECKPOINT_META + ".tmp")
    tmp_meta.write_text(json.dumps(meta))
    tmp.replace(ckpt_dir / CHECKPOINT_FILE)
    tmp_meta.replace(ckpt_dir / CHECKPOINT_META)


def load_checkpoint(ckpt_dir: Path, field: LightField, opt: torch.optim.Optimizer, gen: torch.Generator,
                     fingerprint: str) -> tuple[int, list[float]] | None:
    """Restore a matching checkpoint; returns (step, losses) or None if absent/mismatched."""
    f, m = ckpt_dir / CHECKPOINT_FILE, ckpt_dir / CHECKPOINT_META
    if not (f.is_file() and m.is_file()):
        return None
    try:
        meta = json.loads(m.read_text())
        if meta.get("fingerprint") != fingerprint:
            return None
        tensors = load_file(str(f))
    except Exception:  # a corrupt checkpoint is just not resumed from
        return None
    field.load_state_dict({k[len("field."):]: v for k, v in tensors.items() if k.startswith("field.")})
    state: dict = {}
    for k, v in tensors.items():
        if k.startswith("opt."):
            _, idx, key = k.split(".", 2)
            state.setdefault(int(idx), {})[key] = v
    opt.load_state_dict({"state": state, "param_groups": meta["param_groups"]})
    gen.set_state(tensors["rng"])
    return int(meta["step"]), tensors["losses"].tolist()


def fingerprint(capture: Capture, cfg: DistillConfig, field_cfg: FieldConfig, seed: int, prior: Prior) -> str:
    """What a checkpoint must match to be resumed: the frames (sampled), settings, seed and prior."""
    h = hashlib.sha256()
    h.update(capture.frames.numpy().tobytes()[:: max(1, capture.frames.numel() // 100_000)])
    if capture.stated_ev is not None:  # the same frames under other stated exposures are another job
        h.update(capture.stated_ev.numpy().tobytes())
    # the device is not part of it: a checkpoint written on a GPU resumes on CPU and back
    h.update(json.dumps([cfg.model_dump(exclude={"device"}), field_cfg.model_dump(), seed, prior.name],
                        sort_keys=True, default=str).encode())
    return h.hexdigest()[:32]


def clear_checkpoint(ckpt_dir: Path) -> None:
    for name in (CHECKPOINT_FILE, CHECKPOINT_META):
        (ckpt_dir / name).unlink(missing_ok=True)
