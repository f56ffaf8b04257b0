"""The camera's response, estimated from frames taken at different exposures
(docs/captures.md, "The camera's response").

Loading decodes each frame from the curve its file declares (core.transfer). A phone adds a tone
curve it does not declare (a filmic toe and shoulder), and a file may declare nothing. Where the
exposure varies, the frames themselves say which curve made them: a surface seen at exposures
ev_i and ev_j gives codes c_i and c_j with g(c_j) / g(c_i) = 2^(ev_j - ev_i), g the inverse
response. The same equation is Debevec and Malik's, with each surface's radiance eliminated
between the two readings, so a moving camera's frames serve through their poses and depth
(core.capture.temporal's warp) as well as a static camera's pixels.

log g is piecewise linear in the code (as many knots as explain held-out samples best, of
`ResponseConfig.knots`: a filmic shoulder needs more than a power law), fixed at 0 at the clip point
(code 1 stays white), pulled towards the declared curve by a smoothness prior on the difference,
and fitted by iteratively reweighted least squares (a lamp that switches between two readings is
an outlier, not a curve). Every frame's exposure gets a correction fitted with the curve: it
absorbs a misstated or misestimated exposure and a change of the whole room's light alike
(daylight fading while the auto-exposure follows it), so only how a pair's ratio varies with the
code level is left to the curve, which is what tells a curve from a light. The fit is used only
when it explains frames it was NOT fitted on clearly better than the declared curve with its own
best exposures, so a capture whose declared curve is right keeps it, and a capture that cannot
tell (a locked exposure, one frame) is left alone. Frames are held out by stretches of time, not
by pixels: a camera's curve is the same in every stretch, while a light that changes in part of
the view (a lamp switched off beside a wall the camera sees) bends a curve fitted through its
stretch in a way no other stretch confirms; held out by pixels, the fitted shoulder explained the
switch's own other pixels and passed. Exposures the frames
did not state are not enough: a curve and unknown exposures are defined together only up to a
power (g^k with k ev explains the same frames), and fitting both through that ambiguity moved a
correctly declared pan's estimated exposures by over a stop, so such captures keep the declared
curve (prepare_capture fits only stated exposures).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from core.capture.base import Capture
from core.capture.temporal import ANALYSIS_HEIGHT, OVERLAP_PAIRS_PER_FRAME, _overlapping_pairs, _warp_into
from core.conventions import GAMMA, valid_depth_mask


@dataclass(frozen=True)
class ResponseConfig:
    # log g at this many codes over [code_lo, 1]: the count whose fit explains held-out samples best
    knots: tuple[int, ...] = (9, 17, 33)
    code_lo: float = 0.05  # convention codes below: noise and quantisation (8-bit code 1 of sRGB is 0.034)
    code_hi: float = 0.97  # above: clipped, or the codec's ringing around clipped pixels
    min_span_stops: float = 0.5  # a capture whose exposures span less is not fitted
    smoothness: float = 0.1  # weight of the second-difference prior on log g minus the declared curve's
    edge_contrast: float = 0.03  # samples whose 3x3 neighbourhood varies more (edges: the warp blurs) are left out
    samples_per_pair: int = 4000
    max_samples: int = 60_000  # over all pairs: the fit has at most 33 unknowns
    irls_rounds: int = 4
    min_pair_stops: float = 0.5
    time_folds: int = 4  # stretches of time held out in turn (module docstring)


DEFAULT = ResponseConfig()


@dataclass
class ResponseFit:
    knots: torch.Tensor  # [K] float64 convention codes
    log_g: torch.Tensor  # [K] float64 log linear value at the knots (0 at code 1)
    declared_error: float  # median |log residual| of the held-out samples, declared curve
    fitted_error: float  # the same, fitted curve
    samples: int
    better: bool  # the fit explains the held-out samples clearly better (_clearly_better)

    def apply(self, frames: torch.Tensor) -> torch.Tensor:
        """Convention codes re-encoded through the fitted curve: exp(log g(c) / GAMMA); below the
        first knot the curve continues as the declared power law from it."""
        return apply_curve(frames, self.knots, self.log_g)

    def as_dict(self) -> dict:
        return {"codes": [round(float(c), 4) for c in self.knots],
                "log_linear": [round(float(v), 5) for v in self.log_g],
                "held_out_error_declared": round(self.declared_error, 5),
                "held_out_error_fitted": round(self.fitted_error, 5), "samples": self.samples}


def apply_curve(frames: torch.Tensor, knots, log_g) -> torch.Tensor:
    knots = torch.as_tensor(knots, dtype=torch.float64)
    log_g = torch.as_tensor(log_g, dtype=torch.float64)
    c = frames.double().clamp(0.0, 1.0)
    w = _hat_weights(c.reshape(-1), knots)
    y = (w @ log_g).reshape(c.shape)
    lo = float(knots[0])
    below = c < lo
    y_lo = float(log_g[0])
    y = torch.where(below, y_lo + GAMMA * torch.log(c.clamp_min(1e-12) / lo), y)
    return torch.exp(y / GAMMA).clamp(0.0, 1.0).to(frames.dtype)


def _hat_weights(c: torch.Tensor, knots: torch.Tensor) -> torch.Tensor:
    """[N, K] linear-interpolation weights of codes c [N] (clamped to the knots' range)."""
    K = knots.shape[0]
    step = float(knots[1] - knots[0])
    x = ((c.clamp(float(knots[0]), float(knots[-1])) - knots[0]) / step).clamp(0.0, K - 1 - 1e-9)
    i = x.floor().long()
    f = x - i
    w = torch.zeros(c.shape[0], K, dtype=torch.float64)
    w.scatter_(1, i[:, None], (1.0 - f)[:, None])
    w.scatter_add_(1, (i + 1).clamp(max=K - 1)[:, None], f[:, None])
    return w


def _pair_samples(capture: Capture, config: ResponseConfig) -> tuple[torch.Tensor, ...]:
    """(c_i [N], c_j [N], log exposure ratio [N], surface parity [N] bool, frame i [N], frame j [N]):
    one reading of a surface in two frames, per colour channel, at the analysis resolution."""
    small = capture.resized(ANALYSIS_HEIGHT)
    ev = capture.frame_ev.double()
    T, h, w = small.depth.shape
    frames = small.frames.double()
    blur = F.avg_pool2d(frames.permute(0, 3, 1, 2), 3, 1, 1, count_include_pad=False).permute(0, 2, 3, 1)
    flat = (frames - blur).abs().amax(-1) <= config.edge_contrast  # [T, h, w]
    if capture.static_camera:  # each frame with its next few, as a moving camera's overlapping pairs
        pairs = [(i, j) for i in range(T) for j in range(i + 1, min(T, i + 1 + OVERLAP_PAIRS_PER_FRAME))]
    else:
        pairs = _overlapping_pairs(capture)
    depth = torch.where(valid_depth_mask(small.depth), small.depth, torch.nan)
    parity = (torch.arange(h)[:, None] // 2 + torch.arange(w)[None] // 2) % 2 == 0
    gen = torch.Generator().manual_seed(0)
    ci, cj, ratio, par, fi, fj = [], [], [], [], [], []
    for i, j in pairs:
        step = float(ev[j] - ev[i])
        if abs(step) < config.min_pair_stops:
            continue
        if capture.static_camera:
            read_j, ok = frames[j], torch.ones(h, w, dtype=torch.bool)
            flat_j = flat[j]
        else:
            planes = torch.cat((frames[j], flat[j].double()[..., None]), -1).float()
            warped, ok = _warp_into(planes, depth[i], depth[j], small.intrinsics, capture.poses[i], capture.poses[j])
            read_j, flat_j = warped[..., :3].double(), warped[..., 3] > 0.999
        keep = ok & flat[i] & flat_j
        a, b = frames[i][keep], read_j[keep]  # [n, 3]
        p = parity[keep][:, None].expand_as(a)
        good = (a > config.code_lo) & (a < config.code_hi) & (b > config.code_lo) & (b < config.code_hi)
        a, b, p = a[good], b[good], p[good]
        if a.numel() > config.samples_per_pair:
            pick = torch.randperm(a.numel(), generator=gen)[: config.samples_per_pair]
            a, b, p = a[pick], b[pick], p[pick]
        ci.append(a), cj.append(b), par.append(p)
        ratio.append(torch.full_like(a, step * math.log(2.0)))
        fi.append(torch.full(a.shape, i, dtype=torch.long)), fj.append(torch.full(a.shape, j, dtype=torch.long))
    if not ci:
        empty = torch.zeros(0, dtype=torch.float64)
        index = torch.zeros(0, dtype=torch.long)
        return empty, empty, empty, torch.zeros(0, dtype=torch.bool), index, index
    out = tuple(torch.cat(x) for x in (ci, cj, ratio, par, fi, fj))
    if out[0].numel() > config.max_samples:
        pick = torch.randperm(out[0].numel(), generator=gen)[: config.max_samples]
        out = tuple(x[pick] for x in out)
    return out


def _solve(samples, knots, config: ResponseConfig, frames: int, curve: bool = True):
    """(log g at the knots [K] (last = 0), exposure corrections [frames] in log units) fitted to the
    samples by IRLS (module docstring). `curve`: the curve is free at the stated exposures (they
    pin its power); else the declared curve with every frame but the first given a correction to
    its exposure (log units), which absorbs a misstated exposure and a change of the
    whole room's light alike: the baseline a fitted curve must beat."""
    ci, cj, ratio, fi, fj = samples
    K = knots.shape[0]
    prior = GAMMA * torch.log(knots)  # the declared curve, in the convention: log g0(c) = GAMMA log c
    A = _hat_weights(cj, knots) - _hat_weights(ci, knots)
    r0 = ratio - A @ prior  # what the declared curve leaves unexplained
    A = A[:, :-1]  # the clip point's value is fixed (log g(1) = 0)
    D = torch.zeros(K - 3, K - 1, dtype=torch.float64)
    for k in range(K - 3):
        D[k, k], D[k, k + 1], D[k, k + 2] = 1.0, -2.0, 1.0
    reg = config.smoothness * (D.T @ D) + 1e-6 * torch.eye(K - 1, dtype=torch.float64)
    if not curve:
        A, reg = A[:, :0], reg[:0, :0]
    exposures = not curve
    if exposures and frames > 1:  # y(c_j) - y(c_i) = (ev_j + e_j - ev_i - e_i) ln 2 (frame 0 fixed)
        E = torch.zeros(r0.shape[0], frames, dtype=torch.float64)
        E[torch.arange(r0.shape[0]), fj] -= 1.0
        E[torch.arange(r0.shape[0]), fi] += 1.0
        A = torch.cat((A, E[:, 1:]), 1)
        reg = torch.block_diag(reg, 1e-6 * torch.eye(frames - 1, dtype=torch.float64))
    weight = torch.ones_like(r0)
    delta = torch.zeros(A.shape[1], dtype=torch.float64)
    n = max(int(r0.numel()), 1)
    for _ in range(config.irls_rounds):
        Aw = A * weight[:, None]
        delta = torch.linalg.solve(Aw.T @ A / n + reg, Aw.T @ r0 / n)
        res = r0 - A @ delta
        scale = 1.4826 * float(res.abs().median()) + 1e-6
        weight = 1.0 / (1.0 + (res / (2.0 * scale)) ** 2)  # Cauchy: a switch between two readings is an outlier
    log_g = prior.clone()
    curve_cols = K - 1 if curve else 0
    if curve_cols:
        log_g[:-1] += delta[:curve_cols]
    log_g[-1] = 0.0
    exposure = torch.zeros(max(frames, 1), dtype=torch.float64)
    if exposures and frames > 1:
        exposure[1:] = delta[curve_cols:]
    return torch.cummax(log_g, 0).values, exposure  # a response is monotone


def _take(samples, mask: torch.Tensor) -> tuple:
    return tuple(x[mask] for x in samples)


def _time_folds(fi: torch.Tensor, fj: torch.Tensor, parity: torch.Tensor, frames: int, count: int) -> list[tuple]:
    """(train, profile, score) sample masks per stretch of time: the frames cut into `count`
    contiguous stretches; a fold holds out the pairs whose earlier frame is in its stretch and
    trains on the pairs touching none of it; the held-out pairs are split by surface parity, one
    half fitting the baseline's exposures, the other scoring both curves. Folds with fewer than
    100 samples in a part are dropped."""
    stretch = torch.arange(frames) * min(count, frames) // frames
    si, sj = stretch[fi], stretch[fj]
    out = []
    for b in range(min(count, frames)):
        held = si == b
        train = (si != b) & (sj != b)
        profile, score = held & parity, held & ~parity
        if min(int(train.sum()), int(profile.sum()), int(score.sum())) >= 100:
            out.append((train, profile, score))
    return out


def _held_out_residuals(samples, knots, log_g, exposure) -> torch.Tensor:
    ci, cj, ratio, fi, fj = samples
    shift = exposure[fj] - exposure[fi] if exposure.numel() > 1 else 0.0
    return (ratio + shift - (_hat_weights(cj, knots) - _hat_weights(ci, knots)) @ log_g).abs()


CODE_STEP = math.log(256.0 / 255.0)  # one 8-bit code at white, in log light: a curve difference smaller is no camera's


def _clearly_better(fitted: torch.Tensor, declared: torch.Tensor) -> bool:
    """True when the fitted curve's held-out residuals are lower than the declared curve's by more
    than twice the standard error of their paired difference (residuals capped at 5 robust
    scales, so a switching lamp's readings do not decide) AND by more than one 8-bit code in the
    median (with 60,000 samples a difference far below what a curve could make is significant)."""
    cap = 5.0 * 1.4826 * float(torch.minimum(fitted, declared).median()) + 1e-9
    d = declared.clamp(max=cap) - fitted.clamp(max=cap)
    significant = float(d.mean()) > 2.0 * float(d.std()) / math.sqrt(max(d.numel(), 1))
    return significant and float(declared.median() - fitted.median()) > CODE_STEP


def fit_response(capture: Capture, config: ResponseConfig = DEFAULT) -> ResponseFit | None:
    """The response fitted to the capture's frames at their stated exposures, or None where they
    cannot tell (fewer than two frames, exposures spanning under `min_span_stops`, too few shared
    surfaces). It is used only when it explains held-out surfaces clearly better than the declared
    curve with every frame's exposure free: that baseline explains any per-frame factor (a
    misstated exposure, the whole room's light fading), so the fit wins only where the ratio
    between two readings varies with their level, as only a curve makes it."""
    if capture.num_frames < 2 or capture.stated_ev is None:
        return None
    ev = capture.frame_ev
    if float(ev.max() - ev.min()) < config.min_span_stops:
        return None
    ci, cj, ratio, parity, fi, fj = _pair_samples(capture, config)
    if int(parity.sum()) < 200 or int((~parity).sum()) < 200:
        return None
    frames = capture.num_frames
    samples = (ci, cj, ratio, fi, fj)
    folds = _time_folds(fi, fj, parity, frames, config.time_folds)
    if not folds:
        return None
    best = None
    for count in config.knots:
        knots = torch.linspace(config.code_lo, 1.0, count, dtype=torch.float64)
        fitted = torch.cat([_held_out_residuals(_take(samples, score), knots,
                                                *_solve(_take(samples, train), knots, config, frames))
                            for train, _, score in folds])
        if best is None or float(fitted.median()) < float(best[1].median()):
            best = (knots, fitted)
    knots, fitted = best
    declared_log_g = GAMMA * torch.log(knots)
    # the baseline: the declared curve with the held-out stretch's exposures fitted to its own other half
    declared = torch.cat([_held_out_residuals(_take(samples, score), knots, declared_log_g,
                                              _solve(_take(samples, profile), knots, config, frames, curve=False)[1])
                          for _, profile, score in folds])
    log_g, _ = _solve(samples, knots, config, frames)
    return ResponseFit(
        knots,
        log_g,
        float(declared.median()),
        float(fitted.median()),
        int(ci.numel()),
        _clearly_better(fitted, declared),
    )


def with_estimated_response(capture: Capture, config: ResponseConfig = DEFAULT) -> tuple[Capture, ResponseFit | None]:
    """The capture re-encoded through the response its frames show, when it explains them better
    than the declared curve (module docstring, `fit_response`); `metadata["response"]` says what
    was decided."""
    fit = fit_response(capture, config)
    meta = dict(capture.metadata)
    if fit is None:
        meta["response"] = {"used": False, "why": "the frames' exposures do not vary enough to tell a curve"}
        return replace(capture, metadata=meta), None
    meta["response"] = {"used": fit.better, **fit.as_dict(),
                        "why": ("it explains held-out frames better than the declared curve" if fit.better else
                                "the declared curve explains held-out frames as well or better")}
    if not fit.better:
        return replace(capture, metadata=meta), fit
    return replace(capture, frames=fit.apply(capture.frames), metadata=meta), fit
