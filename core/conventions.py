"""The project's conventions, in one place. Every module imports them from here.

See docs/conventions.md for the prose version. Summary:

* World frame: right-handed, +y up, a camera looks along -z (OpenGL / ARKit / WebXR).
  Without given poses, world = camera frame of the first frame. Poses are
  camera-to-world 4x4 matrices in that camera convention. Units: metres.
* Image pixels: row r (down), column c (right); continuous pixel coordinates put the
  centre of pixel (r, c) at (u, v) = (c + 0.5, r + 0.5). Intrinsics fx, fy, cx, cy use
  these continuous coordinates, so a centred principal point is (W/2, H/2).
  The camera-frame ray through (u, v) is ((u - cx)/fx, -(v - cy)/fy, -1).
* Equirectangular env map, H x W with W = 2H: pixel centre (i, j) has
  theta = pi (i + 1/2) / H measured from +y and phi = 2 pi (j + 1/2) / W - pi,
  d = (sin theta sin phi, cos theta, -sin theta cos phi). The image centre looks
  forward (-z), right of centre is +x, the top row is up. d is the direction light
  ARRIVES FROM (from the probe towards the source).
* Radiance: linear HDR float32, relative units unless calibrated.
* Exposure / tone map (the paper's): LDR = clip((2^ev * L)^(1/2.4), 0, 1).
* Depth: planar depth (distance along the optical axis, i.e. -z in camera frame), metres;
  invalid = non-finite or <= 0, carried as a mask.
* Time: seconds from the first frame, t = frame / fps.
"""
from __future__ import annotations

import math

import torch

CONVENTIONS_VERSION = "1.0"

WORLD_UP = (0.0, 1.0, 0.0)
CAMERA_FORWARD = (0.0, 0.0, -1.0)
GAMMA = 2.4
DEFAULT_HFOV_DEG = 60.0  # intrinsics guess when none are given (documented in conventions.md)
DEFAULT_BRACKET_EVS = (0.0, -2.5, -5.0)
DEFAULT_EV_MIN = -5.0

# Summary sent with every artefact and HTTP response (header X-Lightfield-Conventions).
CONVENTIONS_SUMMARY = (
    f"v{CONVENTIONS_VERSION}; world=right-handed,+y up,camera -z; "
    "equirect=theta from +y,phi=0 at -z,+x right of centre,top row up,d=direction light arrives from; "
    "radiance=linear HDR; ldr=clip((2^ev*L)^(1/2.4),0,1); depth=planar metres; t=seconds from first frame"
)


# ---------------------------------------------------------------------------------------
# Equirectangular layout
# ---------------------------------------------------------------------------------------
def equirect_width(height: int) -> int:
    return 2 * int(height)


