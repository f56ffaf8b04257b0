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
   coefficients are fitted by bench/clip_rule.py on the `dev` panoramas only; the fit, its
   measured error in stops and its known limit (very bright point sources are
   underestimated) are in docs/highlights.md. A log-linear extrapolation of the halo into
   the core was tried and got no weight on dev.
3. The colour of a white-hot blob (`spill_colour`): its pixels say only "every channel at
   least white", so the rule's factor would leave a warm lamp white. The halo's excess over
   its background is the source's own light (lens glare and blur spill it past the edge; the
   surface around a lamp is lit by it), so its chromaticity stands for the source's, where
   that excess is clear of the background (SPILL_COLOUR_MIN_EXCESS) and only as saturated as
   SPILL_COLOUR_MIN_RATIO allows (a coloured wall tints the spill too). No channel of a
   recoloured pixel drops below its linearised value: it is still at least white.

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
# Fitted by `python -m bench.clip_rule --fit` on the dev panoramas (see docs/highlights.md).
RULE_COEFFICIENTS = (-0.452, -0.042, -0.808, 1.247, -0.075)
# The spill's colour is used when its excess luminance over the background is at least this
# share of the background (else it is noise on the background's own colour), with each
# channel at least SPILL_COLOUR_MIN_RATIO of the largest (a tinted wall tints the spill too).
SPILL_COLOUR_MIN_EXCESS = 0.05
SPILL_COLOUR_MIN_RATIO = 0.7
MIN_EXPOSURE_RATIO_PIXELS = 64  # unclipped mid-tone pixels needed to trust a frame's exposure ratio


@dataclass(frozen=True)
class Blob:
    """One connected clipped region of one frame."""

    area_px: int
    area_sr: float
    halo: tuple[float | None, ...]  # mean linear luminance of rings 1..HALO_RINGS px outside (None: no pixels)
    ring_pixels: tuple[int, ...] = ()  # unclipped pixels in each ring
    white_fraction: float = 1.0  # of its pixels, the share with ALL channels clipped (white-hot, not a coloured surface)
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
    from scipy import ndimage

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


def estimate_clipped(linear: np.ndarray, clipped: np.ndarray, pixel_sr: float, coefficients=RULE_COEFFICIENTS) -> np.ndarray:
    """One frame's linear radiance [H, W, 3] with each clipped blob estimated: its pixels times
    the blob's boost, and its white-hot pixels (every channel clipped) in the spill's colour
    where the halo gives one (`Blob.spill_colour`), never below their linearised value."""
    labels, blobs = find_blobs(linear, clipped, pixel_sr)
    out = linear.astype(np.float64, copy=True)
    if not blobs:
        return out
    white_hot = white_hot_mask(linear)
    for k, blob in enumerate(blobs, start=1):
        own = labels == k
        boost = blob_boost(blob, coefficients)
        out[own] *= boost
        colour = blob.spill_colour()
        if colour is not None:
            hot = own & white_hot
            y = out[hot] @ np.asarray(LUMINANCE_WEIGHTS)
            out[hot] = np.maximum(y[:, None] * np.asarray(colour)[None, :], linear[hot])
    return out


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


def recover_from_exposures(linear: torch.Tensor, clipped: torch.Tensor) -> torch.Tensor:
    """[T, H, W, 3]: clipped pixels replaced by the same pixel of a darker frame, rescaled to
    this frame's exposure, where that is unclipped and above white (the brightest such
    reading wins); other pixels unchanged. Needs a static camera (the caller checks). Works
    on the clipped pixels only (a video's frames are not copied)."""
    ratios = exposure_ratios(linear, clipped)
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


def linearise_highlights(frames: torch.Tensor, intrinsics, compare_frames: bool,
                         coefficients=RULE_COEFFICIENTS) -> torch.Tensor:
    """LDR frames [T, H, W, 3] -> linear radiance (ev 0) with clipped sources estimated:
    exposure changes first, then the blob rule for what stays clipped. `compare_frames`: the
    frames see the same radiance up to exposure (a static camera and static lighting), so
    one frame's unclipped reading may stand in for another's clipped one."""
    ldr = frames.clamp(0, 1)
    lin = inverse_tonemap(ldr)
    clipped = clipped_mask(ldr)
    if not bool(clipped.any()):
        return lin
    recovered = torch.zeros_like(clipped)
    if compare_frames and frames.shape[0] > 1:
        lin2 = recover_from_exposures(lin, clipped)
        recovered = clipped & (lin2 != lin).any(-1)
        lin = lin2
    pixel_sr = pixel_solid_angle(intrinsics)
    for t in range(frames.shape[0]):  # in place: lin is this function's own tensor
        still = (clipped[t] & ~recovered[t]).numpy()
        if not still.any():
            continue
        lin[t] = torch.from_numpy(estimate_clipped(lin[t].numpy(), still, pixel_sr, coefficients)).to(lin.dtype)
    return lin
