"""Reader for the prior's training data ("lightfield-balls" v1, docs/training-data.md).

    DIR/dataset.json                 {"format": "lightfield-balls", "version": 1, "count", "resolution": [H, W]}
    DIR/samples/000000/
        image_with_balls.exr         linear HDR with the balls
        background.exr               linear HDR without them
        ball_mask.png                8-bit union of ball coverage
        depth_with_balls.npz         array `depth` [H, W], planar metres (NaN = none)
        meta.json                    {balls: [{center, radius, pixel}], intrinsics, c2w}

Any renderer can produce it. Samples are resized to the model's working size here; the
exposure and tone map are applied per training step (a fresh EV every time).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from core.priors.diffusion.conditioning import depth_to_control, resize

DATA_FORMAT = "lightfield-balls"
DATA_VERSION = 1
SAMPLE_FILES = ("image_with_balls.exr", "background.exr", "ball_mask.png", "depth_with_balls.npz", "meta.json")


class TrainingDataError(ValueError):
    """The training-data directory does not follow the lightfield-balls format."""


@dataclass(frozen=True)
class DatasetInfo:
    root: Path
    count: int
    resolution: tuple[int, int]
    samples: tuple[Path, ...]


def read_dataset_info(root: str | Path) -> DatasetInfo:
    root = Path(root)
    doc_path = root / "dataset.json"
    if not doc_path.is_file():
        raise TrainingDataError(f"{root}: no dataset.json (expected a lightfield-balls training-data directory)")
    try:
        doc = json.loads(doc_path.read_text())
    except json.JSONDecodeError as exc:
        raise TrainingDataError(f"{doc_path}: not valid JSON ({exc})") from exc
    if doc.get("format") != DATA_FORMAT:
        raise TrainingDataError(f"{doc_path}: format must be {DATA_FORMAT!r}, got {doc.get('format')!r}")
    if int(doc.get("version", 0)) > DATA_VERSION:
        raise TrainingDataError(f"{doc_path}: version {doc.get('version')} is newer than supported ({DATA_VERSION})")
    count = int(doc.get("count", 0))
    res = doc.get("resolution")
    if count < 1 or not (isinstance(res, list) and len(res) == 2 and min(res) > 0):
        raise TrainingDataError(
            f"{doc_path}: needs count >= 1 and resolution [H, W], got count={count}, resolution={res}"
        )
    samples = tuple(root / "samples" / f"{i:06d}" for i in range(count))
    for s in samples:
        missing = [f for f in SAMPLE_FILES if not (s / f).is_file()]
        if missing:
            raise TrainingDataError(f"{s}: missing {', '.join(missing)}")
    return DatasetInfo(root, count, (int(res[0]), int(res[1])), samples)


class BallDataset(Dataset):
    """Items: dict(hdr [3,h,w], background [3,h,w], coverage [1,h,w], control [3,h,w]) at `size`."""

    def __init__(self, root: str | Path, size: tuple[int, int]):
        self.info = read_dataset_info(root)
        self.size = (int(size[0]), int(size[1]))

    def __len__(self) -> int:
        return self.info.count

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        from core.io.depth import read_depth  # noqa: PLC0415 — core.io.depth pulls in av, cv2, OpenEXR, PIL: imported when used
        from core.io.exr import read_exr  # noqa: PLC0415 — core.io.exr pulls in av, cv2, OpenEXR, PIL: imported when used
        from core.io.images import read_image  # noqa: PLC0415 — core.io.images pulls in av, cv2, OpenEXR, PIL: imported when used

        d = self.info.samples[index]
        hdr = _chw(read_exr(d / "image_with_balls.exr"))
        background = _chw(read_exr(d / "background.exr"))
        coverage = _chw(read_image(d / "ball_mask.png"))[:1]
        depth = torch.from_numpy(np.ascontiguousarray(read_depth(d / "depth_with_balls.npz"), dtype=np.float32))
        shape = tuple(hdr.shape[-2:])
        for name, t in (("background.exr", background), ("ball_mask.png", coverage), ("depth_with_balls.npz", depth)):
            if tuple(t.shape[-2:]) != shape:
                raise TrainingDataError(
                    f"{d / name}: size {tuple(t.shape[-2:])} differs from image_with_balls.exr {shape}"
                )
        # HDR is resized in linear space (area-weighted, so highlights keep their energy)
        hdr, background = (resize(_finite(x)[None], self.size, mode="area")[0] for x in (hdr, background))
        return {
            "hdr": hdr,
            "background": background,
            "coverage": resize(coverage[None], self.size, mode="area")[0],
            "control": resize(depth_to_control(depth)[None], self.size)[0],
        }


class StepOrder(Sampler):
    """Sample indices as a pure function of (seed, position): epoch-wise permutations.

    Position k is the k-th sample this process consumes; resuming at position k0 yields
    exactly the indices an uninterrupted run would have, with no loader state to save.
    Under multi-GPU each rank reads a disjoint stride of the global sequence.
    """

    def __init__(self, count: int, seed: int, start: int = 0, rank: int = 0, world: int = 1):
        self.count, self.seed, self.start, self.rank, self.world = count, seed, start, rank, world

    def index_at(self, global_position: int) -> int:
        epoch, offset = divmod(global_position, self.count)
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + epoch)
        return int(torch.randperm(self.count, generator=g)[offset])

    def __iter__(self):
        k = self.start
        while True:
            yield self.index_at(k * self.world + self.rank)
            k += 1


def _chw(a: np.ndarray) -> torch.Tensor:
    t = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
    if t.dim() == 2:
        t = t[..., None]
    if t.shape[-1] == 1:
        t = t.expand(-1, -1, 3)
    return t[..., :3].permute(2, 0, 1).contiguous()


def _finite(hdr: torch.Tensor) -> torch.Tensor:
    """Non-finite or negative radiance (renderer fireflies) -> 0 / a large finite value."""
    return torch.nan_to_num(hdr, nan=0.0, posinf=1e6, neginf=0.0).clamp(0.0, 1e6)
