"""The indoor HDR panoramas the benches read, and the camera that looks into one.

The set lives outside the repository, by default in ../shared/hdri beside it (`--hdri-dir`
elsewhere): 1k equirectangular .hdr files (Poly Haven, CC0) and MANIFEST.tsv, one row per file
with its `split` (dev: tune on it; test and extra: report; control: outdoor, scored apart).
Every bench that scores real rooms lists its panoramas through here (bench/README.md says how
to get them)."""
from __future__ import annotations

import csv
from pathlib import Path

import torch

DEFAULT_HDRI_DIR = Path(__file__).resolve().parents[2] / "shared" / "hdri"  # ../shared/hdri from the repo
CROP_HFOV_DEG = 60.0
CROP_SIZE = (192, 144)  # width, height (the protocol)
PANO_HEIGHT = 256  # panoramas are area-downsampled to this before cropping (crop ~0.3 deg/px)
INDOOR_SPLITS = ("dev", "test", "extra")  # every indoor room; `control` is scored apart


def read_manifest(hdri_dir: Path) -> list[dict]:
    with open(hdri_dir / "MANIFEST.tsv", newline="") as f:
        return list(csv.DictReader(f, delimiter="\t"))


def split_files(hdri_dir, split: str, limit: int | None = None) -> list[Path]:
    """The panoramas of one split of MANIFEST.tsv, in its order (the first `limit`)."""
    hdri = Path(hdri_dir)
    return [hdri / r["filename"] for r in read_manifest(hdri) if r["split"] == split][:limit]


def indoor_rooms(hdri_dir: Path, limit: int | None = None) -> list[Path]:
    """Every indoor panorama of MANIFEST.tsv (splits INDOOR_SPLITS together), sorted by name."""
    rows = read_manifest(hdri_dir)
    names = sorted(
        r["filename"] for r in rows if r.get("split") in INDOOR_SPLITS and (hdri_dir / r["filename"]).is_file()
    )
    return [hdri_dir / n for n in names][:limit]


def load_panorama(path: Path) -> torch.Tensor:
    import numpy as np

    from core.envmap import resize_envmap
    from core.io.hdr import read_hdr

    pano = torch.from_numpy(np.ascontiguousarray(read_hdr(path)[..., :3])).float()
    return resize_envmap(pano, PANO_HEIGHT) if pano.shape[0] > PANO_HEIGHT else pano


def camera_rotation(yaw_deg: float, pitch_deg: float) -> torch.Tensor:
    """Camera-to-world rotation: pitch about x (up positive), then yaw about +y (the simulator's camera rule)."""
    from core.sim.state import pose_from_yaw_pitch

    return pose_from_yaw_pitch((0.0, 0.0, 0.0), yaw_deg, pitch_deg)[:3, :3]


def perspective_crop(pano: torch.Tensor, R: torch.Tensor) -> tuple[torch.Tensor, "object"]:
    """Linear HDR crop [H, W, 3] seen by a camera with rotation R at the panorama's centre."""
    from core.camera import Camera, Intrinsics
    from core.envmap import sample_envmap

    intr = Intrinsics.from_hfov(CROP_SIZE[0], CROP_SIZE[1], CROP_HFOV_DEG)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = R
    _, d = Camera(intr, c2w).pixel_rays(dtype=torch.float64)
    return sample_envmap(pano.to(torch.float64), d).to(torch.float32), intr