def theta_phi_to_direction(theta: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """(theta from +y, phi with 0 at -z and +pi/2 at +x) -> unit direction [..., 3]."""
    st = torch.sin(theta)
    return torch.stack((st * torch.sin(phi), torch.cos(theta), -st * torch.cos(phi)), dim=-1)


def direction_to_theta_phi(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit (or any non-zero) direction [..., 3] -> (theta in [0, pi], phi in (-pi, pi]).

    Uses atan2 for theta too, which stays accurate near the poles where acos loses
    precision. At the exact poles phi is 0 (atan2(0, -0) conventions aside): any phi is
    correct there, and samplers must not depend on it.
    """
    x, y, z = d.unbind(-1)
    rho2 = x * x + z * z
    off_axis = rho2 > 0
    # Double `where` keeps values unchanged off the axis and makes the gradient 0 (not NaN,
    # from sqrt'(0) and atan2(0, 0)) on it; on the axis phi is exactly 0 as documented.
    rho = torch.where(off_axis, torch.sqrt(torch.where(off_axis, rho2, torch.ones_like(rho2))), torch.zeros_like(rho2))
    theta = torch.atan2(rho, y)
    phi = torch.atan2(torch.where(off_axis, x, torch.zeros_like(x)), torch.where(off_axis, -z, torch.ones_like(z)))
    return theta, phi


def equirect_pixel_centres(height: int, device=None, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """theta [H, 1] and phi [1, W] of the pixel centres of an H x 2H equirect map."""
    i = torch.arange(height, device=device, dtype=torch.float64)
    j = torch.arange(equirect_width(height), device=device, dtype=torch.float64)
    theta, phi = equirect_pixel_to_theta_phi(i + 0.5, j + 0.5, height)
    return theta[:, None].to(dtype), phi[None, :].to(dtype)


def equirect_pixel_to_theta_phi(
    row_f: torch.Tensor, col_f: torch.Tensor, height: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Continuous pixel coordinates (row_f, col_f; pixel k spans [k, k + 1)) of an H x 2H map
    -> (theta, phi): the inverse of `direction_to_equirect_pixel`'s layout."""
    return math.pi * row_f / height, 2.0 * math.pi * col_f / equirect_width(height) - math.pi


def equirect_directions(height: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """Unit directions [H, 2H, 3] of the pixel centres of an equirect map."""
    theta, phi = equirect_pixel_centres(height, device=device, dtype=torch.float64)
    theta, phi = torch.broadcast_tensors(theta, phi)
    return theta_phi_to_direction(theta, phi).to(dtype)


def direction_to_equirect_pixel(d: torch.Tensor, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Direction [..., 3] -> continuous pixel coordinates (row_f, col_f) of an H x 2H map.

    Pixel centre (i, j) maps back to (i, j) exactly: row_f = H theta / pi - 1/2,
    col_f = W (phi + pi) / (2 pi) - 1/2. col_f is in [-1/2, W - 1/2); callers wrap it.
    """
    return theta_phi_to_equirect_pixel(*direction_to_theta_phi(d), height)


def theta_phi_to_equirect_pixel(
    theta: torch.Tensor, phi: torch.Tensor, height: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """(theta, phi) -> continuous pixel coordinates (row_f, col_f) of an H x 2H map (see
    `direction_to_equirect_pixel`); lets a caller reading several resolutions take the angles once."""
    row = height * theta / math.pi - 0.5
    col = equirect_width(height) * (phi + math.pi) / (2.0 * math.pi) - 0.5
    return row, col


# ---------------------------------------------------------------------------------------
# Camera frame
# ---------------------------------------------------------------------------------------
# OpenCV (x right, y down, z forward) <-> ours (x right, y up, z backward): flip y and z.
OPENCV_TO_OURS = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def pixel_to_camera_ray(u: torch.Tensor, v: torch.Tensor, fx, fy, cx, cy) -> torch.Tensor:
    """Continuous pixel coordinates -> camera-frame ray [..., 3] with z = -1 (not unit)."""
    x = (u - cx) / fx
    y = -(v - cy) / fy
    return torch.stack((x, y, -torch.ones_like(x)), dim=-1)


def sensor_readout_direction(width: int, height: int) -> tuple[float, float]:
    """The (u, v) axis along which a rolling shutter reads a frame: the frame's short side. Phone
    and camera sensors are landscape and read their rows (the long side) one after another, and a
    portrait video is that sensor turned by 90 deg, so the rows stay along the long side whatever
    the display rotation. The sign (which end is read first) is left to the fit."""
    return (1.0, 0.0) if height > width else (0.0, 1.0)


def camera_point_to_pixel(p: torch.Tensor, fx, fy, cx, cy) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Camera-frame points [..., 3] -> (u, v, planar depth). Depth <= 0 means behind."""
    depth = -p[..., 2]
    safe = torch.where(depth.abs() > 1e-12, depth, torch.full_like(depth, 1e-12))
    u = fx * p[..., 0] / safe + cx
    v = -fy * p[..., 1] / safe + cy
    return u, v, depth


# ---------------------------------------------------------------------------------------
# Exposure and tone map (the paper's)
# ---------------------------------------------------------------------------------------
def expose(radiance: torch.Tensor, ev: float | torch.Tensor) -> torch.Tensor:
    """Scale linear radiance by 2^ev."""
    return radiance * torch.pow(
        torch.as_tensor(2.0, dtype=radiance.dtype, device=radiance.device),
        torch.as_tensor(ev, dtype=radiance.dtype, device=radiance.device),
    )


def tonemap(radiance: torch.Tensor, ev: float | torch.Tensor = 0.0) -> torch.Tensor:
    """LDR = clip((2^ev L)^(1/2.4), 0, 1). Negative or non-finite radiance maps to 0/1 safely."""
    x = expose(radiance, ev)
    # clip before the power: values > 1 saturate anyway, and the gradient stays bounded
    x = torch.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)
    return x.pow(1.0 / GAMMA)


def tonemap_unclipped(radiance: torch.Tensor, ev: float | torch.Tensor = 0.0) -> torch.Tensor:
    """(2^ev L)^(1/2.4) without the clip to 1 (for losses that must see above-white values)."""
    x = expose(radiance, ev).clamp_min(0.0)
    return (x + 1e-12).pow(1.0 / GAMMA)


def inverse_tonemap(ldr: torch.Tensor, ev: float | torch.Tensor = 0.0) -> torch.Tensor:
    """Inverse of `tonemap` for unclipped pixels: L = ldr^2.4 / 2^ev."""
    x = ldr.clamp(0.0, 1.0).pow(GAMMA)
    return expose(x, -torch.as_tensor(ev, dtype=x.dtype))


# ---------------------------------------------------------------------------------------
# Depth and time
# ---------------------------------------------------------------------------------------
def valid_depth_mask(depth: torch.Tensor) -> torch.Tensor:
    """True where planar depth is usable: finite and > 0."""
    return torch.isfinite(depth) & (depth > 0)


DEFAULT_MEDIAN_DEPTH_M = 2.0  # metres, when a frame has no valid depth at all


def median_valid_depth(depth: torch.Tensor) -> float:
    """Median of the valid pixels of a depth map: the stand-in where a pixel's depth is invalid
    (DEFAULT_MEDIAN_DEPTH_M when no pixel is valid)."""
    valid = valid_depth_mask(depth)
    return float(depth[valid].median()) if bool(valid.any()) else DEFAULT_MEDIAN_DEPTH_M


def frame_time(frame_index, fps: float):
    """Seconds from the first frame."""
    return frame_index / float(fps)
