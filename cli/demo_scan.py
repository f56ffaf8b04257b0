"""The demo's second job: a room scan of the bundled panorama, as a phone makes it.

A photo-sphere-style scan (core.sim.room_scan: 46 frames at 10 fps, rings at pitch +10, +55 and
-40 degrees with tilts between, hand jitter, a lagging auto-exposure; 8-bit H.264) of
assets/sample_panorama.hdr is uploaded as a plain MP4, with no poses, no exposures and no
intrinsics: the job tracks it as a rotation, recovers each frame's exposure from the overlaps,
merges the frames into one HDR estimate and distils the field. The env map at the first
camera is compared with the panorama seen from there and with a constant map of the clip's
mean colour (the baseline to beat), on a diffuse sphere.
"""
from __future__ import annotations

from pathlib import Path

SPHERE_SIZE = 64


def room_scan_demo(out_dir: Path, backend, preset: str, camera: str = "rec709") -> dict:
    """Upload the scan through `backend` (the demo's service or in-process run), fetch the env
    map at the first camera and score it; returns the summary's `room_scan` entry."""
    import torch

    from cli.demo_upload import Upload
    from core.io import load_envmap
    from core.metrics import angular_error_deg, render_probe_spheres, si_rmse
    from core.sim.room_scan import scan_constant_map, scan_truth, write_sample_scan

    video, clip, pano = write_sample_scan(out_dir, camera)
    backend.estimate(Upload(file=video, depth=None, params={"preset": preset}, name="lightfield-scan"))
    path = out_dir / "first_camera_estimate.exr"
    backend.save_envmap((0.0, 0.0, 0.0), 0.0, path)
    meta = backend.metadata()
    capture = meta.get("capture", {})
    tracking = capture.get("metadata", capture).get("tracking", {}) if isinstance(capture, dict) else {}
    first = int((tracking.get("frames_kept") or [0])[0])  # the job's world: the first kept camera's axes
    est = torch.from_numpy(load_envmap(path))
    truth = scan_truth(pano, clip, est.shape[0], first)
    constant = scan_constant_map(clip, est.shape[0])
    (se, sc, sg), mask = render_probe_spheres([est, constant, truth], "diffuse", SPHERE_SIZE)
    return {
        "video": str(video), "camera": camera, "job": backend.job_id, "frames": len(clip.poses),
        "transfer": capture.get("metadata", {}).get("transfer") if isinstance(capture, dict) else None,
        "exposure_span_stops": round(float(clip.span_stops), 2),
        "envmap": str(path),
        "field": {"si_rmse": si_rmse(se, sg, mask), "angular_deg": angular_error_deg(se, sg, mask)},
        "constant": {"si_rmse": si_rmse(sc, sg, mask), "angular_deg": angular_error_deg(sc, sg, mask)},
        "tracking": tracking.get("method"), "frames_kept": len(tracking.get("frames_kept") or []),
        "wall_time_s": meta.get("training", {}).get("wall_time_s"),
    }


def format_scan(scan: dict) -> str:
    f, c = scan["field"], scan["constant"]
    return (
        f"Room scan ({scan['frames']} frames, {scan.get('camera', 'rec709')} camera, auto-exposure over "
        f"{scan['exposure_span_stops']} stops, no poses) at the "
        f"first camera, diffuse sphere vs the panorama:\n"
        f"  si-RMSE  field {f['si_rmse']:.3f}   constant map {c['si_rmse']:.3f}   "
        f"({f['si_rmse'] / max(c['si_rmse'], 1e-12):.2f}x)\n"
        f"  angle    field {f['angular_deg']:.2f} deg   constant map {c['angular_deg']:.2f} deg   "
        f"({f['angular_deg'] / max(c['angular_deg'], 1e-12):.2f}x)\n"
        f"  video {scan['video']}; env map {scan['envmap']}"
    )
