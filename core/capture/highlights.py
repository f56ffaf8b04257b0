"""Clipped highlights: how much brighter than white is a saturated light source?

An 8-bit pixel at 255 only says "at least white". Light sources are what clips, and their
true radiance decides the lighting, so a single fixed boost (the old CLIP_BOOST = 8x) is
wrong by several stops either way. This module estimates, per clipped blob (8-connected
clipped pixels, any channel >= CLIP_LDR), a radiance factor from what the capture offers:

1. Exposure changes across frames (a static camera's video with auto-exposure): where the
   same pixel is unclipped in a darker frame, its value scaled by the frames' exposure
   ratio IS the radiance (`recover_from_exposures`). Used only where the recovered value
   is above white (otherwise the light changed, not the exposure).
2. Otherwise the blob rule (`blob_boost`): log2(boost) = c . (1, log2(area / REF_AREA_SR),
   edge_stops, white_fraction, spill_stops), clamped to [0, MAX_BOOST_STOPS]: the blob's
   solid angle; how dark its surround is (a blob on a dark surround is a source, one fading
   into bright neighbours a bright surface); the share of its pixels with all channels
   clipped (white-hot vs a saturated colour); and the light its halo holds above the
   background (blur and glare spill a share of a source's energy past its edge). The
   coefficients are fitted by bench/calibration/clip_rule.py on every indoor panorama (refitted without
   the scored room by the accuracy benches); the fit, its measured error in stops and its
   known limit (very bright point sources are underestimated) are in docs/highlights.md. A
   log-linear extrapolation of the halo into the core was tried and got no weight on dev.
3. The colour of a white-hot blob (`spill_colour`): its pixels say only "every channel at
   least white", so the rule's factor would leave a warm lamp white. The halo's excess over
   its background is the source's own light (lens glare and blur spill it past the edge; the
   surface around a lamp is lit by it), so its chromaticity stands for the source's, where
   that excess is clear of the background (SPILL_COLOUR_MIN_EXCESS) and only as saturated as
   SPILL_COLOUR_MIN_RATIO allows (a coloured wall tints the spill too). No channel of a
   recoloured pixel drops below its linearised value: it is still at least white.
4. A static camera's frames (`stops_over_time`): one source is followed over the frames by
   the overlap of its blobs (`source_tracks`); its level is the mean of the rule's stops and
   its changes those of the light on a fixed ring of pixels around it. Frame by frame, the
   rule's surround features made a dimming lamp brighten.

Everything is in the linear units of core.conventions.inverse_tonemap (white = 1 at ev 0).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from core.conventions import inverse_tonemap
from core.exposure import LUMINANCE_WEIGHTS, luminance

CLIP_LDR = 0.99  # a pixel with any channel at or above this is clipped
HALO_RINGS = 8  # rings 1..HALO_RINGS pixels outside a blob sample its halo
BACKGROUND_RINGS = 2  # the outermost rings stand for the background the halo sits on
REF_AREA_SR = 1e-3  # steradians: the area term is relative to a ~1.8 deg wide source
MAX_BOOST_STOPS = 12.0
HALO_FLOOR = 1e-4  # darker halo rings count as this (linear, white = 1)
# Fitted by `python -m bench.calibration.clip_rule --fit` on every indoor panorama of MANIFEST.tsv (dev, test
# and extra: what a user gets; docs/highlights.md). Scored only under leave-one-room-out, where
# each room's job gets the fit on the other rooms (bench.calibration.clip_rule.cv_coefficients).
RULE_COEFFICIENTS = (-0.297, -0.065, -0.576, 1.476, -0.080)
# The spill's colour is used when its excess luminance over the background is at least this
# share of the background (else it is noise on the background's own colour), with each
# channel at least SPILL_COLOUR_MIN_RATIO of the largest (a tinted wall tints the spill too).
# Chosen by `python -m bench.calibration.clip_rule --colour-cv` on every indoor room (what a user gets); the
# leave-one-room-out choice is the same in 23 of 24 folds (docs/highlights.md), and each room's
# job in the accuracy benches gets its fold's (bench.calibration.clip_rule.cv_spill_colour).
SPILL_COLOUR_MIN_EXCESS = 0.2
SPILL_COLOUR_MIN_RATIO = 0.3
SPILL_COLOUR = (SPILL_COLOUR_MIN_EXCESS, SPILL_COLOUR_MIN_RATIO)  # (min excess, min ratio): Blob.spill_colour's
MIN_EXPOSURE_RATIO_PIXELS = 64  # unclipped mid-tone pixels needed to trust a frame's exposure ratio
TRACK_MIN_OVERLAP = 0.5  # share of the smaller blob two frames' blobs must overlap to be one source
TRACK_RING_PX = 2  # width of the fixed ring whose light follows a tracked source over time


@dataclass(frozen=True)
class Blob:
    """One connected clipped region of one frame."""

    area_px: int
    area_sr: float
    halo: tuple[float | None, ...]  # mean linear luminance of rings 1..HALO_RINGS px outside (None: no pixels)
    ring_pixels: tuple[int, ...] = ()  # unclipped pixels in each ring
    # of its pixels, the share with ALL channels clipped (white-hot, not a coloured surface)
    white_fraction: float = 1.0
    halo_rgb: tuple[tuple[float, float, float] | None, ...] = ()  # mean linear RGB of the same rings

    def edge_stops(self) -> float:
        """log2 of the nearest measured halo ring's luminance (0 = white; no ring: 0)."""
        near = next((v for v in self.halo if v is not None), 1.0)
        return math.log2(max(near, HALO_FLOOR))

    def spill_stops(self) -> float:
        """log2 of the light the halo holds above its background, per blob pixel (white = 1):
        a blurred source spills a share of its energy past its edge, in proportion to its
        radiance. Background: the mean of the outer BACKGROUND_RINGS rings."""
        split = halo_and_background(self.halo, self.ring_pixels)
        if split is None:
            return math.log2(HALO_FLOOR)
        inner, background = split
        excess = sum(max(v - background, 0.0) * n for v, n in inner)
        return math.log2(max(excess / self.area_px, HALO_FLOOR))

    def spill_colour(self, min_excess: float = SPILL_COLOUR_MIN_EXCESS,
                     min_ratio: float = SPILL_COLOUR_MIN_RATIO) -> tuple[float, float, float] | None:
        """The chromaticity (luminance 1) of the halo's light above its background (rings as
        `spill_stops`), or None where that excess is not clear of the background."""
        split = halo_and_background([None if c is None else np.asarray(c) for c in self.halo_rgb], self.ring_pixels)
        if split is None:
            return None
        inner, background = split
        excess = sum((c - background) * n for c, n in inner) / sum(n for _, n in inner)
        weights = np.asarray(LUMINANCE_WEIGHTS)
        y_excess, y_background = float(excess @ weights), float(background @ weights)
        if y_excess <= min_excess * max(y_background, HALO_FLOOR):
            return None
        rgb = np.maximum(excess, min_ratio * excess.max())
        rgb = rgb / float(rgb @ weights)
        return (float(rgb[0]), float(rgb[1]), float(rgb[2]))

    def features(self) -> tuple[float, ...]:
        """(1, log2 area / REF_AREA_SR, edge_stops, white_fraction, spill_stops): the rule's inputs."""
        return (1.0, math.log2(max(self.area_sr, 1e-12) / REF_AREA_SR), self.edge_stops(), self.white_fraction,
                self.spill_stops())


