"""A pan's temporal decision against what it must and must not call a change of light.

    python -m bench.pan_light_changes [--curve drawn|NAME|all] [-o bench/results/pan_light_changes.json]

A 60 deg pan (20 frames, 96 x 72, 60 deg FOV, true poses) of the bundled sample panorama
(assets/), decided by `core.capture.temporal.detect_temporal` with the moving camera's local
statistic over single blocks (NEIGHBOURHOOD 1, as before) and over 3 x 3 block neighbourhoods
(3, the product's):
* `pools`: a lamp's pool of light (gain 1.5 / 2 / 3 at its centre, a Gaussian 10 / 20 / 40 deg
  wide, at longitude -30 / 0 / 30 deg) switching off after frame 9: each must read as changing
  light (some are out of view at the switch, or too faint for the 8 % floor, under either rule);
* `drifts`: a soft-edged figure (12 deg wide, 55 deg tall; brightness 0.2 / 2 / 4 / 20 times
  the room's mean) walking along the wall at 1 / 2 / 3 deg a frame while the camera pans: none
  is a change of light.
Each clip is encoded by a camera curve (core.sim.camera_curves, `--curve`: by default drawn per
clip by its name from srgb, rec709, filmic and hlg10), and decoded as the loader decodes what
the file declares (the capture is built in memory). Counts per rule: pools found, drifts read as
changing light, over the realistic curves and per curve. The statistic and curve per clip are
in the JSON. Synthetic and small: the check on the dev panoramas is bench.transients --pans-only.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

PANORAMA = Path(__file__).resolve().parents[1] / "assets" / "sample_panorama.hdr"
FRAMES, SIZE, PAN_DEG, SWITCH = 20, (96, 72), 60.0, 10
RULES = (1, 3)


def pan_capture(paint, curve=None) -> object:
    """The capture of the pan with frame i's panorama `paint(i, pano, lat, lon)` (degrees), shot
    by the camera `curve` and loaded as its file declares (None: frames in the engine's
    convention)."""
    from core.camera import Camera, Intrinsics
    from core.capture.load import capture_from_arrays
    from core.sim.camera_curves import VIDEO
    from core.sim.panorama_room import PanoramaRoom, ldr_clip, load_panorama, render_clip
    from core.sim.state import pose_from_yaw_pitch
    from core.tracking.room import assumed_room

    pano = load_panorama(PANORAMA, 128)
    h, w = pano.shape[:2]
    lat = torch.linspace(90, -90, h)[:, None].expand(h, w)
    lon = torch.linspace(-180, 180, w)[None].expand(h, w)
    k = Intrinsics.from_hfov(*SIZE, 60.0)
    poses = [pose_from_yaw_pitch((0, 0, 0), PAN_DEG * i / (FRAMES - 1), 0) for i in range(FRAMES)]
    frames, depths = [], []
    for i, pose in enumerate(poses):
        room = PanoramaRoom(paint(i, pano, lat, lon), assumed_room(), torch.zeros(3))
        _, depth, hdr = render_clip(room, [Camera(k, pose)], supersample=1)
        frames.append(hdr[0]), depths.append(depth[0])
    ldr = ldr_clip(torch.stack(frames), curve=curve)
    return capture_from_arrays(ldr if curve is None else curve.loaded(ldr, VIDEO), torch.stack(depths), intrinsics=k,
                               poses=torch.stack(poses), fps=10)


def _decide(cap) -> dict:
    import core.capture.temporal as temporal

    out, kept = {}, temporal.NEIGHBOURHOOD
    try:
        for n in RULES:
            temporal.NEIGHBOURHOOD = n
            d = temporal.detect_temporal(cap)
            out[str(n)] = {
                "changing": d.uses_time,
                "statistic": round(d.statistic, 4),
                "threshold": round(d.threshold, 4),
            }
    finally:
        temporal.NEIGHBOURHOOD = kept
    return out


def pool(gain: float, width: float, centre: float):
    def paint(i, pano, lat, lon):
        g = 1 + (gain - 1) * torch.exp(-((lon - centre) ** 2 + (lat - 10) ** 2) / (2 * width**2))
        return pano * g[..., None] if i < SWITCH else pano
    return paint


def drift(brightness: float, speed: float):
    def paint(i, pano, lat, lon):
        a = ((6 - (lon - (-20 + speed * i)).abs()) / 1.4 + 0.5).clamp(0, 1) * ((lat > -40) & (lat < 15)).float()
        return pano * (1 - a[..., None]) + a[..., None] * brightness * float(pano.mean())
    return paint


def main(argv: list[str] | None = None) -> int:
    from bench.report import show_and_write
    from core.sim.camera_curves import NAMES, REFERENCE, VIDEO, add_curve_argument, curve_label, resolve, run_choices

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-o", "--output", default=None)
    add_curve_argument(p)
    args = p.parse_args(argv)

    def cam(name: str, choice: str):
        return resolve(choice, f"pan_light_changes:{name}", VIDEO)

    pools, drifts = [], []
    for choice in run_choices(args.curve, VIDEO):
        for g in (1.5, 2.0, 3.0):
            for wd in (10.0, 20.0, 40.0):
                for c in (-30.0, 0.0, 30.0):
                    curve = cam(f"pool {g} {wd} {c}", choice)
                    pools.append({"gain": g, "width_deg": wd, "centre_deg": c, "curve": curve.name,
                                  **_decide(pan_capture(pool(g, wd, c), curve))})
        for b in (0.2, 2.0, 4.0, 20.0):
            for sp in (1.0, 2.0, 3.0):
                curve = cam(f"drift {b} {sp}", choice)
                drifts.append({"brightness": b, "deg_per_frame": sp, "curve": curve.name,
                               **_decide(pan_capture(drift(b, sp), curve))})

    def counts(pools, drifts):
        return {
            f"neighbourhood {n}": {
                "pools found": f"{sum(r[str(n)]['changing'] for r in pools)} of {len(pools)}",
                "drifts read as changing": f"{sum(r[str(n)]['changing'] for r in drifts)} of {len(drifts)}",
            }
            for n in RULES
        }

    def real(rows):
        return [r for r in rows if r["curve"] != REFERENCE] or rows

    summary = counts(real(pools), real(drifts))
    per_curve = {curve_label(c): counts([r for r in pools if r["curve"] == c], [r for r in drifts if r["curve"] == c])
                 for c in NAMES if any(r["curve"] == c for r in pools + drifts)}
    show_and_write(summary, {"curve": args.curve, "summary": summary, "summary_per_curve": per_curve, "pools": pools,
                             "drifts": drifts}, args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
