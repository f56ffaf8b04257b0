"""Optional learned monocular depth from a LOCAL `transformers` model directory.

`load_depth_estimator(dir)` loads any `AutoModelForDepthEstimation` checkpoint (DPT, Depth
Anything, ...) saved with safetensors weights and its image-processor config; nothing is ever
downloaded (`local_files_only`, HF_HUB_OFFLINE=1) and pickled `.bin` weights are refused.

Most such models predict RELATIVE INVERSE depth (disparity up to an unknown scale and, for
affine-invariant models such as MiDaS / Depth Anything, a small unknown shift). Rule used to
turn it into planar depth, per frame: the shift is taken as zero and the scale is fixed so the
frame's median depth equals the assumed box room's median (`capture.assumed_box_depth` at
the same intrinsics):  depth = median(box) * median(pred) / pred,  clamped to
[median(box) / CLAMP_RATIO, median(box) * CLAMP_RATIO] (zero disparity = far, not infinite).
Layout comes from the model; the SCALE is the box room's, i.e. arbitrary, and ignoring the
shift distorts depth ratios between near and far surfaces somewhat. Each frame is scaled on
its own, which removes the model's per-image scale drift. A frame without a positive median
prediction gets the box room's median depth everywhere. Models that declare metric output
(`depth_estimation_type == "metric"`, ZoeDepth) are used as metres directly.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from core.camera import Intrinsics
from core.capture.base import CaptureError
from core.capture.depth import assumed_box_depth
from core.conventions import DEFAULT_HFOV_DEG

# Converted depth stays within this factor of the box room's median depth.
CLAMP_RATIO = 20.0
METRIC_MODEL_TYPES = {"zoedepth"}


def _fail(message: str) -> CaptureError:
    return CaptureError("depth", f"depth model: {message} (set LIGHTFIELD_DEPTH_MODEL to a local directory; "
                        "nothing is downloaded)")


def check_depth_model_dir(model_dir: str | os.PathLike) -> Path:
    """The directory as a Path, or CaptureError(field='depth') naming what is missing."""
    path = Path(model_dir).expanduser()
    if not path.is_dir():
        looks_like_hub_id = "/" in str(model_dir) and not path.is_absolute() and not path.exists()
        hint = (
            " It looks like a Hugging Face hub id: download it yourself and give the directory."
            if looks_like_hub_id
            else ""
        )
        raise _fail(f"{str(model_dir)!r} is not an existing local directory.{hint}")
    missing = [n for n in ("config.json", "preprocessor_config.json") if not (path / n).is_file()]
    if not any(path.glob("*.safetensors")):
        pickled = " (only pickled weights found, which are refused)" if any(path.glob("*.bin")) else ""
        missing.append(f"model.safetensors{pickled}")
    if missing:
        raise _fail(f"{str(path)!r} is missing {', '.join(missing)}")
    return path


def disparity_to_depth(pred: torch.Tensor, box_depth: torch.Tensor) -> torch.Tensor:
    """Relative disparity [T, H, W] -> planar depth [T, H, W] scaled to `box_depth` [H, W]
    by the module docstring's rule. Non-finite predictions take the frame's median depth."""
    pred = pred.double()
    target = float(box_depth.double().median())
    out = torch.empty_like(pred)
    for i in range(pred.shape[0]):
        p = pred[i]
        finite = torch.isfinite(p)
        med = float(p[finite].median()) if finite.any() else 0.0
        if not med > 0:
            out[i] = target
            continue
        d = target * med / torch.where(finite, p, med).clamp_min(1e-300)
        out[i] = d.clamp(target / CLAMP_RATIO, target * CLAMP_RATIO)
    return out.float()


@dataclass
class DepthEstimator:
    """A loaded depth model; call it on frames [T, H, W, 3] in [0, 1] for depth [T, H, W]."""

    model: torch.nn.Module
    processor: object
    name: str
    metric: bool
    batch_size: int = 4

    @property
    def depth_source(self) -> str:
        kind = "metric" if self.metric else "relative, scale arbitrary"
        return f"estimated:{self.name} ({kind})"

    def predict_raw(self, frames: torch.Tensor) -> torch.Tensor:
        """The model's own output [T, H, W] (bilinearly resized to the frame size), in batches
        of `batch_size` frames so memory stays bounded for long videos."""
        T, H, W, _ = frames.shape
        out = torch.empty(T, H, W, dtype=torch.float32)
        with torch.inference_mode():
            for s in range(0, T, self.batch_size):
                chunk = frames[s:s + self.batch_size].clamp(0, 1).float().numpy()
                inputs = self.processor(images=list(chunk), return_tensors="pt", do_rescale=False)
                pred = self.model(pixel_values=inputs["pixel_values"]).predicted_depth
                pred = pred.reshape(pred.shape[0], 1, *pred.shape[-2:]).float()
                out[s:s + self.batch_size] = torch.nn.functional.interpolate(
                    pred, size=(H, W), mode="bilinear", align_corners=False)[:, 0]
        return out

    def __call__(self, frames: torch.Tensor, intrinsics: Intrinsics | None = None) -> torch.Tensor:
        """Planar depth [T, H, W] float32, finite and > 0. `intrinsics` (default: the
        project's default pinhole) fixes the box room the relative scale is aligned to."""
        T, H, W, _ = frames.shape
        raw = self.predict_raw(frames)
        if self.metric:
            return torch.where(torch.isfinite(raw) & (raw > 0), raw, torch.full_like(raw, float("nan")))
        intr = intrinsics or Intrinsics.from_hfov(W, H, DEFAULT_HFOV_DEG)
        return disparity_to_depth(raw, assumed_box_depth(intr))


def _is_metric(config) -> bool:
    return getattr(config, "depth_estimation_type", None) == "metric" or config.model_type in METRIC_MODEL_TYPES


def load_depth_estimator(model_dir: str | os.PathLike, batch_size: int = 4) -> DepthEstimator:
    """Load a depth model from a local directory (config.json, preprocessor_config.json,
    *.safetensors). Raises CaptureError(field='depth') for hub ids, missing or incomplete
    directories, pickled-only weights and anything transformers cannot load."""
    os.environ["HF_HUB_OFFLINE"] = "1"  # belt and braces: local_files_only below already forbids downloads
    path = check_depth_model_dir(model_dir)
    from transformers import AutoImageProcessor, AutoModelForDepthEstimation  # noqa: PLC0415 — transformers is heavy: imported when used
    from transformers.utils import logging as tlog  # noqa: PLC0415 — transformers is heavy: imported when used

    was_enabled = tlog.is_progress_bar_enabled()
    tlog.disable_progress_bar()
    try:
        processor = AutoImageProcessor.from_pretrained(path, local_files_only=True)
        model = AutoModelForDepthEstimation.from_pretrained(path, local_files_only=True, use_safetensors=True)
    except (OSError, ValueError, KeyError) as exc:
        raise _fail(f"cannot load {str(path)!r}: {exc}") from exc
    finally:
        if was_enabled:
            tlog.enable_progress_bar()
    model.eval().requires_grad_(False)
    return DepthEstimator(model, processor, path.name, _is_metric(model.config), max(1, int(batch_size)))
