"""The ControlNet's image, by what the ControlNet was trained on (card `controlnet_conditioning`)
and the inference profile. All encodings return [3, H, W] in [0, 1] on the model canvas.

Depth (the paper's and the authors' `thibaud/controlnet-sd21-depth-diffusers`, and
DiffusionLight's `diffusers/controlnet-depth-sdxl-1.0`) -- MiDaS / DPT style, near = bright:

* `robust_inverse_depth` (paper): 1/depth of the frame WITH the balls composited, mapped
  from its robust [1 %, 99 %] range to [0, 1] (conditioning.depth_to_control).
* `authors_disparity` (seed): the authors' `prepare_depth_control_image_withdepth`
  (SDS/multiball_sds.py): the scene's disparity min-max normalised over the frame, every
  ball's pixels filled with (1/z)^(1/2.4), where z = 1/(normalised disparity) is the ball's
  depth in their units (their `get_local_depth`), then quantised to 8 bits (their PIL
  round trip). Stand-in: the authors run DPT-large on the frame for the disparity; no
  weights are fetched here, so the disparity is 1/depth of the capture's depth map (the
  user's, or our depth model's), which is what DPT estimates up to scale and shift.
  Min-max normalisation removes the scale; the shift is the remaining difference.
* `diffusionlight_nearest` (DiffusionLight): the scene's disparity min-max normalised
  (its `estimate_scene_depth`), ball pixels set to 1 (`fill_depth_circular`, "nearest").

Normals (DiffusionLight's SD-2 variant, `thibaud/controlnet-sd21-normalbae-diffusers`):

* `normals`: DiffusionLight's normal map convention (relighting/ball_processor.py
  `get_ideal_normal_ball`: x towards the image's left, y up, z towards the viewer, RGB =
  (n + 1) / 2). Scene normals come from the capture's depth by geometry (cross product of
  the unprojected point's pixel derivatives) instead of DiffusionLight's Sobel-on-DPT
  stand-in; each ball's pixels get the exact normals of its sphere (ray-sphere hit).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from core.conventions import valid_depth_mask
from core.priors.base import ProbeGeometry
from core.priors.diffusion.canvas import Canvas
from core.priors.diffusion.conditioning import depth_to_control

ENCODINGS = ("robust_inverse_depth", "authors_disparity", "diffusionlight_nearest", "normals")


@dataclass
class ControlInputs:
    depth: torch.Tensor  # [h, w] planar depth with the balls composited
    background_depth: torch.Tensor  # [h, w] planar depth of the scene alone
    ball_masks: torch.Tensor  # [N, h, w] per-ball coverage
    probes: ProbeGeometry


def control_image(encoding: str, inputs: ControlInputs, canvas: Canvas, device) -> torch.Tensor:
    if encoding == "robust_inverse_depth":
        return canvas.to_model(depth_to_control(inputs.depth)[None])[0].to(device)
    if encoding == "normals":
        return canvas.to_model(normal_map(inputs)[None], fill=0.0)[0].clamp(0.0, 1.0).to(device)
    disparity = canvas.to_model(_disparity(inputs.background_depth)[None, None])[0, 0]
    lo, hi = disparity.min(), disparity.max()
    out = (disparity - lo) / (hi - lo) if hi > lo else torch.full_like(disparity, 0.5)
    masks = canvas.mask_to_model(inputs.ball_masks.float()) > 0  # [N, H, W]
    if encoding == "diffusionlight_nearest":
        out = torch.where(masks.any(0), torch.ones_like(out), out)
        return out.expand(3, -1, -1).clone().to(device)
    if encoding == "authors_disparity":
        ball_disp = _normalised_ball_disparity(inputs, lo, hi)  # [N]
        for i in range(masks.shape[0]):  # later balls win where they overlap, as in project_multiball
            fill = ball_disp[i].clamp(min=1e-6) ** (1.0 / 2.4)  # (1/z)^(1/2.4) with z = 1/disparity
            out = torch.where(masks[i], fill.to(out.dtype), out)
        out = torch.floor(out.clamp(0.0, 1.0) * 255.0) / 255.0  # (x * 255).astype(uint8), then / 255
        return out.expand(3, -1, -1).clone().to(device)
    raise ValueError(f"unknown control encoding {encoding!r}; choose one of {ENCODINGS}")


def _disparity(depth: torch.Tensor) -> torch.Tensor:
    d = depth.float()
    valid = valid_depth_mask(d)
    return torch.where(valid, 1.0 / d.clamp(min=1e-12), torch.zeros_like(d))  # invalid -> far


def _normalised_ball_disparity(inputs: ControlInputs, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Each ball centre's disparity on the frame's normalised scale (1 = the nearest scene point)."""
    p = inputs.probes
    depth = p.camera.project(p.centers.double())[2].float().clamp(min=1e-6)
    disp = 1.0 / depth
    if hi > lo:
        return ((disp - lo) / (hi - lo)).clamp(0.0, 1.0)
    return torch.full_like(disp, 0.5)


def normal_map(inputs: ControlInputs) -> torch.Tensor:
    """[3, h, w] DiffusionLight-convention normals in [0, 1] (see the module docstring)."""
    cam = inputs.probes.camera
    k = cam.intrinsics
    h, w = inputs.background_depth.shape
    rays = cam._camera_rays().float()  # [h, w, 3], z = -1 (camera frame: x right, y up, z back)
    if (k.height, k.width) != (h, w):
        raise ValueError(f"depth {h}x{w} does not match the camera {k.height}x{k.width}")
    d = inputs.background_depth.float()
    valid = valid_depth_mask(d)
    p = rays * torch.where(valid, d, torch.ones_like(d))[..., None]
    dv, du = torch.gradient(p, dim=(0, 1))  # along rows (down) and columns (right)
    n = torch.cross(dv, du, dim=-1)  # faces the camera for a fronto-parallel plane
    n = torch.where((n * p).sum(-1, keepdim=True) > 0, -n, n)
    norm = n.norm(dim=-1, keepdim=True)
    facing = torch.tensor([0.0, 0.0, 1.0]).expand_as(n)
    n = torch.where((norm > 1e-12) & valid[..., None], n / norm.clamp(min=1e-12), facing)
    n = _paint_spheres(n, rays, inputs)
    dl = torch.stack((-n[..., 0], n[..., 1], n[..., 2]), dim=0)  # x towards the left, y up, z towards the viewer
    return (dl + 1.0) * 0.5


def _paint_spheres(n: torch.Tensor, rays: torch.Tensor, inputs: ControlInputs) -> torch.Tensor:
    p = inputs.probes
    r = rays / rays.norm(dim=-1, keepdim=True)
    centres = p.camera.world_to_camera(p.centers.double()).float()
    for i in range(centres.shape[0]):
        inside = inputs.ball_masks[i] > 0
        if not bool(inside.any()):
            continue
        c, radius = centres[i], float(p.radii[i])
        rc = (r * c).sum(-1)
        disc = (rc * rc - (c * c).sum() + radius * radius).clamp(min=0.0)  # 0: the silhouette's tangent point
        hit = (rc - disc.sqrt())[..., None] * r
        ball_n = (hit - c) / radius
        ball_n = ball_n / ball_n.norm(dim=-1, keepdim=True).clamp(min=1e-12)
        n = torch.where(inside[..., None], ball_n, n)
    return n
