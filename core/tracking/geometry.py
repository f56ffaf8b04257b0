"""Small geometric helpers for tracking, on top of core.conventions (never re-deriving it).

Bearings are unit camera-frame rays in OUR camera frame (+y up, looking along -z); a
camera-to-world rotation R maps them to world directions. Poses are c2w 4x4 float64.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from core.camera import Intrinsics
from core.conventions import OPENCV_TO_OURS, camera_point_to_pixel, pixel_to_camera_ray


def bearings(points: np.ndarray, k: Intrinsics, focal: float | None = None) -> np.ndarray:
    """Pixels [N, 2] (u, v) -> unit bearings [N, 3] in our camera frame."""
    fx = fy = focal if focal is not None else None
    fx, fy = (k.fx, k.fy) if fx is None else (fx, fx * k.fy / k.fx)
    p = torch.from_numpy(np.asarray(points, np.float64))
    r = pixel_to_camera_ray(p[:, 0], p[:, 1], fx, fy, k.cx, k.cy)
    return (r / r.norm(dim=-1, keepdim=True)).numpy()


def project(p_cam: np.ndarray, k: Intrinsics, focal: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points [N, 3] -> (pixels [N, 2], planar depth [N])."""
    fx, fy = (k.fx, k.fy) if focal is None else (focal, focal * k.fy / k.fx)
    u, v, z = camera_point_to_pixel(torch.from_numpy(np.asarray(p_cam, np.float64)), fx, fy, k.cx, k.cy)
    return torch.stack((u, v), -1).numpy(), z.numpy()


def kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation R [3, 3] minimising sum |b - R a|^2 for unit vectors a, b [N, 3]."""
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def rotation_angle_deg(R: np.ndarray) -> float:
    c = (np.trace(R) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(v, np.float64).reshape(-1, 3)).as_matrix()


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(np.asarray(R, np.float64).reshape(-1, 3, 3)).as_rotvec()


def opencv_w2c_to_c2w(R_cv: np.ndarray, t_cv: np.ndarray) -> np.ndarray:
    """OpenCV world-to-camera (x_cam = R X + t; camera x right, y down, z forward) -> our c2w 4x4."""
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R_cv, np.asarray(t_cv).reshape(3)
    return np.linalg.inv(w2c) @ OPENCV_TO_OURS.numpy()


def c2w_to_opencv_w2c(c2w: np.ndarray) -> np.ndarray:
    """Our c2w 4x4 -> OpenCV world-to-camera 4x4 (inverse of `opencv_w2c_to_c2w`)."""
    return np.linalg.inv(np.asarray(c2w, np.float64) @ OPENCV_TO_OURS.numpy())


def relative_to_first(c2w: np.ndarray, points: np.ndarray | None = None):
    """Re-express poses [T, 4, 4] (and points [N, 3]) in the first camera's frame (world = frame 0,
    as core.conventions prescribes when no poses are given)."""
    inv0 = np.linalg.inv(c2w[0])
    out = inv0[None] @ c2w
    if points is None:
        return out, None
    return out, points @ inv0[:3, :3].T + inv0[:3, 3]
