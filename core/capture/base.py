"""The `Capture`: what every layer works on (frames, depth, cameras, times), and the error
that names a bad capture input. Loading lives in core.capture.load."""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from core.camera import Camera, Intrinsics
from core.conventions import inverse_tonemap, valid_depth_mask


class CaptureError(ValueError):
    """Bad or inconsistent capture input; `.field` names the offending input."""

    def __init__(self, field_name: str, message: str):
        super().__init__(f"{field_name}: {message}")
        self.field = field_name


@dataclass
class Capture:
    frames: torch.Tensor  # [T, H, W, 3] float32 LDR in [0, 1]
    depth: torch.Tensor  # [T, H, W] float32 planar metres, NaN where invalid
    intrinsics: Intrinsics
    poses: torch.Tensor  # [T, 4, 4] float64 camera-to-world
    times: torch.Tensor  # [T] float32 seconds from the first frame
    fps: float
    depth_source: str
    source: str = ""
    warnings: list[str] = field(default_factory=list)
    # what the files said and what was assumed or estimated (intrinsics_source, poses_source,
    # depth_given, file metadata, tracking), listed in the artefact (docs/captures.md)
    metadata: dict = field(default_factory=dict)
    # [T] float32: the exposure (stops, core.conventions.tonemap's ev) each frame was taken at,
    # when the capture says (an auto-exposure video's per-frame metadata); None: every frame at 0
    stated_ev: torch.Tensor | None = None
    # the capture this one was resized from (Capture.resized): its LDR frames still hold what
    # area-averaging loses, which pixels clipped (core.capture.highlights linearises there)
    full_resolution: "Capture | None" = field(default=None, repr=False, compare=False)

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def height(self) -> int:
        return int(self.frames.shape[1])

    @property
    def width(self) -> int:
        return int(self.frames.shape[2])

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0]) if self.num_frames > 1 else 0.0

    @property
    def frame_ev(self) -> torch.Tensor:
        """[T] float32 exposure of each frame in stops (zeros unless the capture gave them)."""
        if self.stated_ev is None:
            return torch.zeros(self.num_frames)
        return self.stated_ev.float()

    def linear(self) -> torch.Tensor:
        """[T, H, W, 3] linear radiance of the frames in scene units: each frame's own exposure
        removed (core.conventions.inverse_tonemap), clipped pixels at their frame's white."""
        return inverse_tonemap(self.frames, self.frame_ev[:, None, None, None])

    @property
    def static_camera(self) -> bool:
        return bool(torch.allclose(self.poses, self.poses[:1].expand_as(self.poses), atol=1e-9))

    def nearest_frames(self, t: torch.Tensor) -> torch.Tensor:
        """Indices [N] (long) of the frames nearest to times t [N] seconds (a tie: the earlier)."""
        t = torch.as_tensor(t, dtype=torch.float64).reshape(-1)
        return (t[:, None] - self.times.double()[None]).abs().argmin(1)

    def spread_frames(self, n: int) -> torch.Tensor:
        """At most `n` distinct frame indices [k] (long, ascending) spread evenly over the capture:
        the first frame, and with n >= 2 the last."""
        count = max(1, min(self.num_frames, int(n)))
        return torch.linspace(0, self.num_frames - 1, count).round().long().unique()

    def camera(self, i: int) -> Camera:
        return Camera(self.intrinsics, self.poses[i])

    def resized(self, height: int) -> "Capture":
        """The same capture at a working resolution (area-averaged frames, nearest-valid depth
        by min-pooling so thin near objects are not averaged with the far wall)."""
        if height >= self.height:
            return self
        width = max(1, round(self.width * height / self.height))
        f = torch.nn.functional.interpolate(self.frames.permute(0, 3, 1, 2), size=(height, width), mode="area")
        d = self.depth.clone()
        d = torch.where(valid_depth_mask(d), d, torch.full_like(d, float("inf")))
        d = -torch.nn.functional.adaptive_max_pool2d(-d[:, None], (height, width))[:, 0]
        d = torch.where(torch.isfinite(d), d, torch.full_like(d, float("nan")))
        return Capture(
            frames=f.permute(0, 2, 3, 1).contiguous().clamp(0, 1),
            depth=d.contiguous(),
            intrinsics=self.intrinsics.scaled(width, height),
            poses=self.poses,
            times=self.times,
            fps=self.fps,
            depth_source=self.depth_source,
            source=self.source,
            warnings=list(self.warnings),
            metadata=dict(self.metadata),
            stated_ev=self.stated_ev,
            full_resolution=self.full_resolution or self,
        )

    def summary(self) -> dict:
        return {
            "source": self.source,
            "frames": self.num_frames,
            "width": self.width,
            "height": self.height,
            "fps": self.fps,
            "duration_s": self.duration,
            "intrinsics": self.intrinsics.as_dict(),
            "static_camera": self.static_camera,
            "poses": self.poses.reshape(self.num_frames, 16).tolist(),
            "depth_source": self.depth_source,
            "frame_ev": None if self.stated_ev is None else [round(float(e), 4) for e in self.stated_ev],
            "warnings": list(self.warnings),
            "metadata": dict(self.metadata),
        }
