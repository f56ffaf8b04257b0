"""Real photographs of light: indoor HDR panoramas -> perspective LDR crop -> env map.

Protocol (DiffusionLight-style single-image evaluation):
1. Panorama: the linear HDR file listed in MANIFEST.tsv (`dev` and `test` reported
   separately; `control` (not indoor) reported apart and never mixed into the indoor numbers).
2. Camera: at the panorama's centre, horizontal FOV CROP_HFOV_DEG, CROP_SIZE pixels, yaw
   uniform in [-180, 180) and pitch uniform in [-PITCH_DEG, PITCH_DEG], drawn from a
   generator seeded by SEED and the file name (fixed across runs and machines).
3. Crop: the panorama sampled bilinearly along every pixel ray, tone mapped with
   DiffusionLight's TonemapHDR rule (core.exposure.display_tonemap: x^(1/2.4) scaled so its
   99th percentile maps to 0.9, clipped) and quantised to 8 bits, i.e. an ordinary LDR photo.
4. Ground truth: the panorama rotated into that camera's frame (world = camera frame, as for
   any single image the engine receives), compared at GT_HEIGHT rows.
5. Estimates at the camera centre: the reprojection prior on the crop with the engine's
   assumed box-room depth (no depth is given, as for a user's photo), and the trivial
   baseline: a constant env map of the crop's mean linearised colour.
Scores: the three-sphere metrics of bench.suite.evaluation (all scale-invariant or
percentile-normalised, so the photo's unknown exposure does not matter).
"""
from __future__ import annotations

import csv
import random
import time
from pathlib import Path

import torch

SEED = 7
CROP_HFOV_DEG = 60.0
CROP_SIZE = (128, 96)  # width, height
PITCH_DEG = 15.0
GT_HEIGHT = 64
PANO_HEIGHT = 256  # panoramas are area-downsampled to this before cropping (crop ~0.5 deg/px)
PRIOR_ENV_HEIGHT = 32
SPLITS = ("dev", "test", "control")

PROTOCOL = (
    f"Crop: {CROP_SIZE[0]}x{CROP_SIZE[1]} px, {CROP_HFOV_DEG:g}° horizontal FOV, yaw U[-180°, 180°), pitch U[-{PITCH_DEG:g}°, {PITCH_DEG:g}°] "
    f"(seed {SEED} + file name), DiffusionLight TonemapHDR (gamma 2.4, 99th percentile -> 0.9), 8-bit. "
    f"Ground truth: the panorama rotated into the camera frame, {GT_HEIGHT}x{2 * GT_HEIGHT}. Estimates at the camera centre: "
    "reprojection prior with the engine's assumed box-room depth; baseline = constant map of the crop's mean linearised colour. "
    "`control` panoramas are not indoor and are reported apart."
)


def read_manifest(hdri_dir: Path) -> list[dict]:
    with open(hdri_dir / "MANIFEST.tsv", newline="") as f:
        return list(csv.DictReader(f, delimiter="\t"))


def camera_rotation(yaw_deg: float, pitch_deg: float) -> torch.Tensor:
    """Camera-to-world rotation: pitch about x (up positive), then yaw about +y (the simulator's camera rule)."""
    from core.sim.state import pose_from_yaw_pitch

    return pose_from_yaw_pitch((0.0, 0.0, 0.0), yaw_deg, pitch_deg)[:3, :3]


def view_for(filename: str) -> tuple[float, float]:
    rng = random.Random(f"{SEED}:{filename}")
    return rng.uniform(-180.0, 180.0), rng.uniform(-PITCH_DEG, PITCH_DEG)


def perspective_crop(pano: torch.Tensor, R: torch.Tensor) -> tuple[torch.Tensor, "object"]:
    """Linear HDR crop [H, W, 3] seen by a camera with rotation R at the panorama's centre."""
    from core.camera import Camera, Intrinsics
    from core.envmap import sample_envmap

    intr = Intrinsics.from_hfov(CROP_SIZE[0], CROP_SIZE[1], CROP_HFOV_DEG)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = R
    _, d = Camera(intr, c2w).pixel_rays(dtype=torch.float64)
    return sample_envmap(pano.to(torch.float64), d).to(torch.float32), intr


