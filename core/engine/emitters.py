"""Find the small bright sources of a capture: the field's emitters (core.fields.emitters).

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

import cv2
import numpy as np
import torch

from core.capture.base import Capture
from core.exposure import luminance
from core.fields import SceneBounds

MERGE_DISTANCE = 0.25  # metres: blobs of different frames closer than this are one source
MIN_PIXELS = 1
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


def _frame_geometry(capture: Capture, i: int):
    """World points [H, W, 3], distances [H, W] and pixel footprints area_p [H, W] (m^2) of frame i."""
    cam = capture.camera(i)
    k = cam.intrinsics
    z = capture.depth[i].double()
    pts = cam.unproject(capture.depth[i].double())
    dist = (pts - cam.position[None, None]).norm(dim=-1)
    area = z.pow(3) / (dist * k.fx * k.fy)  # d^2 x pixel solid angle (cos^3 / (fx fy)), cos = z / d
    return pts, dist, area


def _blobs(capture: Capture, i: int, linear: torch.Tensor, contrast: float, max_radius: float) -> list[tuple]:
    """(centre [3], radius, intensity [3], flat pixel indices) of the brightest bright blobs of frame i."""
    lum = luminance(linear.double())
    ok = torch.isfinite(lum) & torch.isfinite(capture.depth[i]) & (capture.depth[i] > 0)
    if not bool(ok.any()):
        return []
    threshold = contrast * float(lum[ok].median().clamp_min(1e-12))
    n, labels = cv2.connectedComponents((ok & (lum > threshold)).numpy().astype(np.uint8), connectivity=8)
    if n <= 1:
        return []
    pts, dist, area = _frame_geometry(capture, i)
    # a blob wider than max_radius is a broad source (window, panel): left to the network whole,
    # not cut into cores. The others are cut to their core: pixels within CORE_FRACTION of the
    # blob's peak, so the wall a lamp lights (bright, but dimmer than the lamp) is not averaged in
    labels_t = torch.from_numpy(labels.astype(np.int64)).reshape(-1)
    blob_area = torch.zeros(n, dtype=area.dtype).index_add(0, labels_t, torch.nan_to_num(area, nan=0.0).reshape(-1))
    peak = torch.zeros(n, dtype=lum.dtype).scatter_reduce(0, labels_t, lum.reshape(-1), reduce="amax")
    small = torch.sqrt(blob_area / math.pi) <= max_radius
    core = ((labels_t > 0) & small[labels_t] & (lum.reshape(-1) >= CORE_FRACTION * peak[labels_t])).reshape(lum.shape)
    n, labels = cv2.connectedComponents(core.numpy().astype(np.uint8), connectivity=8)
    labels_t = torch.from_numpy(labels.astype(np.int64)).reshape(-1)
    core_peak = torch.zeros(n, dtype=lum.dtype).scatter_reduce(0, labels_t, lum.reshape(-1), reduce="amax")
    brightest = [int(k) for k in torch.argsort(core_peak[1:], descending=True)[:MAX_BLOBS_PER_FRAME] + 1]
    origin = capture.camera(i).position.to(pts.dtype)
    labels_t = labels_t.reshape(lum.shape)
    out = []
    for lab in brightest:
        sel = labels_t == lab
        if int(sel.sum()) < MIN_PIXELS:
            continue
        a = area[sel]
        radius = math.sqrt(float(a.sum()) / math.pi)
        if radius > max_radius:
            continue
        col = linear.double()[sel]
        w = luminance(col) * a
        # along the blob's luminance-weighted ray, at its nearest point: a downsampled depth map
        # blends a small lamp's depth with the wall behind it, and the lamp is the near surface
        rays = (pts[sel] - origin) / dist[sel][:, None].clamp_min(1e-9)
        ray = (rays * w[:, None]).sum(0)
        centre = origin + ray / ray.norm().clamp_min(1e-12) * float(dist[sel].min())
        out.append((centre, radius, (col * a[:, None]).sum(0), torch.nonzero(sel.reshape(-1)).reshape(-1)))
    return out


def _footprint_intensity(capture: Capture, i: int, linear: torch.Tensor, centre: torch.Tensor, radius: float,
                         claimed: torch.Tensor):
    """Intensity [3] the frame shows within the source's projected disk (+ 1 pixel) outside the
    pixels another source `claimed` (then claimed too; 0 when its centre's pixel is claimed), or
    None when the source is out of view or occluded in frame i."""
    cam = capture.camera(i)
    k = cam.intrinsics
    u, v, z = cam.project(centre[None].double())
    u, v, z = float(u[0]), float(v[0]), float(z[0])
    if not (z > 0 and 0 <= u < k.width and 0 <= v < k.height):
        return None
    if bool(claimed[int(v), int(u)]):  # another source has these pixels: the same lamp, placed apart by depth noise
        return torch.zeros(3, dtype=torch.float64)
    pts, dist, area = _frame_geometry(capture, i)
    seen = float(capture.depth[i][int(v), int(u)])
    if not math.isfinite(seen) or seen < z - max(OCCLUSION_MARGIN, 3 * radius):
        return None
    r_px = radius * k.fx / z + 1.0
    vv, uu = torch.meshgrid(torch.arange(k.height, dtype=torch.float64) + 0.5, torch.arange(k.width, dtype=torch.float64) + 0.5,
                            indexing="ij")
    sel = ((uu - u).pow(2) + (vv - v).pow(2) <= r_px ** 2) & torch.isfinite(area) & ~claimed
    if not bool(sel.any()):
        return None
    claimed |= sel
    return (linear.double()[sel] * area[sel][:, None]).sum(0)


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
            if all(d[0] != det[0] for d in cl) and float((cl[0][1] - det[1]).norm()) < max(MERGE_DISTANCE, 2 * (cl[0][2] + det[2])):
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
        intensity.append(_at_knots(series, capture.times.double(), bounds, knots))
    return EmitterSources(torch.stack(centres).float(), torch.tensor(radii, dtype=torch.float32),
                          torch.stack(intensity).float())


def _at_knots(series: torch.Tensor, times: torch.Tensor, bounds: SceneBounds, knots: int) -> torch.Tensor:
    """Per-frame intensities [T, 3] -> [knots, 3]: the median for one knot, else the frame
    nearest each knot's time."""
    if knots == 1:
        return series.median(0).values[None]
    kt = bounds.t0 + torch.linspace(0, 1, knots, dtype=torch.float64) * (bounds.t1 - bounds.t0)
    nearest = (kt[:, None] - times[None]).abs().argmin(1)
    return series[nearest]