def halo_and_background(values, counts):
    """The measured halo rings [(value, pixels)] inside the background, and the background (the
    pixel-weighted mean of the outer BACKGROUND_RINGS measured rings); None with too few rings.
    Values are luminances or RGB arrays."""
    rings = [(v, n) for v, n in zip(values, counts) if v is not None and n > 0]
    if len(rings) <= BACKGROUND_RINGS:
        return None
    outer = rings[-BACKGROUND_RINGS:]
    return rings[:-BACKGROUND_RINGS], sum(v * n for v, n in outer) / sum(n for _, n in outer)


def white_hot_mask(linear: np.ndarray) -> np.ndarray:
    """[H, W, 3] linear radiance (of an LDR frame) -> [H, W] bool: every channel clipped."""
    return linear.min(axis=-1) >= inverse_tonemap(torch.tensor(CLIP_LDR)).item()


def clipped_mask(ldr: torch.Tensor) -> torch.Tensor:
    """[..., H, W, 3] LDR -> [..., H, W] bool: any channel at or above CLIP_LDR."""
    return ldr.amax(dim=-1) >= CLIP_LDR


def pixel_solid_angle(intrinsics) -> float:
    """Steradians of one pixel at the image centre (pinhole: 1 / (fx fy))."""
    return 1.0 / (float(intrinsics.fx) * float(intrinsics.fy))


