"""Things moving through the view (a person walking through), told apart from a change of
light and painted out, so that they are not read as the light changing and the prior does not
paint them into the room's light (docs/captures.md, "Things moving through the view").

A static camera (`_static_mask`) sees a room whose light may change: lights switch, dim, an
exposure moves. In linear radiance every such change is a sum of a few fixed images, each on
its own course over time (what stays, plus one image per light that changes on its own, times
its intensity): the clip, as a frames x pixels matrix, has a low rank. A person walking
through does not: the pixels they cover change at different times as they move, which no few
shared courses make. So each frame is compared with a robust low-rank model of the clip
(`low_rank_course`: at most `rank` courses, each kept only if it explains most of what is
left); the pixels that depart from it by more than `transient_ratio` (and by more than
`k_sigma` times their own noise; the knobs are capture.transients.*, core/capture/config.py)
are transient, and are replaced by the pixel's own detail from the frames
where it is clear, on the model's course of light for that frame (`paint_out`).

A moving camera (`_moving_mask`) has no fixed pixels: each frame is compared with its
neighbours before and after it, warped into it by depth and poses, and painted from their
median (`paint_from_neighbours`).

Left alone, by design:
* clips of fewer than capture.transients.min_frames frames (a few frames cannot tell a course of light from a
  passer-by);
* something that stays in one place for most of a static clip, or on the same part of the
  room for most of a moving camera's window (someone the camera follows);
* a frame whose transient share exceeds capture.transients.max_frame_share: most of the view changed in a way no
  light explains (a cut, the camera knocked), so painting it out would invent a frame.
"""
from __future__ import annotations

from dataclasses import replace

import torch
import torch.nn.functional as F

from core.capture.base import Capture
from core.capture.config import TransientsConfig, capture_config
from core.capture.temporal import CLIP_HI, DARK_LO, _warp_into  # LDR: clipped, and too dark for a ratio
from core.conventions import (  # the tone curve: d(log linear)/d(LDR) = GAMMA/LDR
    GAMMA,
    inverse_tonemap,
    tonemap,
    valid_depth_mask,
)


def _knobs() -> TransientsConfig:
    return capture_config().transients


def _rank(num_frames: int) -> int:
    return _knobs().rank if num_frames >= 12 else 2


