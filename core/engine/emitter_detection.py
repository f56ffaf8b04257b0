"""Find the small bright sources of a capture: the field's emitters (core.fields.components.emitters).

Per frame, pixels brighter than `emitter_contrast` x the frame's median luminance (the prior's
linear radiance, clip rule applied) with valid depth form connected blobs, each cut to its core
(pixels at least CORE_FRACTION of its peak: not the wall a lamp lights); each core gives a
3D centre (along its luminance-weighted ray, at its nearest point), a radius (of the disk of its projected
area) and an intensity sum(L_p x area_p), area_p the pixel's footprint at its distance, so a
lamp smaller than a pixel still has the right energy. Blobs wider than `emitter_max_radius`
(windows, ceiling panels) are left to the network, which holds broad sources well. Blobs of
different frames within MERGE_DISTANCE of each other are one source; the `emitters` brightest are kept.

Intensity over time, per frame: the blob's where the frame has one; else, where the source is in
view and not occluded, what the frame's pixels show in its footprint outside pixels another
source took (a lamp switched off in view becomes dark; a lamp split in two by depth noise is
counted once); else (out of view) the nearest frame in time that has a value. A field
without a time input gets the median over the frames.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from core.capture.base import Capture
from core.conventions import pixel_to_camera_ray, valid_depth_mask
from core.exposure import luminance
from core.fields import SceneBounds

MERGE_DISTANCE = 0.25  # metres: blobs of different frames closer than this are one source
MAX_BLOBS_PER_FRAME = 16  # the brightest blobs of a frame (bounds the work on a noisy or sparkly frame)
CORE_FRACTION = 0.5  # a blob's pixels at least this fraction of its peak luminance make the source
OCCLUSION_MARGIN = 0.1  # metres: the depth in front of a source that still counts as the source


@dataclass(frozen=True)
class EmitterSources:
    centres: torch.Tensor  # [K, 3] metres
    radii: torch.Tensor  # [K] metres
    intensity: torch.Tensor  # [K, knots, 3] linear radiance x m^2

    @property
    def count(self) -> int:
        return int(self.centres.shape[0])

    def describe(self) -> list[dict]:
        return [{"centre": [round(float(v), 3) for v in c], "radius": round(float(r), 4),
                 "intensity_max": round(float(luminance(i).max()), 4)}
                for c, r, i in zip(self.centres, self.radii, self.intensity)]


EIGHT_NEIGHBOURS = np.ones((3, 3), dtype=bool)  # blob connectivity, as core.capture.highlights.find_blobs


def _footprints(k, depth: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
    """area_p (m^2) of pixels (rows, cols) with planar depths `depth`: d^2 x the pixel's solid
    angle cos^3 / (fx fy), d = z / cos, i.e. z^2 cos / (fx fy) (NaN where depth is invalid)."""
    ray = pixel_to_camera_ray(cols.double() + 0.5, rows.double() + 0.5, k.fx, k.fy, k.cx, k.cy)
    z = torch.where(valid_depth_mask(depth), depth.double(), torch.full_like(depth, float("nan"), dtype=torch.float64))
    return z.pow(2) / (ray.norm(dim=-1) * k.fx * k.fy)


def _blobs(capture: Capture, i: int, linear: torch.Tensor, contrast: float, max_radius: float) -> list[tuple]:
    """(centre [3], radius, intensity [3], flat pixel indices) of the brightest bright blobs of frame i."""
    lum = luminance(linear.double())
    depth = capture.depth[i]
    ok = torch.isfinite(lum) & valid_depth_mask(depth)
    if not bool(ok.any()):
        return []
    threshold = contrast * float(lum[ok].median().clamp_min(1e-12))
    lum_np = lum.numpy()
    labels, n = ndimage.label((ok & (lum > threshold)).numpy(), structure=EIGHT_NEIGHBOURS)
    if n == 0:
        return []
    H, W = depth.shape
    rows, cols = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    area = _footprints(capture.intrinsics, depth, rows, cols)
    # a blob wider than max_radius is a broad source (window, panel): left to the network whole,
    # not cut into cores. The others are cut to their core: pixels within CORE_FRACTION of the
    # blob's peak, so the wall a lamp lights (bright, but dimmer than the lamp) is not averaged in
    index = np.arange(1, n + 1)
    blob_area = np.asarray(ndimage.sum(np.nan_to_num(area.numpy()), labels, index))
    peak = np.concatenate([[np.inf], ndimage.maximum(lum_np, labels, index)])
    small = np.concatenate([[False], np.sqrt(blob_area / math.pi) <= max_radius])
    labels, n = ndimage.label(small[labels] & (lum_np >= CORE_FRACTION * peak[labels]), structure=EIGHT_NEIGHBOURS)
    if n == 0:
        return []
    core_peak = np.asarray(ndimage.maximum(lum_np, labels, np.arange(1, n + 1)))
    brightest = set((np.argsort(-core_peak, kind="stable")[:MAX_BLOBS_PER_FRAME] + 1).tolist())
    cam = capture.camera(i)
    pts = cam.unproject(depth.double())
    out = []
    for lab, window in enumerate(ndimage.find_objects(labels), start=1):
        if lab not in brightest:
            continue
        r, c = np.nonzero(labels[window] == lab)
        r = torch.from_numpy(r + window[0].start)
        c = torch.from_numpy(c + window[1].start)
        a = area[r, c]
        radius = math.sqrt(float(a.sum()) / math.pi)
        if radius > max_radius:
            continue
        col = linear.double()[r, c]
        w = luminance(col) * a
        # along the blob's luminance-weighted ray, at its nearest point: a downsampled depth map
        # blends a small lamp's depth with the wall behind it, and the lamp is the near surface
        p = pts[r, c]
        dist = (p - cam.position).norm(dim=-1)
        ray = ((p - cam.position) / dist[:, None].clamp_min(1e-9) * w[:, None]).sum(0)
        centre = cam.position + ray / ray.norm().clamp_min(1e-12) * float(dist.min())
        out.append((centre, radius, (col * a[:, None]).sum(0), r * W + c))
    return out


def _footprint_intensity(capture: Capture, i: int, linear: torch.Tensor, centre: torch.Tensor, radius: float,
                         claimed: torch.Tensor):
    """Intensity [3] the frame shows within the source's projected disk (+ 1 pixel) outside the
    pixels another source `claimed` (then claimed too; 0 when its centre's pixel is claimed), or
    None when the source is out of view or occluded in frame i."""
    cam = capture.camera(i)
    k = cam.intrinsics
    u, v, z = (float(a[0]) for a in cam.project(centre[None].double()))
    if not (z > 0 and 0 <= u < k.width and 0 <= v < k.height):
        return None
    if bool(claimed[int(v), int(u)]):  # another source has these pixels: the same lamp, placed apart by depth noise
        return torch.zeros(3, dtype=torch.float64)
    depth = capture.depth[i]
    seen = float(depth[int(v), int(u)])
    if not math.isfinite(seen) or seen < z - max(OCCLUSION_MARGIN, 3 * radius):
        return None
    r_px = radius * k.fx / z + 1.0  # only the disk's bounding window is looked at
    rows = torch.arange(max(int(v - r_px), 0), min(int(v + r_px) + 1, k.height))
    cols = torch.arange(max(int(u - r_px), 0), min(int(u + r_px) + 1, k.width))
    rr, cc = torch.meshgrid(rows, cols, indexing="ij")
    area = _footprints(k, depth[rr, cc], rr, cc)
    sel = ((cc + 0.5 - u).pow(2) + (rr + 0.5 - v).pow(2) <= r_px ** 2) & torch.isfinite(area) & ~claimed[rr, cc]
    if not bool(sel.any()):
        return None
    claimed[rr[sel], cc[sel]] = True
    return (linear.double()[rr[sel], cc[sel]] * area[sel][:, None]).sum(0)


def find_emitters(capture: Capture, linear_frame, *, count: int, contrast: float, max_radius: float,
                  bounds: SceneBounds, knots: int) -> EmitterSources | None:
    """Up to `count` sources (None when there are none). `linear_frame(i)` -> [H, W, 3] linear
    radiance of frame i; `knots` evenly spaced over the bounds' time range (1: static)."""
    def frame(i: int) -> torch.Tensor:  # on demand: a long clip's frames are not copied at once
        return torch.nan_to_num(linear_frame(i).detach().cpu().float(), nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)

    detections = []  # (frame, centre, radius, intensity, flat pixel indices)
    for i in range(capture.num_frames):
        detections += [(i, *b) for b in _blobs(capture, i, frame(i), contrast, max_radius)]
    if not detections:
        return None
    # greedy clustering, brightest first; two blobs of one frame are two sources however close
    detections.sort(key=lambda d: -float(luminance(d[3])))
    clusters: list[list] = []
    for det in detections:
        for cl in clusters:
            if all(d[0] != det[0] for d in cl) and float((cl[0][1] - det[1]).norm()) < max(
                MERGE_DISTANCE, 2 * (cl[0][2] + det[2])
            ):
                cl.append(det)
                break
        else:
            clusters.append([det])
    clusters.sort(key=lambda cl: -max(float(luminance(d[3])) for d in cl))
    clusters = clusters[:count]
    T = capture.num_frames
    # a frame's pixels count for one source only: its blobs first, then footprints in turn (two
    # clusters of one lamp, split by pose noise, must not both take its light)
    claimed = [torch.zeros(capture.height, capture.width, dtype=torch.bool) for _ in range(T)]
    for cl in clusters:
        for d in cl:
            claimed[d[0]].view(-1)[d[4]] = True
    centres, radii, intensity = [], [], []
    for cl in clusters:
        w = torch.tensor([float(luminance(d[3])) for d in cl], dtype=torch.float64)
        centre = (torch.stack([d[1] for d in cl]) * w[:, None]).sum(0) / w.sum()
        radius = float(np.median([d[2] for d in cl]))
        per_frame: list[torch.Tensor | None] = [None] * T
        for d in cl:
            per_frame[d[0]] = d[3] if per_frame[d[0]] is None else per_frame[d[0]] + d[3]
        for i in range(T):
            if per_frame[i] is None:
                per_frame[i] = _footprint_intensity(capture, i, frame(i), centre, radius, claimed[i])
        have = [i for i in range(T) if per_frame[i] is not None]
        for i in range(T):  # out of view: the nearest frame in time that has a value
            if per_frame[i] is None:
                j = min(have, key=lambda j: abs(float(capture.times[j] - capture.times[i])))
                per_frame[i] = per_frame[j]
        series = torch.stack(per_frame)  # [T, 3]
        centres.append(centre)
        radii.append(radius)
        intensity.append(_at_knots(series, capture, bounds, knots))
    return EmitterSources(torch.stack(centres).float(), torch.tensor(radii, dtype=torch.float32),
                          torch.stack(intensity).float())


def _at_knots(series: torch.Tensor, capture: Capture, bounds: SceneBounds, knots: int) -> torch.Tensor:
    """Per-frame intensities [T, 3] -> [knots, 3]: the median for one knot, else the frame
    nearest each knot's time."""
    if knots == 1:
        return series.median(0).values[None]
    return series[capture.nearest_frames(bounds.knot_times(knots))]
