"""Things moving in front of a static camera's scene (a person walking through the view), told
apart from a change of light and painted out (docs/captures.md, "Things moving through the view").

A static camera sees a room whose light may change: lights switch, dim, an exposure moves.
In linear radiance every such change is a sum of a few fixed images, each on its own course
over time (what stays, plus one image per light that changes on its own, times its intensity):
the clip, as a frames x pixels matrix, has a low rank. A person walking through does not: the
pixels they cover change at different times as they move, which no few shared courses make.
So each frame is compared with a robust low-rank model of the clip (`low_rank_course`: at
most RANK courses, each kept only if it explains most of what is left), and the pixels that
depart from it by more than TRANSIENT_RATIO (and by more than K_SIGMA times their own noise)
are transient.
They are replaced by the model's prediction: the pixel's own detail from the frames where
it is clear, on the model's course of light for that frame and pixel. Without this, a person
walking through reads as the light changing, and the prior paints them into the room's light.

Left alone, by design:
* a moving camera (its frames need warping first; not done here);
* clips of fewer than MIN_FRAMES frames (a few frames cannot tell a course of light from a
  passer-by);
* something that stays in one place for most of the clip: it is part of the scene;
* a frame whose transient share exceeds MAX_FRAME_SHARE: most of the view changed in a way no
  low-rank light explains (a cut, the camera knocked), so painting it out would invent a frame.
"""
from __future__ import annotations

import math
from dataclasses import replace

import torch
import torch.nn.functional as F

from core.capture.base import Capture
from core.capture.temporal import CLIP_HI, DARK_LO  # LDR: clipped, and too dark for a ratio
from core.conventions import inverse_tonemap, tonemap

MIN_FRAMES = 8  # fewer frames cannot separate a course of light from a passer-by
RANK = 3  # what stays + up to two lights changing on their own courses (12+ frames; 8-11: 2)
ANALYSIS_HEIGHT = 36  # the model is fitted on frames area-downsampled to this height (noise averages out;
# a passer-by still spans many pixels)
TRANSIENT_RATIO = math.log(1.3)  # a departure from the model under 30 % is not a transient
K_SIGMA = 5.0  # ... nor one within 5x the pixel's own noise (its departures' robust spread)
MAX_FRAME_SHARE = 0.5  # a frame more than half transient is left as it is
MIN_SHARE = 1e-3  # a clip with fewer transient pixels than this share is left as it is
ITERATIONS = 12
KEEP_COURSE = 0.5  # a course of light is kept if it explains at least half of the departures left


def _rank(num_frames: int) -> int:
    return RANK if num_frames >= 12 else 2


def low_rank_course(x: torch.Tensor, w: torch.Tensor, max_rank: int, iterations: int = ITERATIONS) -> tuple[torch.Tensor, int]:
    """A robust low-rank model [T, P] of `x` [T, P] (each column near 1: values over their
    median) with `w` [T, P] 0/1 (usable entries), and its rank.

    The first course of light is the frames' median course (an exposure, a change of the whole
    room). Further candidate courses are the leading singular vectors over time of what that
    leaves. Each pixel's mix of the courses is fitted robustly (`fit_courses`), so the few frames a passer-by covers it in do not pull its fit. A course
    is kept only if it explains most of what the courses before it left unexplained
    (`departures` fall by at least KEEP_COURSE): a light that changes moves all its pixels along
    one course, so one component takes all of it, where a passer-by moves each pixel in
    different frames and one component takes a little of them. The rank stops at `max_rank`."""
    course = torch.where(w > 0, x, torch.nan).nanmedian(1).values.nan_to_num(1.0)[:, None]  # [T, 1]
    model = fit_courses(x, w, course, iterations)
    left, rank = int(departures(x, w, model).sum()), 1
    if left == 0 or max_rank < 2:
        return model, rank
    more = torch.linalg.svd((x - model) * w, full_matrices=False)[0]  # what the median course leaves
    best = None
    for k in range(2, min(max_rank, more.shape[1] + 1) + 1):
        basis = torch.linalg.qr(torch.cat((course, more[:, :k - 1]), 1))[0]
        candidate = fit_courses(x, w, basis, iterations)
        now = int(departures(x, w, candidate).sum())
        if now <= (1.0 - KEEP_COURSE) * left and (best is None or now < best[1]):
            best = (candidate, now, k)
    if best is not None:
        model, left, rank = best
    return model, rank