def find_blobs(linear: np.ndarray, clipped: np.ndarray, pixel_sr: float) -> tuple[np.ndarray, list[Blob]]:
    """Label the clipped blobs of one frame (linear [H, W, 3] of the LDR frame, clipped [H, W]);
    labels [H, W] (0 = not clipped, k = blobs[k - 1]) and each blob's area, halo rings and
    white fraction."""
    from scipy import ndimage  # noqa: PLC0415 — scipy is heavy: imported when used

    labels, n = ndimage.label(clipped, structure=np.ones((3, 3), dtype=bool))
    if n == 0:
        return labels, []
    y = linear.astype(np.float64) @ np.asarray(LUMINANCE_WEIGHTS)
    H, W = clipped.shape
    all_clipped = white_hot_mask(linear)
    blobs = []
    pad = HALO_RINGS + 1
    for k, sl in enumerate(ndimage.find_objects(labels), start=1):
        r0, r1 = max(sl[0].start - pad, 0), min(sl[0].stop + pad, H)
        c0, c1 = max(sl[1].start - pad, 0), min(sl[1].stop + pad, W)
        own = labels[r0:r1, c0:c1] == k
        dist = ndimage.distance_transform_edt(~own)
        usable = ~clipped[r0:r1, c0:c1]  # other blobs are no halo
        yy = y[r0:r1, c0:c1]
        rgb = linear[r0:r1, c0:c1].astype(np.float64)
        halo, halo_rgb, counts = [], [], []
        for ring in range(1, HALO_RINGS + 1):
            sel = usable & (dist > ring - 0.5) & (dist <= ring + 0.5)
            halo.append(float(yy[sel].mean()) if sel.any() else None)
            halo_rgb.append(tuple(float(v) for v in rgb[sel].mean(0)) if sel.any() else None)
            counts.append(int(sel.sum()))
        area = int(own.sum())
        white = float(all_clipped[r0:r1, c0:c1][own].mean())
        blobs.append(Blob(area, area * pixel_sr, tuple(halo), ring_pixels=tuple(counts), white_fraction=white,
                          halo_rgb=tuple(halo_rgb)))
    return labels, blobs


def blob_boost(blob: Blob, coefficients=RULE_COEFFICIENTS) -> float:
    """The rule: radiance factor (>= 1) of a clipped blob's pixels over their linearised value."""
    stops = sum(c * f for c, f in zip(coefficients, blob.features()))
    return 2.0 ** min(max(stops, 0.0), MAX_BOOST_STOPS)


def estimate_clipped(
    linear: np.ndarray,
    clipped: np.ndarray,
    pixel_sr: float,
    coefficients=RULE_COEFFICIENTS,
    found: tuple[np.ndarray, list[Blob]] | None = None,
    stops: list[float] | None = None,
    spill: tuple[float, float] = SPILL_COLOUR,
) -> np.ndarray:
    """One frame's linear radiance [H, W, 3] with each clipped blob estimated: its pixels times
    the blob's boost, and its white-hot pixels (every channel clipped) in the spill's colour
    where the halo gives one (`Blob.spill_colour`), never below their linearised value.
    `found`: this frame's `find_blobs` result when the caller has it; `stops`: each blob's
    log2 boost when the caller decided it (`stops_over_time`), else the rule's; `spill`: the
    spill colour's (min excess, min ratio)."""
    labels, blobs = found if found is not None else find_blobs(linear, clipped, pixel_sr)
    out = linear.astype(np.float64, copy=True)
    if not blobs:
        return out
    white_hot = white_hot_mask(linear)
    for k, blob in enumerate(blobs, start=1):
        own = labels == k
        boost = 2.0 ** stops[k - 1] if stops is not None else blob_boost(blob, coefficients)
        out[own] *= boost
        colour = blob.spill_colour(*spill)
        if colour is not None:
            hot = own & white_hot
            y = out[hot] @ np.asarray(LUMINANCE_WEIGHTS)
            out[hot] = np.maximum(y[:, None] * np.asarray(colour)[None, :], linear[hot])
    return out


def source_tracks(
    labels: list[np.ndarray], counts: list[int], min_overlap: float = TRACK_MIN_OVERLAP
) -> list[list[tuple[int, int]]]:
    """Chains of (frame, blob index) that are one source seen by a static camera: a blob
    continues the track of the previous frame's blob it overlaps most, when that overlap is at
    least `min_overlap` of the smaller of the two and no other blob of its frame took that
    track first. `labels` [T] of [H, W] (0 = none, k = blob k - 1), `counts` [T] blobs each."""
    tracks: list[list[tuple[int, int]]] = []
    previous: list[int] = []  # track of each blob of the previous frame
    for t, (lab, n) in enumerate(zip(labels, counts)):
        share = None
        if t > 0 and n and previous:
            m = len(previous)
            joint = np.bincount((lab.astype(np.int64) * (m + 1) + labels[t - 1]).ravel(),
                                minlength=(n + 1) * (m + 1)).reshape(n + 1, m + 1)
            sizes, prev_sizes = joint.sum(1)[1:], joint.sum(0)[1:]
            share = joint[1:, 1:] / np.maximum(np.minimum(sizes[:, None], prev_sizes[None, :]), 1)
        current: list[int] = []
        for k in range(n):
            track = None
            if share is not None:
                for j in np.argsort(-share[k], kind="stable"):
                    if share[k, j] < min_overlap:
                        break
                    if previous[j] not in current:
                        track = previous[j]
                        break
            if track is None:
                track = len(tracks)
                tracks.append([])
            tracks[track].append((t, k))
            current.append(track)
        previous = current
    return tracks