def ldr_photo(hdr: torch.Tensor) -> torch.Tensor:
    from core.exposure import display_tonemap

    ldr = display_tonemap(hdr, percentile=99.0, gamma=2.4, max_mapping=0.9)
    return torch.round(ldr * 255.0) / 255.0


def estimate_reprojection(ldr: torch.Tensor, intr) -> torch.Tensor:
    from core.capture.load import capture_from_arrays
    from core.priors.reprojection import ReprojectionPrior

    capture = capture_from_arrays(ldr, None, intrinsics=intr)  # assumed box-room depth
    prior = ReprojectionPrior(env_height=PRIOR_ENV_HEIGHT)
    prior.bind(capture)
    return prior.envmaps(torch.zeros(1, 3), 0.0, GT_HEIGHT)[0]  # the camera centre (world = camera frame)


def estimate_mean_colour(ldr: torch.Tensor) -> torch.Tensor:
    from core.conventions import equirect_width, inverse_tonemap

    mean = inverse_tonemap(ldr).reshape(-1, 3).mean(0)
    return mean.expand(GT_HEIGHT, equirect_width(GT_HEIGHT), 3).clone()


def evaluate_panorama(path: Path, sphere_size: int) -> dict:
    import numpy as np

    from bench.suite.evaluation import score_probe
    from core.envmap import resize_envmap, rotate_envmap
    from core.io.hdr import read_hdr

    pano = torch.from_numpy(np.ascontiguousarray(read_hdr(path)[..., :3])).float()
    pano = resize_envmap(pano, PANO_HEIGHT) if pano.shape[0] > PANO_HEIGHT else pano
    yaw, pitch = view_for(path.name)
    R = camera_rotation(yaw, pitch)
    hdr, intr = perspective_crop(pano, R)
    ldr = ldr_photo(hdr)
    gt = rotate_envmap(resize_envmap(pano, GT_HEIGHT), R.T)  # camera frame: gt(d) = pano(R d)
    preds, seconds = {}, {}
    for name, fn in (("reprojection", lambda: estimate_reprojection(ldr, intr)), ("mean-colour", lambda: estimate_mean_colour(ldr))):
        t0 = time.perf_counter()
        preds[name] = fn()
        seconds[name] = time.perf_counter() - t0
    scores = score_probe(preds, gt, sphere_size)
    return {"file": path.name, "yaw_deg": round(yaw, 2), "pitch_deg": round(pitch, 2),
            "clipped_fraction": float((ldr.amax(-1) >= 0.99).float().mean()), "seconds": seconds, "scores": scores}


def run_panoramas(hdri_dir: Path, limit: int | None, sphere_size: int, quick: bool = False) -> dict:
    """Per split: every method's mean scores and per-image results (`skipped` if no data)."""
    from bench.suite.evaluation import mean_scores

    hdri_dir = Path(hdri_dir)
    if not (hdri_dir / "MANIFEST.tsv").is_file():
        return {"skipped": f"no MANIFEST.tsv in {hdri_dir} (pass --hdri-dir); the real-panorama section was not run"}
    rows = read_manifest(hdri_dir)
    out: dict = {"protocol": PROTOCOL, "hdri_dir": str(hdri_dir), "limit_per_split": limit, "splits": {}}
    for split in SPLITS:
        files = sorted(r["filename"] for r in rows if r.get("split") == split)
        files = [f for f in files if (hdri_dir / f).is_file()]
        if limit is not None:
            files = files[:limit]
        if not files:
            continue
        images = [evaluate_panorama(hdri_dir / f, sphere_size) for f in files]
        methods = {}
        for name in ("reprojection", "mean-colour"):
            methods[name] = {
                "images": len(images),
                "seconds_per_image": sum(im["seconds"][name] for im in images) / len(images),
                "metrics": mean_scores([im["scores"][name] for im in images]),
            }
        out["splits"][split + (" (not indoor)" if split == "control" else "")] = {"files": files, "methods": methods, "images": images}
    return out
