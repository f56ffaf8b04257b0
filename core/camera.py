"""Pinhole camera: intrinsics, camera-to-world poses, projection and unprojection.

Pixel and frame conventions come from core.conventions (OpenGL camera, planar depth).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from core.conventions import DEFAULT_HFOV_DEG, camera_point_to_pixel, pixel_to_camera_ray, valid_depth_mask


class CameraError(ValueError):
    """Invalid camera parameters or a point that cannot be projected (e.g. behind the camera)."""


# What a capture may claim (checked where user input becomes a camera: core.capture.load,
# hence also the service's upload check). Indoor scenes: a camera 10 km from the origin is
# a unit error, and float32 fields lose centimetres there. A pinhole beyond 170 degrees or
# below 1 degree of field of view is not a camera this method can use.
MAX_POSE_TRANSLATION_M = 1e4
RIGID_TOLERANCE = 1e-2  # |R^T R - I|, |det R - 1|, last row vs [0, 0, 0, 1]
MIN_FOV_DEG, MAX_FOV_DEG = 1.0, 170.0


def check_rigid_pose(c2w, what: str = "pose") -> None:
    """Raise CameraError unless `c2w` [4, 4] is a finite rigid camera-to-world transform
    (orthonormal rotation with det +1, last row [0, 0, 0, 1], translation within
    MAX_POSE_TRANSLATION_M). The message names `what` and the first rule broken."""
    p = torch.as_tensor(c2w, dtype=torch.float64)
    if p.shape != (4, 4) or not torch.isfinite(p).all():
        raise CameraError(f"{what} must be a finite 4x4 matrix")
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    if (p[3] - bottom).abs().max() > RIGID_TOLERANCE:
        raise CameraError(f"{what}: last row must be [0, 0, 0, 1], got {p[3].tolist()}")
    r = p[:3, :3]
    if (r.T @ r - torch.eye(3, dtype=torch.float64)).abs().max() > RIGID_TOLERANCE:
        raise CameraError(f"{what}: rotation part is not orthonormal (a rigid camera-to-world transform is expected)")
    if abs(float(torch.linalg.det(r)) - 1.0) > RIGID_TOLERANCE:
        raise CameraError(f"{what}: rotation part has determinant {float(torch.linalg.det(r)):.3g}, expected +1")
    if p[:3, 3].abs().max() > MAX_POSE_TRANSLATION_M:
        raise CameraError(f"{what}: translation {p[:3, 3].tolist()} m is beyond +-{MAX_POSE_TRANSLATION_M:g} m")


@dataclass(frozen=True)
class Intrinsics:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        for name in ("fx", "fy", "cx", "cy"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise CameraError(f"intrinsics.{name} must be finite, got {v}")
        if self.fx <= 0 or self.fy <= 0:
            raise CameraError(f"intrinsics focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise CameraError(f"image size must be positive, got {self.width}x{self.height}")

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_deg: float = DEFAULT_HFOV_DEG) -> "Intrinsics":
        if not (0.0 < hfov_deg < 180.0):
            raise CameraError(f"hfov_deg must be in (0, 180), got {hfov_deg}")
        f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(f, f, width / 2.0, height / 2.0, width, height)

    def matrix(self, dtype=torch.float32) -> torch.Tensor:
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=dtype)

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """Intrinsics for the same camera resampled to width x height."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)

    @property
    def hfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(0.5 * self.width / self.fx))

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(0.5 * self.height / self.fy))

    def check_plausible(self) -> "Intrinsics":
        """Raise CameraError unless both fields of view lie in [MIN_FOV_DEG, MAX_FOV_DEG] and the
        principal point lies within one image size of the centre (a user-given camera)."""
        for name, fov in (("fx", self.hfov_deg), ("fy", self.vfov_deg)):
            if not MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
                raise CameraError(f"intrinsics.{name} gives a {fov:.4g} deg field of view for a "
                                  f"{self.width}x{self.height} image; expected {MIN_FOV_DEG:g} to {MAX_FOV_DEG:g} deg")
        if abs(self.cx - self.width / 2) > self.width or abs(self.cy - self.height / 2) > self.height:
            raise CameraError(f"intrinsics.cx, cy = ({self.cx:g}, {self.cy:g}) lie more than one image size "
                              f"from the centre of the {self.width}x{self.height} image")
        return self

    def as_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width, "height": self.height}


@dataclass(frozen=True)
class Camera:
    """Intrinsics plus a camera-to-world pose (4x4, float64 tensor)."""

    intrinsics: Intrinsics
    c2w: torch.Tensor

    def __post_init__(self):
        c2w = torch.as_tensor(self.c2w, dtype=torch.float64)
        if c2w.shape != (4, 4):
            raise CameraError(f"pose must be 4x4, got {tuple(c2w.shape)}")
        if not torch.isfinite(c2w).all():
            raise CameraError("pose contains non-finite values")
        object.__setattr__(self, "c2w", c2w)

    @property
    def position(self) -> torch.Tensor:
        return self.c2w[:3, 3]

    @property
    def w2c(self) -> torch.Tensor:
        return torch.linalg.inv(self.c2w)

    def _camera_rays(self) -> torch.Tensor:
        """Camera-frame rays [H, W, 3] (z = -1, float64) through every pixel centre."""
        k = self.intrinsics
        v, u = torch.meshgrid(
            torch.arange(k.height, dtype=torch.float64) + 0.5,
            torch.arange(k.width, dtype=torch.float64) + 0.5,
            indexing="ij",
        )
        return pixel_to_camera_ray(u, v, k.fx, k.fy, k.cx, k.cy)

    def pixel_rays(self, dtype=torch.float32, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        """World-space ray origins [3] and unit directions [H, W, 3] through every pixel centre."""
        d = self._camera_rays() @ self.c2w[:3, :3].T
        d = d / d.norm(dim=-1, keepdim=True)
        return self.position.to(dtype=dtype, device=device), d.to(dtype=dtype, device=device)

    def unproject(self, depth: torch.Tensor) -> torch.Tensor:
        """Planar depth [H, W] -> world points [H, W, 3] (non-finite where depth is invalid)."""
        k = self.intrinsics
        if tuple(depth.shape) != (k.height, k.width):
            raise CameraError(f"depth shape {tuple(depth.shape)} does not match image {k.height}x{k.width}")
        ray = self._camera_rays()  # z = -1
        d64 = depth.to(torch.float64)
        p_cam = ray * torch.where(valid_depth_mask(d64), d64, torch.full_like(d64, float("nan")))[..., None]
        p = p_cam @ self.c2w[:3, :3].T + self.c2w[:3, 3]
        return p.to(depth.dtype if depth.is_floating_point() else torch.float32)

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """World points [..., 3] -> (u, v, planar depth); depth <= 0 means behind the camera."""
        k = self.intrinsics
        return camera_point_to_pixel(self.world_to_camera(points), k.fx, k.fy, k.cx, k.cy)

    def world_to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """World points [..., 3] -> camera frame, in the points' dtype and device."""
        w2c = self.w2c.to(dtype=points.dtype, device=points.device)
        return points @ w2c[:3, :3].T + w2c[:3, 3]


def identity_pose() -> torch.Tensor:
    return torch.eye(4, dtype=torch.float64)