def stops_over_time(found: list[tuple[np.ndarray, list[Blob]]], linear: torch.Tensor,
                    coefficients=RULE_COEFFICIENTS) -> list[list[float]]:
    """Each frame's blobs' log2 boosts [frame][blob] for a static camera's frames (`found`: each
    frame's `find_blobs`; `linear` [T, H, W, 3] their linear radiance): one source's level over
    the clip, and its changes from the light around it.

    The rule's inputs are the blob's surround, fitted ACROSS sources (a blob on a dark surround
    is more likely a lamp): within one source over time they point the wrong way, as a lamp
    that dims darkens its own halo and the rule then calls it brighter (the simulator's dimming
    lamp was estimated 2.1 stops brighter at the end of its clip than at its start, where its
    luminance had fallen 2.2 stops; `python -m bench.clip_tracks`). So along a track (`source_tracks`) the level is the
    mean of the rule's stops, and
    the frame-to-frame changes are those of the mean luminance of a fixed ring of pixels
    (TRACK_RING_PX wide) around every frame's blob of the track, clipped in no frame: the
    surface next to a source is lit mostly by it (and glare spills in proportion to it), so
    it brightens and dims with it; fixed pixels, because a blob that dims also shrinks and
    its own rings would move. A track without such pixels keeps the rule's stops."""
    from scipy import ndimage  # noqa: PLC0415 — scipy is heavy: imported when used

    stops = [[math.log2(blob_boost(b, coefficients)) for b in blobs] for _, blobs in found]
    H, W = found[0][0].shape
    never_clipped = np.ones((H, W), dtype=bool)
    for lab, _ in found:
        never_clipped &= lab == 0
    boxes = [ndimage.find_objects(lab) for lab, _ in found]  # each blob's bounding slices
    for track in source_tracks([lab for lab, _ in found], [len(blobs) for _, blobs in found]):
        if len(track) < 2:
            continue
        # the track's bounding box grown by the ring: the work stays proportional to the blob
        r0 = max(min(boxes[t][k][0].start for t, k in track) - TRACK_RING_PX, 0)
        r1 = min(max(boxes[t][k][0].stop for t, k in track) + TRACK_RING_PX, H)
        c0 = max(min(boxes[t][k][1].start for t, k in track) - TRACK_RING_PX, 0)
        c1 = min(max(boxes[t][k][1].stop for t, k in track) + TRACK_RING_PX, W)
        union = np.zeros((r1 - r0, c1 - c0), dtype=bool)
        for t, k in track:
            union |= found[t][0][r0:r1, c0:c1] == k + 1
        ring = ndimage.binary_dilation(union, iterations=TRACK_RING_PX) & never_clipped[r0:r1, c0:c1]
        if not ring.any():
            continue
        logs = [math.log2(max(float(luminance(linear[t, r0:r1, c0:c1]).numpy()[ring].mean()), HALO_FLOOR))
                for t, _ in track]
        level = sum(stops[t][k] for t, k in track) / len(track)
        mean_log = sum(logs) / len(logs)
        for (t, k), lg in zip(track, logs):
            stops[t][k] = min(max(level + lg - mean_log, 0.0), MAX_BOOST_STOPS)
    return stops


def exposure_ratios(linear: torch.Tensor, clipped: torch.Tensor) -> torch.Tensor | None:
    """Each frame's exposure relative to frame 0 [T], from pixels unclipped and mid-tone
    (linear 0.02..0.8) in both: the median of their luminance ratio. None when some frame
    shares too few such pixels with frame 0 (then exposures are not used)."""
    y = luminance(linear)
    good = (~clipped) & (y > 0.02) & (y < 0.8)
    ratios = [torch.ones((), dtype=y.dtype)]
    for t in range(1, y.shape[0]):
        both = good[0] & good[t]
        if int(both.sum()) < MIN_EXPOSURE_RATIO_PIXELS:
            return None
        ratios.append(torch.median(y[t][both] / y[0][both]))
    return torch.stack(ratios)