def low_rank_course(
    x: torch.Tensor, w: torch.Tensor, max_rank: int, iterations: int | None = None
) -> tuple[torch.Tensor, int]:
    """A robust low-rank model [T, P] of `x` [T, P] (each column near 1: values over their
    median) with `w` [T, P] 0/1 (usable entries), and its rank.

    The first course of light is the frames' median course (an exposure, a change of the whole
    room). Further candidate courses are the leading singular vectors over time of what that
    leaves. Each pixel's mix of the courses is fitted robustly (`fit_courses`), so the few frames a passer-by covers it
    in do not pull its fit. A course
    is kept only if it explains most of what the courses before it left unexplained
    (`departures` fall by at least capture.transients.keep_course): a light that changes moves all its pixels along
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
        if now <= (1.0 - _knobs().keep_course) * left and (best is None or now < best[1]):
            best = (candidate, now, k)
    if best is not None:
        model, left, rank = best
    return model, rank


def fit_courses(x: torch.Tensor, w: torch.Tensor, U: torch.Tensor, iterations: int | None = None) -> torch.Tensor:
    """Each column of `x` fitted as a mix of the courses `U` [T, r], by iteratively reweighted
    least squares (Cauchy weights against the column's own residual scale: `_weights`)."""
    iterations = _knobs().iterations if iterations is None else iterations
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
    """[T, P] bool: usable entries over capture.transients.transient_ratio (log) from the model
    and over capture.transients.k_sigma times their column's noise (1.4826 x its median absolute
    log departure over time)."""
    dev = (x.clamp_min(1e-6) / model.clamp_min(1e-6)).log().abs() * w
    noise = 1.4826 * torch.where(w > 0, dev, torch.nan).nanmedian(0).values.nan_to_num(0.0)
    return (dev > torch.maximum(torch.full_like(noise, _knobs().transient_ratio), _knobs().k_sigma * noise)) & (w > 0)


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
    """[T, H, W] bool transient pixels of a clip (all False where nothing is looked for) and the
    evidence (`looked`, `camera`, `reason`, shares; a static camera's `rank`), with the model
    the pixels are painted from (`evidence["model"]`, popped by `without_transients`)."""
    T, H, W = capture.num_frames, capture.height, capture.width
    none = torch.zeros(T, H, W, dtype=torch.bool)
    if T < _knobs().min_frames:
        return none, {"looked": False, "reason": f"fewer than {_knobs().min_frames} frames: not looked for"}
    mask_small, evidence = _static_mask(capture) if capture.static_camera else _moving_mask(capture)
    if not bool(mask_small.any()):
        return none, evidence
    mask = F.interpolate(mask_small[:, None].float(), size=(H, W), mode="nearest")[:, 0] > 0.5
    return mask, evidence


def _analysis(capture: Capture, h: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(linear frames [T, h, w, 3] area-downsampled after linearising, usable [T, h, w]: every
    source pixel neither clipped nor too dark)."""
    w = max(1, round(capture.width * h / capture.height))
    ldr = capture.frames.permute(0, 3, 1, 2)
    peak = ldr.max(1, keepdim=True).values
    usable = F.interpolate(((peak < CLIP_HI) & (peak >= DARK_LO)).float(), size=(h, w), mode="area")[:, 0] > 0.999
    lin = F.interpolate(inverse_tonemap(ldr), size=(h, w), mode="area").permute(0, 2, 3, 1)
    return lin, usable


def _tidy(flagged: torch.Tensor, evidence: dict) -> tuple[torch.Tensor, dict]:
    """Flags [T, h, w] as regions: something in front of the scene covers a region, so a pixel
    flagged with fewer than half its 3x3 neighbourhood is noise, and the rest grow by a pixel,
    which shares the edge's blend; frames over capture.transients.max_frame_share and clips under
    capture.transients.min_share are left alone. The evidence gains the shares and the reason."""
    T = flagged.shape[0]
    near = F.avg_pool2d(flagged[:, None].float(), 3, stride=1, padding=1, count_include_pad=False)[:, 0]
    flagged = flagged & (near >= 0.5)
    flagged = F.max_pool2d(flagged[:, None].float(), 3, stride=1, padding=1)[:, 0] > 0.5
    share = flagged.reshape(T, -1).float().mean(1)
    too_much = share > _knobs().max_frame_share
    flagged[too_much] = False
    total = float(flagged.float().mean())
    evidence.update({"looked": True, "analysis_height": int(flagged.shape[1]),
                     "frames_with_transients": int((flagged.reshape(T, -1).any(1)).sum()),
                     "pixel_share": round(total, 5),
                     "max_frame_share": round(float(share[~too_much].max()) if bool((~too_much).any()) else 0.0, 4),
                     "frames_left_alone": [int(i) for i in torch.nonzero(too_much).flatten()]})
    if total < _knobs().min_share:
        flagged[:] = False
        evidence["frames_with_transients"] = 0
        evidence["reason"] = f"nothing moved through the view (transient share {total:.5f} < {_knobs().min_share})"
    else:
        evidence["reason"] = "something moved through the view: its pixels painted out"
    return flagged, evidence


def _static_mask(capture: Capture) -> tuple[torch.Tensor, dict]:
    T = capture.num_frames
    lin, usable = _analysis(capture, min(_knobs().analysis_height, capture.height))
    _, h, w, _ = lin.shape
    x = lin.reshape(T, -1).double()  # [T, h*w*3]
    ok = usable[..., None].expand(-1, -1, -1, 3).reshape(T, -1)
    enough = ok.sum(0) >= (T + 1) // 2  # a pixel usable in most frames has a median to stand on
    med = torch.where(ok, x, torch.nan).nanmedian(0).values
    x = torch.where(ok & enough, x / med.clamp_min(1e-12), torch.ones_like(x))
    wt = (ok & enough).double()
    model, rank = low_rank_course(x, wt, _rank(T))
    flagged, evidence = _tidy(departures(x, wt, model).reshape(T, h, w, 3).any(-1), {"camera": "static", "rank": rank})
    evidence["model"] = model.float().reshape(T, h, w, 3)
    return flagged, evidence


def _moving_mask(capture: Capture) -> tuple[torch.Tensor, dict]:
    """A moving camera's frames: each frame against the medians of its capture.transients.moving_window neighbours
    before and after it, warped into it by depth and poses (core.capture.temporal's warp), each
    neighbour first scaled by its median log ratio to the frame over what both show (an
    exposure, a change of the whole room). A passer-by who covers a point of the room in this
    frame and in fewer than half the frames either side departs from both medians the same way;
    a light that switched within the window agrees with the side the frame is on. A point that
    fewer than capture.transients.moving_min_side neighbours see on one side (the clip's first and last frames, the
    edge of a pan's view) is judged by the other side alone, if all capture.transients.moving_one_side neighbours
    there see it and no light switched within the window (capture.transients.switch_share of the points judged
    both ways agree with one side only); else not judged. Painted from the median of all the
    neighbours."""
    T = capture.num_frames
    small = capture.resized(min(_knobs().moving_height, capture.height))
    lin, usable = _analysis(capture, small.height)
    depth = torch.where(valid_depth_mask(small.depth), small.depth, torch.nan)
    flagged = torch.zeros(usable.shape, dtype=torch.bool)
    consensus = lin.clone()
    for t in range(T):
        sides = {-1: [], 1: []}
        for n in range(max(0, t - _knobs().moving_window), min(T, t + _knobs().moving_window + 1)):
            if n == t:
                continue
            planes = torch.cat((lin[n], usable[n][..., None].float()), -1)
            warped, ok = _warp_into(planes, depth[t], depth[n], small.intrinsics, capture.poses[t], capture.poses[n])
            ok = ok & (warped[..., 3] > 0.999)
            both = ok & usable[t]
            if int(both.sum()) < _knobs().min_shared_pixels:
                continue
            scale = (warped[..., :3][both].clamp_min(1e-8).log() - lin[t][both].clamp_min(1e-8).log()).median()
            sides[1 if n > t else -1].append(torch.where(ok[..., None], warped[..., :3] / scale.exp(), torch.nan))
        if not sides[-1] and not sides[1]:
            continue
        nan = torch.full_like(lin[t], torch.nan)[None]
        before = torch.stack(sides[-1]) if sides[-1] else nan
        after = torch.stack(sides[1]) if sides[1] else nan
        n_before = torch.isfinite(before[..., 0]).sum(0)
        n_after = torch.isfinite(after[..., 0]).sum(0)
        two_sided = (n_before >= _knobs().moving_min_side) & (n_after >= _knobs().moving_min_side)
        one_sided = ~two_sided & ((n_before >= _knobs().moving_one_side) | (n_after >= _knobs().moving_one_side))
        judged = usable[t] & (two_sided | one_sided)
        if not bool(judged.any()):
            continue
        own = lin[t].clamp_min(1e-6).log()
        d_before = _beyond_local_range(own, before.nanmedian(0).values)  # [h, w, 3]
        d_after = _beyond_local_range(own, after.nanmedian(0).values)
        # a passer-by departs from both sides alike; a light that switched agrees with one side
        same_way = torch.sign(d_before) == torch.sign(d_after)
        dev = torch.where(same_way, torch.minimum(d_before.abs(), d_after.abs()), torch.zeros_like(d_before))
        one = torch.where(n_before[..., None] >= _knobs().moving_one_side, d_before, d_after).abs()  # NaN-free side
        dev = torch.where(two_sided[..., None], dev, one.nan_to_num(0.0)).max(-1).values
        median = torch.cat((before, after)).nanmedian(0).values
        plain = (own - median.clamp_min(1e-6).log()).abs().max(-1).values  # the frame's noise: their robust spread
        scored = judged & plain.isfinite()
        noise = 1.4826 * float(plain[scored].median()) if bool(scored.any()) else 0.0
        threshold = max(_knobs().transient_ratio, _knobs().k_sigma * noise)
        # where the light switched within the window (points that depart from one side and agree
        # with the other), one side alone cannot tell a switch from a passer-by: not judged
        # (a switch between two frames of one side: the neighbours beyond it all depart the same
        # way and the nearer ones agree, and every neighbour of the other side agrees; something
        # that comes into view in the next frame or two and moves on is not that)
        near_b, near_a = before.flip(0), after  # nearest first
        switched = (
            two_sided
            & usable[t]
            & (
                (_switch_beyond(own, near_b, threshold) & _agrees(own, near_a, threshold))
                | (_switch_beyond(own, near_a, threshold) & _agrees(own, near_b, threshold))
            )
        )
        if int(switched.sum()) >= _knobs().switch_share * max(int((two_sided & usable[t]).sum()), 1):
            judged = judged & two_sided
        # a dark pixel's log is noisier: the frame's noise in 8-bit units (tone curve slope
        # GAMMA / value), scaled back to each pixel's log
        slope = GAMMA / tonemap(lin[t]).max(-1).values.clamp_min(DARK_LO)
        noise_ldr = 1.4826 * float((plain / slope)[scored].median()) if bool(scored.any()) else 0.0
        flagged[t] = judged & (dev > torch.clamp(_knobs().k_sigma * noise_ldr * slope, min=_knobs().transient_ratio))
        consensus[t] = torch.where(judged[..., None], median.nan_to_num(0.0), lin[t])
    flagged, evidence = _tidy(flagged, {"camera": "moving", "window": _knobs().moving_window})
    evidence["neighbours"] = consensus
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


def _beyond_local_range(own_log: torch.Tensor, other: torch.Tensor) -> torch.Tensor:
    """[h, w, 3] how far (log) a frame's value lies outside the range of `other` [h, w, 3] (linear,
    NaN where unseen) over the pixel's 3x3 neighbourhood: a warp a pixel off puts an edge's
    value anywhere in that range, which is no departure (NaN where `other` is unseen)."""
    seen = ~other.isnan().any(-1, keepdim=True)
    o = torch.where(seen, other, own_log.exp()).clamp_min(1e-6).log().permute(2, 0, 1)[None]
    hi = F.max_pool2d(o, 3, stride=1, padding=1)[0].permute(1, 2, 0)
    lo = -F.max_pool2d(-o, 3, stride=1, padding=1)[0].permute(1, 2, 0)
    d = own_log - own_log.clamp(min=lo, max=hi)
    return torch.where(seen, d, torch.nan)


def _log_ratios(own_log: torch.Tensor, side: torch.Tensor) -> torch.Tensor:
    """[m, h, w] log ratio (channel mean) of a frame over each neighbour of one side ([m, h, w, 3]
    linear, NaN where it does not see the point)."""
    return (own_log[None] - side.clamp_min(1e-6).log()).mean(-1)


def _agrees(own_log: torch.Tensor, side: torch.Tensor, threshold: float) -> torch.Tensor:
    """[h, w]: every neighbour of the side that sees the point is within half the threshold."""
    r = _log_ratios(own_log, side)
    return ((r.abs() < threshold / 2) | r.isnan()).all(0)


def _switch_beyond(own_log: torch.Tensor, side_nearest_first: torch.Tensor, threshold: float) -> torch.Tensor:
    """[h, w]: for some split of the side (nearest first), the nearer neighbours agree and the
    farther ones, at least two seen, all depart the same way (unseen ones count as either)."""
    r = _log_ratios(own_log, side_nearest_first)
    seen = ~r.isnan()
    agree = (r.abs() < threshold / 2) | ~seen
    up, down = (r > threshold) | ~seen, (r < -threshold) | ~seen
    out = torch.zeros(r.shape[1:], dtype=torch.bool)
    for j in range(r.shape[0]):
        near_ok = agree[:j].all(0) if j else torch.ones_like(out)
        far_seen = seen[j:].sum(0) >= 2  # one far frame alone is something coming into view
        out |= near_ok & far_seen & (up[j:].all(0) | down[j:].all(0))
    return out


def paint_from_neighbours(capture: Capture, mask: torch.Tensor, neighbours: torch.Tensor) -> Capture:
    """A moving camera's capture with `mask`ed pixels [T, H, W] replaced by the median of the
    frame's neighbours warped into it (`neighbours` [T, h, w, 3] linear, upsampled: the painted
    region keeps the analysis height's detail, 72 rows, enough for light)."""
    T, H, W = mask.shape
    frames = capture.frames.clone()
    for t in range(T):
        if not bool(mask[t].any()):
            continue
        up = F.interpolate(neighbours[t].permute(2, 0, 1)[None], size=(H, W), mode="bilinear",
                           align_corners=False)[0].permute(1, 2, 0)
        frames[t][mask[t]] = tonemap(up[mask[t]].clamp_min(0.0)).clamp(0.0, 1.0)
    return replace(capture, frames=frames, full_resolution=None)


def without_transients(capture: Capture, params=None) -> Capture:
    """The capture with what moved through its view painted out, the evidence in
    `metadata["transients"]` and a warning when anything was (`params.transients="keep"`: as is)."""
    mode = getattr(params, "transients", "remove") if params is not None else "remove"
    if mode == "keep":
        return capture
    mask, evidence = transient_mask(capture)
    model, neighbours = evidence.pop("model", None), evidence.pop("neighbours", None)
    meta = dict(capture.metadata)
    meta["transients"] = evidence
    if not bool(mask.any()):
        return replace(capture, metadata=meta)
    if model is not None:
        cleaned, source = paint_out(capture, mask, model), "the frames where they were clear"
    else:
        cleaned, source = paint_from_neighbours(capture, mask, neighbours), "the neighbouring frames"
    share = float(mask.float().mean())
    warning = (
        f"something moved through the view in {evidence['frames_with_transients']} of {capture.num_frames} frames "
        f"(a person walking through?): {100 * share:.1f} % of the clip's pixels were painted out from {source}, "
        f"so it is not read as the light changing; params.transients='keep' keeps them"
    )
    return replace(cleaned, metadata=meta, warnings=[*capture.warnings, warning])