def fit_courses(x: torch.Tensor, w: torch.Tensor, U: torch.Tensor, iterations: int = ITERATIONS) -> torch.Tensor:
    """Each column of `x` fitted as a mix of the courses `U` [T, r], by iteratively reweighted
    least squares (Cauchy weights against the column's own residual scale: `_weights`)."""
    r = U.shape[1]
    weight = w.clone()
    model = torch.ones_like(x)
    for _ in range(iterations):
        A = torch.einsum("tp,ti,tj->pij", weight, U, U) + 1e-9 * torch.eye(r, dtype=x.dtype)
        b = torch.einsum("tp,ti,tp->pi", weight, U, x)
        model = U @ torch.linalg.solve(A, b[..., None])[..., 0].T
        weight = _weights(x, w, model)
    return model


def departures(x: torch.Tensor, w: torch.Tensor, model: torch.Tensor) -> torch.Tensor:
    """[T, P] bool: usable entries over TRANSIENT_RATIO (log) from the model and over K_SIGMA
    times their column's noise (1.4826 x its median absolute log departure over time)."""
    dev = (x.clamp_min(1e-6) / model.clamp_min(1e-6)).log().abs() * w
    noise = 1.4826 * torch.where(w > 0, dev, torch.nan).nanmedian(0).values.nan_to_num(0.0)
    return (dev > torch.maximum(torch.full_like(noise, TRANSIENT_RATIO), K_SIGMA * noise)) & (w > 0)


def _weights(x: torch.Tensor, w: torch.Tensor, model: torch.Tensor) -> torch.Tensor:
    """Cauchy weights of the residuals against each pixel's own scale (1.4826 x its median
    absolute residual over time, floored by the clip's): a passer-by covers a pixel in a few
    frames, which its median over time does not see, so those entries lose their weight."""
    resid = (x - model) * w
    absr = torch.where(w > 0, resid.abs(), torch.nan)
    used = absr[w > 0]
    floor = max(float(1.4826 * used.median()) if used.numel() else 0.0, 1e-3)
    scale = (1.4826 * absr.nanmedian(0).values).nan_to_num(floor).clamp_min(floor)
    return w / (1.0 + (resid / (3.0 * scale)).square())


def transient_mask(capture: Capture) -> tuple[torch.Tensor, dict]:
    """[T, H, W] bool transient pixels of a static camera's clip (all False where nothing is
    looked for) and the evidence (`looked`, `reason`, shares, rank)."""
    T, H, W = capture.num_frames, capture.height, capture.width
    none = torch.zeros(T, H, W, dtype=torch.bool)
    if not capture.static_camera:
        return none, {"looked": False, "reason": "moving camera: not looked for"}
    if T < MIN_FRAMES:
        return none, {"looked": False, "reason": f"fewer than {MIN_FRAMES} frames: not looked for"}
    mask_small, evidence = _small_mask(capture)
    if not bool(mask_small.any()):
        return none, evidence
    mask = F.interpolate(mask_small[:, None].float(), size=(H, W), mode="nearest")[:, 0] > 0.5
    return mask, evidence