def recover_from_exposures(linear: torch.Tensor, clipped: torch.Tensor,
                           known_ratios: torch.Tensor | None = None) -> torch.Tensor:
    """[T, H, W, 3]: clipped pixels replaced by the same pixel of a darker frame, rescaled to
    this frame's exposure, where that is unclipped and above white (the brightest such
    reading wins); other pixels unchanged. Needs a static camera (the caller checks). Works
    on the clipped pixels only (a video's frames are not copied). `known_ratios` [T]: each
    frame's exposure relative to frame 0 when the capture states it (else estimated)."""
    ratios = exposure_ratios(linear, clipped) if known_ratios is None else known_ratios.to(linear.dtype)
    if ratios is None or linear.shape[0] < 2 or bool((ratios - 1.0).abs().max() < 0.05):
        return linear
    out = linear.clone()
    for t in range(linear.shape[0]):
        idx = clipped[t].reshape(-1).nonzero()[:, 0]
        if idx.numel() == 0:
            continue
        value = linear[t].reshape(-1, 3)[idx].clone()
        best = torch.zeros(idx.numel(), dtype=linear.dtype)
        for s in range(linear.shape[0]):
            if s == t:
                continue
            scaled = linear[s].reshape(-1, 3)[idx] * (ratios[t] / ratios[s])  # frame s's reading at frame t's exposure
            y = luminance(scaled)
            use = ~clipped[s].reshape(-1)[idx] & (y > 1.0) & (y > best)
            value[use] = scaled[use]
            best = torch.where(use, y, best)
        out[t].view(-1, 3)[idx] = value
    return out


def _compact(found: tuple[np.ndarray, list[Blob]]) -> tuple[np.ndarray, list[Blob]]:
    """A frame's blob labels in 16 bits where they fit: every frame's are kept for the whole clip."""
    labels, blobs = found
    return (labels.astype(np.uint16) if len(blobs) < 2**16 else labels), blobs


def linearise_highlights(frames: torch.Tensor, intrinsics, compare_frames: bool,
                         coefficients=RULE_COEFFICIENTS, static_camera: bool = False,
                         known_ratios: torch.Tensor | None = None,
                         spill: tuple[float, float] = SPILL_COLOUR) -> torch.Tensor:
    """LDR frames [T, H, W, 3] -> linear radiance in each frame's own units (ev 0: white = 1)
    with clipped sources estimated (`known_ratios` [T]: each frame's stated exposure relative
    to frame 0, else estimated from the frames): exposure changes first, then the blob rule for what stays clipped.
    `compare_frames`: the
    frames see the same radiance up to exposure (a static camera and static lighting), so
    one frame's unclipped reading may stand in for another's clipped one. `static_camera`
    (implied by `compare_frames`): a source stays at its pixels, so its blobs are followed
    over the frames and estimated together (`stops_over_time`). `coefficients` and `spill`: the
    blob rule's and the spill colour's settings (`estimate_clipped`)."""
    ldr = frames.clamp(0, 1)
    lin = inverse_tonemap(ldr)
    clipped = clipped_mask(ldr)
    if bool(clipped.any()):
        lin = _estimate_highlights(lin, clipped, intrinsics, compare_frames, coefficients, static_camera, known_ratios,
                                   spill)
    return lin


def _estimate_highlights(lin, clipped, intrinsics, compare_frames, coefficients, static_camera, known_ratios, spill):
    recovered = torch.zeros_like(clipped)
    if compare_frames and lin.shape[0] > 1:
        lin2 = recover_from_exposures(lin, clipped, known_ratios)
        recovered = clipped & (lin2 != lin).any(-1)
        lin = lin2
    pixel_sr = pixel_solid_angle(intrinsics)
    still = (clipped & ~recovered).numpy()
    found = [_compact(find_blobs(lin[t].numpy(), still[t], pixel_sr)) for t in range(lin.shape[0])]
    stops = (stops_over_time(found, lin, coefficients)
             if (static_camera or compare_frames) and lin.shape[0] > 1 else None)
    for t in range(lin.shape[0]):  # in place: lin is this function's own tensor
        if not still[t].any():
            continue
        lin[t] = torch.from_numpy(estimate_clipped(lin[t].numpy(), still[t], pixel_sr, coefficients, found=found[t],
                                                   stops=None if stops is None else stops[t], spill=spill)
                                  ).to(lin.dtype)
    return lin
