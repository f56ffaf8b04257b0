"""Scores for predicted env maps: three-sphere metrics (batched), flicker, switch lag.

Sphere renders are the expensive part (the matte lobe is a brute-force convolution), so all
methods' predictions for one probe are rendered in ONE `render_probe_spheres` call per
material together with the ground truth: the filter weights are computed once per probe.
A prediction with any non-finite value is not scored; it is reported as a failure.
"""
from __future__ import annotations

import math

import torch

from core.envmap import integrate
from core.exposure import luminance
from core.metrics import MATERIALS, angular_error_deg, normalized_rmse, render_probe_spheres, si_rmse, temporal_flicker

METRIC_NAMES = ("si_rmse", "si_rmse_rel", "angular_deg", "nrmse")


def finite(env: torch.Tensor) -> bool:
    return bool(torch.isfinite(env).all())


def score_probe(preds: dict[str, torch.Tensor], gt: torch.Tensor, sphere_size: int) -> dict[str, dict]:
    """{method: {material: {metric: value}} or {"non_finite": True}} for one probe."""
    ok = {name: env for name, env in preds.items() if finite(env)}
    out: dict[str, dict] = {name: {"non_finite": True} for name in preds if name not in ok}
    if not ok:
        return out
    names = list(ok)
    scores: dict[str, dict] = {name: {} for name in names}
    for material in MATERIALS:
        images, mask = render_probe_spheres([gt, *(ok[n] for n in names)], material, sphere_size)
        g = images[0]
        g_rms = float(g[mask].to(torch.float64).pow(2).sum(-1).mean().sqrt())
        for name, p in zip(names, images[1:]):
            err = si_rmse(p, g, mask)
            scores[name][material] = {
                "si_rmse": err,
                # si-RMSE is in the scene's radiance units (a bright lamp dominates it); divided by
                # the RMS of the ground-truth render it is comparable across suites and probes.
                "si_rmse_rel": err / g_rms if g_rms > 0 else None,
                "angular_deg": angular_error_deg(p, g, mask),
                "nrmse": normalized_rmse(p, g, mask),
            }
    out.update(scores)
    return out


def mean_scores(per_probe: list[dict]) -> dict:
    """Average {material: {metric}} over the probes that were scored; count failures."""
    scored = [s for s in per_probe if "non_finite" not in s]
    out: dict = {"probes_scored": len(scored), "probes_non_finite": len(per_probe) - len(scored)}
    for material in MATERIALS:
        out[material] = {}
        for m in METRIC_NAMES:
            vals = [s[material][m] for s in scored if s[material][m] is not None]
            out[material][m] = sum(vals) / len(vals) if vals else None
    return out


BOOTSTRAP_DRAWS = 2000


def ratio_interval(num: list[float], den: list[float], seed: int = 0, level: float = 0.90) -> list[float]:
    """`level` (default 90 %) bootstrap interval of mean(num) / mean(den), resampling the PAIRS
    (probes, images or rooms) with replacement: a target is missed (or met) for sure only when
    the whole interval is past (or inside) it."""
    a, b = torch.tensor(num, dtype=torch.float64), torch.tensor(den, dtype=torch.float64)
    idx = torch.randint(0, len(a), (BOOTSTRAP_DRAWS, len(a)), generator=torch.Generator().manual_seed(seed))
    r = a[idx].mean(1) / b[idx].mean(1).clamp_min(1e-30)
    tail = (1.0 - level) / 2.0
    return [round(float(v), 3) for v in torch.quantile(r, torch.tensor([tail, 1.0 - tail], dtype=torch.float64))]


# ---------------------------------------------------------------------------------------
# Time series
# ---------------------------------------------------------------------------------------
def envmap_brightness(envs: torch.Tensor) -> torch.Tensor:
    """Luminance of the solid-angle integral of each map [K, h, 2h, 3] -> [K] (irradiance-like)."""
    return torch.stack([luminance(integrate(e.to(torch.float64))) for e in envs])


def relative_course(pred: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """pred / truth brightness per sample [K] (float64), divided by its mean: 1 on every sample
    for a prediction that follows the truth's course at any scale (a stretch's flatness)."""
    r = pred.double() / truth.double().clamp_min(1e-30)
    return r / r.mean()


def flicker(envs: torch.Tensor) -> float | None:
    """core.metrics.temporal_flicker of a [K, h, 2h, 3] sequence (None when non-finite)."""
    return temporal_flicker(envs) if finite(envs) else None


def _crossing(times: torch.Tensor, progress: torch.Tensor, level: float) -> float | None:
    """First time the progress curve reaches `level` (linear interpolation between samples)."""
    for k in range(len(times)):
        if progress[k] >= level:
            if k == 0:
                return float(times[0])
            p0, p1 = float(progress[k - 1]), float(progress[k])
            w = (level - p0) / (p1 - p0) if p1 != p0 else 1.0
            return float(times[k - 1] + w * (times[k] - times[k - 1]))
    return None


def step_response(times: torch.Tensor, signal: torch.Tensor) -> dict:
    """How a brightness signal moves from its first to its last sample across a step.

    progress(t) = (s(t) - s_first) / (s_last - s_first). Returns the 50 % crossing time, the
    10-90 % transition width, and the step's log-contrast log(s_first / s_last).
    """
    s = signal.to(torch.float64).clamp_min(1e-30)
    first, last = float(s[0]), float(s[-1])
    contrast = math.log(first / last)
    if abs(last - first) <= 1e-9 * max(abs(first), abs(last), 1e-30):
        return {"log_contrast": contrast, "t50": None, "width_10_90": None}
    progress = (s - first) / (last - first)
    t10, t50, t90 = (_crossing(times, progress, q) for q in (0.1, 0.5, 0.9))
    width = None if t10 is None or t90 is None else t90 - t10
    return {"log_contrast": contrast, "t50": t50, "width_10_90": width}


def switch_lag(times: torch.Tensor, pred: torch.Tensor, gt: torch.Tensor, fps: float) -> dict:
    """Compare a predicted brightness step with the ground truth's over the same window.

    lag = t50(pred) - t50(gt) (seconds and frames; negative = early, e.g. a smooth field
    interpolating between the last frame before and the first after the switch);
    captured = pred log-contrast / gt log-contrast (1 = the full switch, 0 = none).
    """
    p, g = step_response(times, pred), step_response(times, gt)
    lag = None if p["t50"] is None or g["t50"] is None else p["t50"] - g["t50"]
    captured = p["log_contrast"] / g["log_contrast"] if abs(g["log_contrast"]) > 1e-9 else None
    return {
        "lag_s": lag,
        "lag_frames": None if lag is None else lag * fps,
        "width_10_90_s": p["width_10_90"],
        "gt_width_10_90_s": g["width_10_90"],
        "contrast_captured": captured,
    }