def _small_mask(capture: Capture) -> tuple[torch.Tensor, dict]:
    T = capture.num_frames
    h = min(ANALYSIS_HEIGHT, capture.height)
    w = max(1, round(capture.width * h / capture.height))
    ldr = capture.frames.permute(0, 3, 1, 2)
    peak = ldr.max(1, keepdim=True).values
    usable = ((peak < CLIP_HI) & (peak >= DARK_LO)).float()
    lin = F.interpolate(inverse_tonemap(ldr), size=(h, w), mode="area")  # linearised before averaging
    usable = F.interpolate(usable, size=(h, w), mode="area") > 0.999
    x = lin.permute(0, 2, 3, 1).reshape(T, -1).double()  # [T, h*w*3]
    ok = usable.permute(0, 2, 3, 1).expand(-1, -1, -1, 3).reshape(T, -1)
    enough = ok.sum(0) >= (T + 1) // 2  # a pixel usable in most frames has a median to stand on
    med = torch.where(ok, x, torch.nan).nanmedian(0).values
    x = torch.where(ok & enough, x / med.clamp_min(1e-12), torch.ones_like(x))
    wt = (ok & enough).double()
    model, rank = low_rank_course(x, wt, _rank(T))
    flagged = departures(x, wt, model).reshape(T, h, w, 3).any(-1)
    # something in front of the scene covers a region: a pixel flagged with fewer than half its
    # 3x3 neighbourhood is noise; the rest grow by a pixel, which shares the edge's blend
    near = F.avg_pool2d(flagged[:, None].float(), 3, stride=1, padding=1, count_include_pad=False)[:, 0]
    flagged = flagged & (near >= 0.5)
    flagged = F.max_pool2d(flagged[:, None].float(), 3, stride=1, padding=1)[:, 0] > 0.5
    share = flagged.reshape(T, -1).float().mean(1)
    too_much = share > MAX_FRAME_SHARE
    flagged[too_much] = False
    total = float(flagged.float().mean())
    evidence = {"looked": True, "rank": rank, "analysis_height": h,
                "frames_with_transients": int((flagged.reshape(T, -1).any(1)).sum()),
                "pixel_share": round(total, 5), "max_frame_share": round(float(share[~too_much].max()) if bool((~too_much).any()) else 0.0, 4),
                "frames_left_alone": [int(i) for i in torch.nonzero(too_much).flatten()]}
    if total < MIN_SHARE:
        flagged[:] = False
        evidence["frames_with_transients"] = 0
        evidence["reason"] = f"nothing moved through the view (transient share {total:.5f} < {MIN_SHARE})"
    else:
        evidence["reason"] = "something moved through the view: its pixels painted out"
    evidence["model"] = model.float().reshape(T, h, w, 3)
    return flagged, evidence


def paint_out(capture: Capture, mask: torch.Tensor, model_small: torch.Tensor) -> Capture:
    """The capture with `mask`ed pixels [T, H, W] replaced: the pixel's detail from the frames
    where it is clear (its linear value over the model's course, median), times the model's
    course [T, h, w, 3] at that frame; depth from the pixel's clear frames (median). Only the
    pixels masked in some frame are touched (memory: a long clip at full resolution)."""
    T, H, W = mask.shape
    where = mask.any(0)  # [H, W]
    course = torch.stack([F.interpolate(model_small[t].permute(2, 0, 1)[None], size=(H, W), mode="bilinear",
                                        align_corners=False)[0].permute(1, 2, 0)[where] for t in range(T)])
    course = course.clamp_min(1e-6)  # [T, N, 3]
    ldr = capture.frames[:, where]  # [T, N, 3]
    hit = mask[:, where]  # [T, N]
    clear = ~hit
    detail = torch.where(clear[..., None], inverse_tonemap(ldr) / course, torch.nan).nanmedian(0).values  # [N, 3]
    swap = hit & clear.any(0)[None]  # a pixel never clear keeps what it showed
    painted = tonemap(detail[None] * course).clamp(0.0, 1.0)
    frames = capture.frames.clone()
    frames[:, where] = torch.where(swap[..., None], painted, ldr)
    depth = capture.depth.clone()
    d = depth[:, where]
    clear_depth = torch.where(clear, d, torch.nan).nanmedian(0).values  # [N]
    depth[:, where] = torch.where(swap, clear_depth[None].expand_as(d), d)
    return replace(capture, frames=frames, depth=depth, full_resolution=None)


def without_transients(capture: Capture, params=None) -> Capture:
    """The capture with what moved through a static camera's view painted out, the evidence in
    `metadata["transients"]` and a warning when anything was (`params.transients="keep"`: as is)."""
    mode = getattr(params, "transients", "remove") if params is not None else "remove"
    if mode == "keep":
        return capture
    mask, evidence = transient_mask(capture)
    model = evidence.pop("model", None)
    meta = dict(capture.metadata)
    meta["transients"] = evidence
    if model is None or not bool(mask.any()):
        return replace(capture, metadata=meta)
    cleaned = paint_out(capture, mask, model)
    share = float(mask.float().mean())
    warning = (f"something moved through the view in {evidence['frames_with_transients']} of {capture.num_frames} frames "
               f"(a person walking through?): {100 * share:.1f} % of the clip's pixels were painted out from the frames "
               f"where they were clear, so it is not read as the light changing; params.transients='keep' keeps them")
    return replace(cleaned, metadata=meta, warnings=[*capture.warnings, warning])
