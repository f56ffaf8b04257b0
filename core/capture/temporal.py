"""Does the lighting change over time? Decide whether the light field gets a time input.

Statistic (documented in docs/engine.md):
1. Linearise frames (inverse tone map) and take luminance, then area-downsample (linear
   values are resampled, never gamma-encoded ones, whose averaging biases linear means when
   there is noise). (A moving camera: see below.)
2. Drop clipped (LDR >= 0.99) and near-black (LDR < 0.02) pixels, which carry no ratio, and
   pixels within CLIP_MARGIN of a clipped one: around a saturated source an 8-bit video's codec
   rings and a lens glares, by amounts that follow the exposure, not the light; a pixel is used
   only if it is usable in EVERY frame (same pixel set for all frames).
3. Average linear luminance in a coarse grid of blocks (BLOCKS_Y x BLOCKS_X) per frame and take
   logs: l[t, b]. Block averaging suppresses sensor noise and block-compression artefacts.
4. Deviation e[t] = mean over blocks of |l[t, b] - median_t l[t, b]|: how far frame t's
   lighting is from the clip's typical lighting, on average over the image. A local lamp that
   switches changes many blocks by a large factor; a small moving object changes few.
   statistic = max_t e[t].
5. Noise floor sigma = 1.4826 * MAD of consecutive block differences / sqrt(2) (a step change
   happens at few frame pairs, so the MAD ignores it). threshold = max(ABS_FLOOR, K_SIGMA * sigma).
uses_time = statistic > threshold.

A moving camera (poses given or tracked) soon sees nothing frame 0 saw, so frames are
compared with their predecessor instead: frame t is warped into frame t-1's view with depth
and poses (pixels that leave the view or fail a 5 % depth-consistency test are dropped),
both are block-averaged over the pixels usable in both, and d[t, b] = l_t - l_{t-1} per
block. The lighting trajectory L[t] = sum of the per-pair MEDIAN block change (a global
change, chained over the clip) gives e_global[t] = |L[t] - median_t L|; a change confined
to part of the view gives e_local[t] = mean_b |d'[t, b]|, with d' the same change of the
blocks' 3 x 3 neighbourhood means (NEIGHBOURHOOD: the edges of something that moves carry its
light between neighbouring blocks, which cancels there). statistic = max of both over t;
sigma = 1.4826 * MAD of all d / sqrt(2); the same threshold. A camera's own motion thus
never reads as a lighting change, and a pan that ends far from where it started still
compares every frame with one it overlaps.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Literal, get_args

import torch
import torch.nn.functional as F

from core.camera import Camera
from core.conventions import inverse_tonemap, valid_depth_mask

TemporalMode = Literal["auto", "on", "off"]  # the user's choice: detect, or force a time input on / off
TEMPORAL_MODES: tuple[str, ...] = get_args(TemporalMode)
BLOCKS_Y, BLOCKS_X = 6, 8
ABS_FLOOR = math.log(1.08)  # an 8 % mean change over the image is the smallest we call "lighting"
K_SIGMA = 4.0
CLIP_HI, DARK_LO = 0.99, 0.02
CLIP_MARGIN = 2  # source pixels around a clipped one left out (the codec's ringing, the lens's glare)
ANALYSIS_HEIGHT = 72  # frames are area-downsampled to this height first (speed, noise)
MIN_BLOCK_FRACTION = 0.2
OVERLAP_PAIRS_PER_FRAME = 6  # a moving camera's frames are compared with at most this many later ones that overlap
NEIGHBOURHOOD = 3  # blocks: the moving-camera local statistic compares 3 x 3 block means (an edge that moves cancels)


@dataclass(frozen=True)
class TemporalDecision:
    uses_time: bool
    statistic: float
    threshold: float
    reason: str
    mode: str = "auto"

    def as_dict(self) -> dict:
        return asdict(self)


AUTO_EXPOSURE_HINT = ("the whole view changed alike, as a camera's auto-exposure does: if it did, give the "
                      "frames' exposures (params.frame_ev) or frame_ev='estimate' (docs/captures.md, Exposure)")
# (shown only when no exposures are known: a moving camera said to be locked, or a static one)


def _luminance(rgb: torch.Tensor) -> torch.Tensor:
    return 0.2126 * rgb[..., 0] + 0.7152 * rgb[..., 1] + 0.0722 * rgb[..., 2]


def _analysis_planes(capture, h: int, w: int) -> torch.Tensor:
    """[T, h, w, 2]: linear luminance and a 0/1 'usable' plane (neither clipped, nor within
    CLIP_MARGIN of a clipped pixel, nor near black), linearised BEFORE any resampling
    (averaging gamma-encoded noise would bias linear means downwards)."""
    out = []
    for f, ev in zip(capture.frames, capture.frame_ev):
        peak = f.amax(-1)
        clipped = F.max_pool2d((peak >= CLIP_HI).float()[None, None], 2 * CLIP_MARGIN + 1, 1, CLIP_MARGIN)[0, 0] > 0
        usable = (~clipped & (peak >= DARK_LO)).float()
        planes = torch.stack((_luminance(inverse_tonemap(f, ev)), usable), 0)[None]  # a stated exposure removed
        out.append(F.interpolate(planes, size=(h, w), mode="area")[0].permute(1, 2, 0))
    return torch.stack(out)


def block_log_luminance(capture) -> torch.Tensor:
    """[T, B] log mean linear luminance per block of a STATIC camera's frames (NaN where a
    block has too few usable pixels)."""
    small = capture.resized(ANALYSIS_HEIGHT)
    T, h, w = small.depth.shape
    planes = _analysis_planes(capture, h, w)
    usable = planes[..., 1] > 0.999  # every source pixel under the footprint usable
    # the SAME pixels in every frame: a per-frame pixel set would bias block means whenever
    # noise pushes dim pixels across DARK_LO
    usable = usable.all(dim=0, keepdim=True).expand_as(usable)
    return _block_logs(planes[..., 0], usable)


def _block_logs(lum: torch.Tensor, usable: torch.Tensor, neighbourhood: bool = False) -> torch.Tensor:
    """[N, B] log mean linear luminance per block of [N, h, w] planes over `usable` pixels
    (NaN where a block has too few). With `neighbourhood`, each block's mean is taken over it
    and the blocks around it (3 x 3): light that only moves between neighbouring blocks (the
    edges of something moving) then cancels."""
    num = F.adaptive_avg_pool2d(torch.where(usable, lum, 0.0)[:, None], (BLOCKS_Y, BLOCKS_X))
    cnt = F.adaptive_avg_pool2d(usable.float()[:, None], (BLOCKS_Y, BLOCKS_X))
    if neighbourhood:
        num, cnt = (F.avg_pool2d(x, NEIGHBOURHOOD, 1, NEIGHBOURHOOD // 2, count_include_pad=False) for x in (num, cnt))
    out = torch.log((num / cnt.clamp_min(1e-12)).clamp_min(1e-8))
    out = torch.where(cnt >= MIN_BLOCK_FRACTION, out, torch.full_like(out, float("nan")))
    return out.reshape(lum.shape[0], -1)


def _warp_into(planes_src: torch.Tensor, depth_ref: torch.Tensor, depth_src: torch.Tensor, intr, pose_ref, pose_src):
    """Planes [h, w, C] of a source view warped into a reference view; (warped, valid [h, w])."""
    h, w, _ = planes_src.shape
    pts = Camera(intr, pose_ref).unproject(depth_ref.double())
    ok = torch.isfinite(pts).all(-1)
    u, v, z = Camera(intr, pose_src).project(torch.nan_to_num(pts))
    gx, gy = (u / w) * 2 - 1, (v / h) * 2 - 1
    grid = torch.stack((gx, gy), -1).float()[None]
    img = F.grid_sample(planes_src.permute(2, 0, 1)[None], grid, mode="bilinear", align_corners=False)[0]
    dz = F.grid_sample(depth_src[None, None].nan_to_num(0.0), grid, mode="nearest", align_corners=False)[0, 0]
    ok = ok & (z > 0) & (gx.abs() <= 1) & (gy.abs() <= 1) & ((dz.double() - z).abs() <= 0.05 * z)
    return img.permute(1, 2, 0), ok


def _consecutive_changes(capture):
    """A moving camera's frame-to-frame brightness changes: each frame warped into its
    predecessor, per-block log differences over the pixels usable in both. Returns (steps:
    [T-1] median block difference per pair, 0 without a shared block; local: [T-1] mean |block
    difference|; diffs: the pairs' block differences; blind: frames without a shared block)."""
    small = capture.resized(ANALYSIS_HEIGHT)
    T, h, w = small.depth.shape
    planes = _analysis_planes(capture, h, w)
    depth = torch.where(valid_depth_mask(small.depth), small.depth, torch.nan)
    steps, local, diffs, blind = [], [], [], []
    for t in range(1, T):
        warped, ok = _warp_into(
            planes[t], depth[t - 1], depth[t], small.intrinsics, capture.poses[t - 1], capture.poses[t]
        )
        usable = ok & (planes[t - 1][..., 1] > 0.999) & (warped[..., 1] > 0.999)
        pair = torch.stack((planes[t - 1][..., 0], warped[..., 0])), usable[None].expand(2, -1, -1)
        logs = _block_logs(*pair)
        keep = torch.isfinite(logs).all(0)
        if int(keep.sum()) == 0:
            steps.append(0.0), local.append(0.0), blind.append(t)
            continue
        d = (logs[1, keep] - logs[0, keep]).double()
        steps.append(float(d.median()))
        around = _block_logs(*pair, neighbourhood=True)
        near = torch.isfinite(around).all(0)
        local.append(float((around[1, near] - around[0, near]).abs().mean()))
        diffs.append(d)
    return steps, local, diffs, blind


def _overlapping_pairs(capture) -> list[tuple[int, int]]:
    """Frame pairs (i < j) of a moving camera that may show the same surfaces: consecutive frames
    and any whose optical axes are within the diagonal field of view (a pan back, a scan's
    rings), at most OVERLAP_PAIRS_PER_FRAME later partners per frame, nearest in angle first."""
    k = capture.intrinsics
    diag = math.degrees(2 * math.atan(math.hypot(k.width / (2 * k.fx), k.height / (2 * k.fy))))
    axes = -capture.poses[:, :3, 2].to(torch.float64)
    angle = torch.rad2deg(torch.acos((axes @ axes.T).clamp(-1.0, 1.0)))
    T = capture.num_frames
    pairs = {(i, i + 1) for i in range(T - 1)}
    for i in range(T - 1):
        later = [j for j in range(i + 2, T) if float(angle[i, j]) <= diag]
        later.sort(key=lambda j: float(angle[i, j]))
        pairs.update((i, j) for j in later[:OVERLAP_PAIRS_PER_FRAME])
    return sorted(pairs)


def overlap_course(capture) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """A moving camera's overall log brightness per frame [T] (relative to frame 0) from every
    pair of frames that show the same surfaces (`_overlapping_pairs`, the later frame warped into
    the earlier by depth and poses): the median block difference of each pair, then per-frame
    values fitted to all of them by least squares (weighted by the blocks they share), as a
    panorama stitcher balances exposures. A chain of consecutive frames would add up every
    step's error; the pairs of a pan back or a scan's rings tie the ends together. Also returns
    the consecutive pairs' block differences (the noise estimate). Frames no pair reaches keep
    the value of the last one before them."""
    small = capture.resized(ANALYSIS_HEIGHT)
    T, h, w = small.depth.shape
    planes = _analysis_planes(capture, h, w)
    depth = torch.where(valid_depth_mask(small.depth), small.depth, torch.nan)
    rows, vals, weights, consecutive = [], [], [], []
    for i, j in _overlapping_pairs(capture):
        warped, ok = _warp_into(planes[j], depth[i], depth[j], small.intrinsics, capture.poses[i], capture.poses[j])
        usable = ok & (planes[i][..., 1] > 0.999) & (warped[..., 1] > 0.999)
        logs = _block_logs(torch.stack((planes[i][..., 0], warped[..., 0])), usable[None].expand(2, -1, -1))
        keep = torch.isfinite(logs).all(0)
        if int(keep.sum()) == 0:
            continue
        d = (logs[1, keep] - logs[0, keep]).double()
        rows.append((i, j)), vals.append(float(d.median())), weights.append(float(keep.sum()))
        if j == i + 1:
            consecutive.append(d)
    course = torch.zeros(T, dtype=torch.float64)
    if not rows:
        return course, consecutive
    A = torch.zeros(len(rows) + 1, T, dtype=torch.float64)
    b = torch.zeros(len(rows) + 1, dtype=torch.float64)
    for n, ((i, j), d, wt) in enumerate(zip(rows, vals, weights)):
        A[n, j], A[n, i], b[n] = math.sqrt(wt), -math.sqrt(wt), math.sqrt(wt) * d
    A[-1, 0] = 1e3  # gauge: frame 0 at 0
    reached = torch.zeros(T, dtype=torch.bool)
    reached[0] = True
    for i, j in rows:
        reached[i] = reached[j] = True
    A[:, ~reached] = 0.0
    course = torch.linalg.lstsq(A, b[:, None]).solution[:, 0]
    for t in range(1, T):
        if not bool(reached[t]):
            course[t] = course[t - 1]
    return course, consecutive


def global_log_course(capture) -> torch.Tensor:
    """[T] float64: each frame's overall log brightness relative to frame 0, from what frames
    both show (blocks usable in every frame for a static camera; every overlapping pair of a
    moving one, `overlap_course`): the median over blocks, so a change confined to part of the
    view moves it little. What an auto-exposure changes."""
    T = capture.num_frames
    if T < 2:
        return torch.zeros(T, dtype=torch.float64)
    if not capture.static_camera:
        return overlap_course(capture)[0]
    l = block_log_luminance(capture)
    keep = torch.isfinite(l).all(0)
    if int(keep.sum()) == 0:
        return torch.zeros(T, dtype=torch.float64)
    l = l[:, keep].double()
    return (l - l[:1]).median(dim=1).values


def detect_temporal_moving(capture) -> TemporalDecision:
    """The moving-camera statistic: overlapping frames, warped (module docstring)."""
    steps, local, diffs, blind = _consecutive_changes(capture)
    if not diffs:
        return TemporalDecision(False, float("nan"), float("nan"),
                                "no two consecutive frames share a usable image block (saturated/dark/occluded): "
                                "assuming static lighting")
    L = overlap_course(capture)[0]
    e_global = (L - L.median()).abs()
    e_local = torch.tensor([0.0] + local, dtype=torch.float64)
    dev = torch.maximum(e_global, e_local)
    stat = float(dev.max())
    all_d = torch.cat(diffs)
    sigma = float(1.4826 * (all_d - all_d.median()).abs().median() / math.sqrt(2.0))
    thr = max(ABS_FLOOR, K_SIGMA * sigma)
    worst = int(dev.argmax())
    kind = "overall" if float(e_global[worst]) >= float(e_local[worst]) else "local"
    uses = stat > thr
    reason = (f"lighting {'changes' if uses else 'is stable'}: max {kind} |log-luminance change| {stat:.3f} at frame "
              f"{worst} vs threshold {thr:.3f} (noise sigma {sigma:.4f}; camera motion compensated: frames that show "
              f"the same surfaces compared, warped by depth and poses"
              f"{f', {len(blind)} pair(s) without a shared block' if blind else ''})")
    if uses and kind == "overall" and capture.stated_ev is None:  # what a phone's auto-exposure does as it pans
        reason += f"; {AUTO_EXPOSURE_HINT}"
    return TemporalDecision(uses, stat, thr, reason)


UNTRACKED_MOTION = ("the camera moves but could not be tracked: a turning view cannot be told from a change of "
                    "light without the camera's motion, so the light is taken as static (give poses, or a capture "
                    "app's export, to estimate a light that changes)")


def untracked_motion(capture) -> bool:
    """True when tracking found the camera moving but registered no track, so the frames stand at
    one pose that they were not taken from (core.tracking.track: 'failed:static-fallback')."""
    tracking = capture.metadata.get("tracking") or {}
    return bool(tracking.get("camera_moves")) and str(tracking.get("method", "")).startswith("failed")


def detect_temporal(capture) -> TemporalDecision:
    """Automatic decision (see module docstring). A moving camera that could not be tracked is
    never read as a change of light (`untracked_motion`)."""
    T = capture.num_frames
    if T < 2:
        return TemporalDecision(False, 0.0, 0.0, "single frame: no time input")
    if untracked_motion(capture):
        return TemporalDecision(False, float("nan"), float("nan"), UNTRACKED_MOTION)
    if not capture.static_camera:
        return detect_temporal_moving(capture)
    l = block_log_luminance(capture)  # [T, B]
    keep = torch.isfinite(l).all(0)  # blocks usable in every frame
    if int(keep.sum()) == 0:
        return TemporalDecision(
            False,
            float("nan"),
            float("nan"),
            "no image block is usable in every frame (saturated/dark/occluded): assuming static lighting",
        )
    l = l[:, keep].double()
    dev = (l - l.median(dim=0).values).abs().mean(dim=1)  # [T]
    stat = float(dev.max())
    diffs = (l[1:] - l[:-1]).flatten()
    sigma = float(1.4826 * (diffs - diffs.median()).abs().median() / math.sqrt(2.0))
    thr = max(ABS_FLOOR, K_SIGMA * sigma)
    worst = int(dev.argmax())
    uses = stat > thr
    verb = "changes" if uses else "is stable"
    reason = (f"lighting {verb}: max mean |log-luminance deviation| {stat:.3f} at frame {worst} vs threshold "
              f"{thr:.3f} (noise sigma {sigma:.4f}, {int(keep.sum())} blocks)")
    return TemporalDecision(uses, stat, thr, reason)


def decide_temporal(capture, mode: str = "auto") -> TemporalDecision:
    """Apply the user's override: 'on' / 'off' force the answer but still record the evidence."""
    if mode not in TEMPORAL_MODES:
        raise ValueError(f"temporal must be one of {', '.join(TEMPORAL_MODES)}, got {mode!r}")
    auto = detect_temporal(capture)
    if mode == "auto" or capture.num_frames < 2:
        return TemporalDecision(auto.uses_time, auto.statistic, auto.threshold, auto.reason, mode)
    forced = mode == "on"
    return TemporalDecision(
        forced, auto.statistic, auto.threshold, f"forced {mode} by user; auto would say: {auto.reason}", mode
    )
