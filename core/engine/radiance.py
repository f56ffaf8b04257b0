"""Radiance supervision: fit the field to a prior's HDR env maps directly (docs/engine.md).

For priors that declare `PriorCapabilities.envmaps` (reprojection, known, the simulator's
oracle) the ball-render loop only re-encodes what the prior already knows as LDR ball pixels
at one exposure per step, a few hundred reflected directions per ball, and loses most of it
(measured: bench/accuracy_probe.py). Here each step asks the prior for env maps at a few probes
of one frame and fits the field's radiance at many random directions per probe in log
radiance, so every decade of dynamic range and every direction, observed or push-pull
filled, is supervised alike.

Probes per step: `envmap_surface_probes` in front of the scene depth (as the ball loop's),
`envmap_room_probes` anywhere along camera rays (the free space the camera saw, so the field
is supervised through the room, not only near surfaces), free-space probes off the camera rays
(core.engine.free_space, only for priors that answer anywhere) and the camera centre (where
users and the bench query). All but the free-space probes are in free space as seen from the
camera, so a simulator oracle can answer them.
"""
from __future__ import annotations

import math

import torch

from core.capture.base import Capture
from core.conventions import (
    equirect_pixel_centres,
    equirect_pixel_to_theta_phi,
    pixel_to_camera_ray,
    theta_phi_to_direction,
)
from core.engine.config import DistillConfig
from core.engine.free_space import FreeSpaceSampler
from core.engine.probes import sample_probes
from core.envmap import equirect_stencil, pad_poles
from core.exposure import luminance

ROOM_DEPTH_FRACTION = (0.05, 0.95)


def supervision_probes(capture: Capture, frame_index: int, cfg: DistillConfig, gen: torch.Generator,
                       free_space: FreeSpaceSampler | None = None) -> torch.Tensor:
    """World probe centres [N, 3] (float32) for one radiance step on frame `frame_index`:
    surface, room, free-space (with a sampler) and last the camera centre. Without a sampler
    (a prior that answers only where the camera saw) the free-space probes' places go to
    surface probes, so such a prior is not asked fewer questions per step."""
    cam = capture.camera(frame_index)
    k = cam.intrinsics
    centers: list[torch.Tensor] = []
    surface = cfg.envmap_surface_probes + (cfg.envmap_free_probes if free_space is None else 0)
    for n, depth_fraction in ((surface, cfg.probe_depth_fraction), (cfg.envmap_room_probes, ROOM_DEPTH_FRACTION)):
        if n == 0:
            continue
        pixels, depths = sample_probes(
            capture, frame_index, cfg.model_copy(update={"n_probes": n, "probe_depth_fraction": depth_fraction}), gen
        )
        # on the ray through each pixel at its planar depth (core.chrome_ball.place_probe, all at once)
        rays = pixel_to_camera_ray(pixels[:, 0], pixels[:, 1], k.fx, k.fy, k.cx, k.cy) * depths[:, None]
        centers.append((rays @ cam.c2w[:3, :3].T.double() + cam.c2w[:3, 3].double()).float())
    if free_space is not None and cfg.envmap_free_probes:
        centers.append(free_space.sample(cfg.envmap_free_probes, gen))
    if cfg.envmap_camera_probe:
        centers.append(capture.poses[frame_index, :3, 3].float()[None])
    return torch.cat(centers)


def random_directions(n: int, gen: torch.Generator) -> torch.Tensor:
    """n directions uniform on the sphere [n, 3]."""
    d = torch.randn(n, 3, generator=gen)
    return d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def bright_directions(maps: torch.Tensor, k: int, gen: torch.Generator) -> torch.Tensor:
    """k directions per map [P, k, 3] drawn with probability ~ luminance x solid angle of the
    maps [P, h, 2h, 3] (uniform within the drawn pixel): the few directions of a small bright
    source, which uniform sampling rarely hits, are fitted every step."""
    p, h, w = maps.shape[:3]
    lum = luminance(maps.to(torch.float64)).clamp_min(0.0)
    theta_c, _ = equirect_pixel_centres(h, dtype=torch.float64)
    weight = (lum * torch.sin(theta_c)).reshape(p, -1) + 1e-12
    index = torch.multinomial(weight, k, replacement=True, generator=gen)
    jitter = torch.rand(p, k, 2, generator=gen, dtype=torch.float64)
    theta, phi = equirect_pixel_to_theta_phi(
        (index // w).double() + jitter[..., 0], (index % w).double() + jitter[..., 1], h
    )
    return theta_phi_to_direction(theta, phi).float()


def radiance_loss(pred: torch.Tensor, target: torch.Tensor, floor: float | torch.Tensor, linear_weight: float,
                  chroma_weight: float = 0.0) -> torch.Tensor:
    """Mean squared log-radiance error with a floor (a scalar or per row [B, 1]: near-black
    pixels do not dominate),
    plus `linear_weight` x the mean absolute linear error relative to the target's mean (so
    a small bright source keeps its energy, which the log term alone underweights)."""
    log_err = torch.log(pred + floor) - torch.log(target + floor)
    loss = log_err.pow(2).mean()
    if chroma_weight > 0:
        # the log error's colour part (each channel's deviation from the row's mean error)
        loss = loss + chroma_weight * (log_err - log_err.mean(-1, keepdim=True)).pow(2).mean()
    if linear_weight > 0:
        floor_min = float(torch.as_tensor(floor).min())
        loss = loss + linear_weight * (pred - target).abs().mean() / target.mean().clamp_min(floor_min)
    return loss


def frame_floors(frames_lin: torch.Tensor, fraction: float) -> list[float]:
    """Per-frame log floors: `fraction` x each frame's mean linear radiance (never 0)."""
    means = frames_lin.reshape(frames_lin.shape[0], -1).to(torch.float64).mean(1)
    return [max(fraction * float(m), 1e-8) if math.isfinite(float(m)) else 1e-8 for m in means]


def targets_at(maps: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Bilinear lookups (core.envmap.sample_envmap's) of maps [P, h, 2h, 3] at directions
    [P, K, 3] -> [P, K, 3] in one gather, non-finite -> 0."""
    p, h = maps.shape[0], maps.shape[1]
    padded = pad_poles(maps)  # [P, (h + 2) * 2h, 3]
    index, weight = equirect_stencil(directions.reshape(-1, 3), h)
    index = index.reshape(p, -1, 4) + (torch.arange(p) * padded.shape[1])[:, None, None]
    out = (weight.reshape(p, -1, 4, 1).to(maps.dtype) * padded.reshape(-1, 3)[index]).sum(-2)
    return torch.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
