"""Training checkpoints without pickle: weights via diffusers' save_pretrained (safetensors),
optimizer state as safetensors tensors + a JSON skeleton.

    OUT/checkpoints/step-000500/
        unet/, controlnet/        save_pretrained (safetensors)
        optimizer.safetensors     every tensor of optimizer.state_dict()["state"]
        optimizer.json            param_groups and non-tensor state entries
        state.json                {"step": 500, ...}; written last, so its presence marks a complete checkpoint
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

CHECKPOINTS = "checkpoints"
STATE_FILE = "state.json"


def optimizer_state_to_files(state_dict: dict) -> tuple[dict[str, torch.Tensor], dict]:
    """Split an optimizer state_dict into named tensors and a JSON-able remainder."""
    tensors: dict[str, torch.Tensor] = {}
    skeleton: dict = {"state": {}, "param_groups": state_dict["param_groups"]}
    for pid, entries in state_dict["state"].items():
        rest = {}
        for key, value in entries.items():
            if torch.is_tensor(value):
                tensors[f"{pid}/{key}"] = value.detach().cpu().contiguous()
            else:
                rest[key] = value
        skeleton["state"][str(pid)] = rest
    return tensors, skeleton


def optimizer_state_from_files(tensors: dict[str, torch.Tensor], skeleton: dict) -> dict:
    state: dict = {int(pid): dict(rest) for pid, rest in skeleton["state"].items()}
    for name, value in tensors.items():
        pid, key = name.split("/", 1)
        state.setdefault(int(pid), {})[key] = value
    return {"state": state, "param_groups": skeleton["param_groups"]}


def save_checkpoint(out_dir: Path, step: int, network, optimizer, extra: dict, keep: int = 2) -> Path:
    """Write step-XXXXXX atomically (tmp dir + rename) and prune all but the newest `keep`."""
    root = Path(out_dir) / CHECKPOINTS
    final = root / f"step-{step:06d}"
    tmp = root / f".tmp-step-{step:06d}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    network.unet.save_pretrained(tmp / "unet", safe_serialization=True)
    network.controlnet.save_pretrained(tmp / "controlnet", safe_serialization=True)
    tensors, skeleton = optimizer_state_to_files(optimizer.state_dict())
    save_file(tensors, str(tmp / "optimizer.safetensors"))
    (tmp / "optimizer.json").write_text(json.dumps(skeleton))
    (tmp / STATE_FILE).write_text(json.dumps({"step": step, **extra}, indent=2))
    shutil.rmtree(final, ignore_errors=True)
    tmp.rename(final)
    for old in list_checkpoints(out_dir)[:-keep] if keep > 0 else []:
        shutil.rmtree(old, ignore_errors=True)
    return final


def list_checkpoints(out_dir: Path) -> list[Path]:
    """Complete checkpoints, oldest first."""
    root = Path(out_dir) / CHECKPOINTS
    if not root.is_dir():
        return []
    done = [p for p in root.glob("step-*") if (p / STATE_FILE).is_file()]
    return sorted(done, key=lambda p: int(p.name.split("-")[1]))


def load_checkpoint(ckpt: Path, network, optimizer) -> dict:
    """Restore weights and optimizer state in place; returns state.json."""
    from diffusers import ControlNetModel, UNet2DConditionModel  # noqa: PLC0415 — diffusers is heavy: imported when used

    for name, cls in (("unet", UNet2DConditionModel), ("controlnet", ControlNetModel)):
        loaded = cls.from_pretrained(ckpt, subfolder=name, local_files_only=True, use_safetensors=True)
        getattr(network, name).load_state_dict(loaded.state_dict())
    skeleton = json.loads((ckpt / "optimizer.json").read_text())
    optimizer.load_state_dict(optimizer_state_from_files(load_file(str(ckpt / "optimizer.safetensors")), skeleton))
    return json.loads((ckpt / STATE_FILE).read_text())
