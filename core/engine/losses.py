"""Distillation losses on tone-mapped LDR ball pixels.

* Masked L2 with a saturation hinge: the prediction is tone mapped WITHOUT the clip to 1
  (`tonemap_unclipped`), so an over-bright ball still gets a gradient; where the target is
  saturated (>= SATURATED) it only says "at least white", so only a prediction below it is
  penalised. The clipped tone map would have zero gradient above white and let a field that
  starts too bright stay there.
* Perceptual term: LPIPS needs a pretrained backbone (torchvision, not usable here) so it is
  only reported as available when LIGHTFIELD_LPIPS_WEIGHTS points at weights AND the `lpips`
  package imports; otherwise the documented fallback is masked SSIM (1 - SSIM with a 7x7
  Gaussian window, weighted by the ball mask). The choice is recorded in the metadata.
"""
from __future__ import annotations

import os

import torch
import torch.nn.functional as F
from safetensors.torch import load_file

SATURATED = 0.999
SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2


def masked_l2(pred_ldr_unclipped: torch.Tensor, target_ldr: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over masked pixels of the squared residual. pred/target [3, H, W], mask [H, W] in [0, 1]."""
    over = pred_ldr_unclipped - target_ldr
    resid = torch.where(target_ldr >= SATURATED, over.clamp(max=0.0), over)
    w = mask[None]
    return (w * resid * resid).sum() / (3.0 * w.sum()).clamp_min(1e-8)


def _gaussian_window(size: int = 7, sigma: float = 1.5, dtype=torch.float32) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    g = g / g.sum()
    return (g[:, None] * g[None, :])[None, None].expand(3, 1, size, size).contiguous()


def masked_ssim_loss(
    pred_ldr: torch.Tensor, target_ldr: torch.Tensor, mask: torch.Tensor, size: int = 7
) -> torch.Tensor:
    """1 - SSIM averaged over masked pixels (local statistics with a Gaussian window)."""
    win = _gaussian_window(size, dtype=pred_ldr.dtype).to(pred_ldr.device)
    x, y = pred_ldr.clamp(0, 1)[None], target_ldr.clamp(0, 1)[None]
    pad = size // 2

    def blur(z):
        return F.conv2d(F.pad(z, (pad,) * 4, mode="replicate"), win, groups=3)

    mx, my = blur(x), blur(y)
    vx = blur(x * x) - mx * mx
    vy = blur(y * y) - my * my
    cxy = blur(x * y) - mx * my
    ssim = ((2 * mx * my + SSIM_C1) * (2 * cxy + SSIM_C2)) / ((mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2))
    w = mask[None, None]
    return ((1.0 - ssim) * w).sum() / (3.0 * w.sum()).clamp_min(1e-8)


LPIPS_WEIGHTS_ENV = {"alex": "LIGHTFIELD_LPIPS_WEIGHTS", "vgg": "LIGHTFIELD_LPIPS_VGG_WEIGHTS"}


def perceptual_kind(net: str = "alex") -> str:
    """'lpips' when local LPIPS weights (for `net`) and the lpips package are both available, else 'ssim'."""
    path = os.environ.get(LPIPS_WEIGHTS_ENV[net])
    if not path or not os.path.exists(path):
        return "ssim"
    try:
        import lpips  # noqa: F401, PLC0415 — optional: probed here
    except Exception:
        return "ssim"
    return "lpips"


def perceptual_description(net: str = "alex") -> dict:
    kind, env = perceptual_kind(net), LPIPS_WEIGHTS_ENV[net]
    if kind == "ssim":
        why = (f"{env} not set" if not os.environ.get(env) else "LPIPS weights or the lpips package unavailable")
        return {"kind": "ssim", "window": 7, "sigma": 1.5, "wanted": f"lpips-{net}", "reason": f"fallback: {why}"}
    return {"kind": "lpips", "net": net, "weights": os.environ[env]}


class PerceptualLoss:
    """Callable (pred [3,H,W], target [3,H,W], mask [H,W]) -> scalar; LPIPS or SSIM fallback."""

    def __init__(self, net: str = "alex") -> None:
        self.kind = perceptual_kind(net)
        self._lpips = None
        if self.kind == "lpips":  # pragma: no cover - needs weights that CI never has
            import lpips  # noqa: PLC0415 — lpips is heavy: imported when used

            model = lpips.LPIPS(pretrained=False, net=net, pnet_rand=True, verbose=False)
            model.load_state_dict(load_file(os.environ[LPIPS_WEIGHTS_ENV[net]]))  # strict: no silently random layers
            self._lpips = model.eval().requires_grad_(False)

    def __call__(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        if self._lpips is None:
            return masked_ssim_loss(pred, target, mask)
        self._lpips.to(pred.device)  # pragma: no cover - no-op once there
        d = self._lpips(pred[None] * 2 - 1, target[None] * 2 - 1,  # pragma: no cover
                        retPerLayer=False, normalize=False)
        return d.mean()  # pragma: no cover
