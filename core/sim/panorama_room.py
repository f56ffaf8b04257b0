"""Captures with real texture and exact geometry: a panorama projected onto a box room.

The panorama (linear HDR, equirect, our layout) is what a camera at `centre` sees. Every
point of the box room's walls takes the panorama's radiance in the direction from `centre`
to it, so a camera AT the centre sees exactly perspective crops of the panorama (any
rotation), and a camera elsewhere sees the same textured walls with true parallax. Depth,
poses and the env map at any point inside are exact (ray casts of the same box), which is
what tracking and room-fitting tests need: real photographic texture, known answers.

Frames: `ldr_clip` / `render_clip` with a camera curve (core.sim.camera_curves) give that
camera's file codes (what a bench writes as a PNG or an MP4 declaring the curve); without one
they give the frames as the engine holds them after loading (its convention, for captures
built in memory with core.capture.load.capture_from_arrays).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from core.camera import Camera
from core.conventions import equirect_directions
from core.envmap import check_envmap, resize_envmap, sample_envmap
from core.exposure import display_tonemap
from core.sim.camera_curves import CameraCurve, display_exposure
from core.tracking.room import RoomBox


@dataclass(frozen=True)
class PanoramaRoom:
    panorama: torch.Tensor  # [H, 2H, 3] linear HDR
    box: RoomBox
    centre: torch.Tensor  # [3] world metres, inside the box

    def __post_init__(self):
        check_envmap(self.panorama, "panorama")
        object.__setattr__(self, "centre", torch.as_tensor(self.centre, dtype=torch.float64))
        if not bool(self.box.contains(self.centre[None])[0]):
            raise ValueError("panorama centre must be inside the room box")

    def radiance(self, origins: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(radiance [..., 3], hit distance along unit `directions` [...]) from inside the box."""
        d = directions.to(torch.float64)
        d = d / d.norm(dim=-1, keepdim=True)
        s = self.box.exit_distance(origins, d)
        hit = origins.to(torch.float64) + s[..., None] * d
        return sample_envmap(self.panorama.to(torch.float64), hit - self.centre).float(), s

    def render(self, camera: Camera, supersample: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
        """Linear HDR frame [H, W, 3] (box-filtered over s x s subpixels) and planar depth [H, W]."""
        k = camera.intrinsics
        big = Camera(k.scaled(k.width * supersample, k.height * supersample), camera.c2w)
        o, d = big.pixel_rays(dtype=torch.float64)
        rgb, _ = self.radiance(o.expand_as(d), d)
        rgb = torch.nn.functional.avg_pool2d(rgb.permute(2, 0, 1)[None], supersample)[0].permute(1, 2, 0)
        return rgb.contiguous(), self.box.depth(camera)

    def envmap(self, x, height: int) -> torch.Tensor:
        """Ground-truth env map [height, 2 height, 3] at world point x (d = direction light arrives from)."""
        d = equirect_directions(height, dtype=torch.float64)
        o = torch.as_tensor(x, dtype=torch.float64).expand_as(d)
        return self.radiance(o, d)[0]


def ldr_clip(hdr_frames: torch.Tensor, percentile: float = 99.0, curve: CameraCurve | None = None) -> torch.Tensor:
    """Frames [T, H, W, 3] with ONE exposure for the whole clip (DiffusionLight's TonemapHDR
    rule, fixed from all frames together: a locked exposure, no flicker): `curve`'s codes at its
    bit depth, or (None) 8-bit frames in the engine's convention (in-memory captures)."""
    flat = hdr_frames.reshape(1, -1, 3)
    if curve is not None:
        return curve.encode(hdr_frames * display_exposure(flat, percentile, 0.9))
    ldr = display_tonemap(flat, percentile=percentile, gamma=2.4, max_mapping=0.9).reshape(hdr_frames.shape)
    return torch.round(ldr * 255.0) / 255.0


def render_clip(
    room: PanoramaRoom, cameras: list[Camera], supersample: int = 2, curve: CameraCurve | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(frames [T, H, W, 3] at one exposure (`ldr_clip`: the curve's codes, or the engine's
    convention), planar depth [T, H, W], HDR frames)."""
    out = [room.render(c, supersample) for c in cameras]
    hdr = torch.stack([o[0] for o in out])
    return ldr_clip(hdr, curve=curve), torch.stack([o[1] for o in out]), hdr


def load_panorama(path, height: int | None = None) -> torch.Tensor:
    """A panorama file (.hdr / .exr) as [H, 2H, 3] float32, area-downsampled to `height` rows."""
    from core.io.envmap_io import load_envmap  # noqa: PLC0415 — core.io.envmap_io pulls in av, cv2, OpenEXR, PIL: imported when used

    pano = torch.from_numpy(np.ascontiguousarray(load_envmap(path)[..., :3])).float()
    return resize_envmap(pano, height) if height is not None and pano.shape[0] > height else pano
