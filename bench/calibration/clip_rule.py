"""How far off is the clip rule? Clipped LDR crops of real HDR panoramas with known radiance.

    python -m bench.calibration.clip_rule [--hdri-dir DIR] [--fit] [--splits dev,test,extra] [--curve drawn|NAME]
        [-o out.json]

For every panorama of the split, VIEWS_PER_PANORAMA photos are made exactly as in the
real-panorama protocol (bench.real_panoramas: CROP_SIZE, 60° FOV, TonemapHDR's exposure, a
camera curve per photo (core.sim.camera_curves, `--curve`: drawn by the photo's name by
default), 8 bits, read as the loader reads the PNG: decoded with what the file declares),
with views seeded by the file name and the view index (pitch up to +-VIEW_PITCH_DEG so
ceiling lamps are in some); every other view is over-exposed by up to MAX_EXTRA_EV stops, so
the rule is not fitted to one tone map's exposure only. Each photo's clipped blobs (core.capture.highlights.find_blobs)
get a true factor: the blob's mean true luminance, in the photo's linear units (the
exposure is known), over its mean linearised luminance as the engine sees it. Error of a rule = |log2
(estimated factor / true factor)| in stops, per blob (mean, and weighted by the blob's true
energy, which is what lighting feels).

The 1k panoramas (area-downsampled) hold few point sources brighter than ~5 stops over
white, so each dev panorama also gets SYNTHETIC_LAMPS_PER_PANORAMA photos with a disc lamp
added through a lens PSF (synthetic_lamp_samples; up to 8 stops, with glare).

Rules compared: the old fixed boost (8x), the best single boost (same weights), and the blob
rule (core.capture.highlights.RULE_COEFFICIENTS). `--fit` refits the rule's coefficients on
the real blobs of every panorama of `--splits` (by default every indoor room: dev, test and
extra, what a user gets) by weighted least squares in stops, and reports their
leave-one-panorama-out error; the synthetic lamps (dev) are reported as a stress test, not
fitted. The accuracy benches refit the coefficients without the room they score
(`cv_coefficients`). Colour (`colour`): the white-hot pixels' estimate left white vs in the
halo's spill colour (core.capture.highlights.Blob.spill_colour), degrees between RGB vectors;
the accuracy benches choose its two settings without the room they score too
(`cv_spill_colour`).
"""
from __future__ import annotations

import argparse
import json
import math
import random
import sys
from pathlib import Path

import numpy as np
import torch

from core.exposure import LUMINANCE_WEIGHTS
from core.priors.reprojection import CLIP_BOOST

VIEWS_PER_PANORAMA = 16
VIEW_PITCH_DEG = 40.0
MAX_EXTRA_EV = 3.0
SYNTHETIC_LAMPS_PER_PANORAMA = 12
FIXED_BOOST = CLIP_BOOST  # the reprojection prior's old fixed boost (clip_rule "fixed")


def photo_views(filename: str) -> list[tuple[float, float, float]]:
    """(yaw, pitch, extra exposure in stops): even views use the protocol's exposure, odd ones
    are over-exposed by U(0, MAX_EXTRA_EV) (a camera metering a dark room clips more)."""
    rng = random.Random(f"clip-rule:{filename}")
    return [
        (
            rng.uniform(-180.0, 180.0),
            rng.uniform(-VIEW_PITCH_DEG, VIEW_PITCH_DEG),
            rng.uniform(0.0, MAX_EXTRA_EV) * (i % 2),
        )
        for i in range(VIEWS_PER_PANORAMA)
    ]


def view_curve(filename: str, view: int, curve: str = "drawn"):
    """The camera curve of one of the panorama's photos here (`curve` "drawn": drawn by the
    photo's name, among the still curves; a name forces it)."""
    from core.sim.camera_curves import STILL, resolve

    return resolve(curve, f"{filename}#clip-rule-view{view}", STILL)


def as_loaded(true: torch.Tensor, cam) -> tuple[torch.Tensor, torch.Tensor]:
    """(frame in the engine's convention, its linearisation) of exposed linear light `true`
    photographed by `cam` and loaded from its PNG (decoded with what the file declares)."""
    from core.conventions import inverse_tonemap
    from core.sim.camera_curves import STILL

    ldr = cam.loaded(cam.encode(true), STILL).float()
    return ldr, inverse_tonemap(ldr)


def exposure_scale(hdr: torch.Tensor) -> float:
    """Linear factor of the protocol's tone map: linearised LDR = scale x HDR where unclipped
    (display_tonemap scales hdr^(1/2.4) by 0.9 / its 99th percentile; inverse_tonemap is x^2.4)."""
    x = hdr.float().clamp_min(0.0).pow(1.0 / 2.4).reshape(-1)
    level = float(torch.quantile(x, 0.99))
    return (0.9 / level) ** 2.4 if level > 1e-8 else 1.0


def blob_samples(path: Path, curve: str = "drawn") -> list[dict]:
    """Every clipped blob of every view of one panorama: features and true factor."""
    from bench.panoramas import camera_rotation, load_panorama, perspective_crop
    from core.capture.highlights import clipped_mask, find_blobs, pixel_solid_angle

    pano = load_panorama(path)
    out = []
    for view, (yaw, pitch, ev) in enumerate(photo_views(path.name)):
        hdr, intr = perspective_crop(pano, camera_rotation(yaw, pitch))
        scale = exposure_scale(hdr) * 2.0 ** ev
        ldr, lin = as_loaded(hdr.clamp_min(0.0) * scale, view_curve(path.name, view, curve))
        lin = lin.numpy()
        clipped = clipped_mask(ldr).numpy()
        labels, blobs = find_blobs(lin, clipped, pixel_solid_angle(intr))
        y_true = (hdr.numpy() * scale) @ np.asarray(LUMINANCE_WEIGHTS)
        y_lin = lin @ np.asarray(LUMINANCE_WEIGHTS)
        for k, blob in enumerate(blobs, start=1):
            sel = labels == k
            true = float(y_true[sel].mean()) / max(float(y_lin[sel].mean()), 1e-9)
            out.append(
                {
                    "file": path.name,
                    "features": list(blob.features()),
                    "area_px": blob.area_px,
                    "halo": list(blob.halo),
                    "ring_pixels": list(blob.ring_pixels),
                    "white_fraction": blob.white_fraction,
                    "true_stops": math.log2(max(true, 1e-9)),
                    "energy": float(y_true[sel].sum()),
                    **colour_sample(hdr.numpy(), lin, sel, blob),
                }
            )
    return out


def colour_sample(true_rgb: np.ndarray, lin: np.ndarray, sel: np.ndarray, blob) -> dict:
    """A blob's white-hot pixels (every channel clipped: the ones the spill colour recolours):
    their true mean RGB and the rule's colour for them (None: left white)."""
    from core.capture.highlights import white_hot_mask

    hot = sel & white_hot_mask(lin)
    if not hot.any():
        return {"hot_true_rgb": None, "spill_colour": None}
    return {
        "hot_true_rgb": [float(v) for v in true_rgb[hot].mean(0)],
        "hot_energy": float(true_rgb[hot].sum()),
        "spill_colour": blob.spill_colour(),
        "halo_rgb": [list(c) if c is not None else None for c in blob.halo_rgb],
    }


COLOUR_SWEEP_EXCESS = (0.01, 0.02, 0.05, 0.1, 0.2)
COLOUR_SWEEP_RATIO = (0.3, 0.5, 0.7)


def recoloured(samples: list[dict], excess: float | None, ratio: float | None) -> list[dict]:
    """The blobs with white-hot pixels, their spill colour redone with the two settings (None:
    left white)."""
    from core.capture.highlights import Blob

    out = []
    for s in samples:
        if s.get("hot_true_rgb") is None:
            continue
        blob = Blob(s["area_px"], 0.0, tuple(s["halo"]), tuple(s["ring_pixels"]), s["white_fraction"],
                    tuple(tuple(c) if c is not None else None for c in s["halo_rgb"]))
        out.append({**s, "spill_colour": None if excess is None else blob.spill_colour(excess, ratio)})
    return out


def colour_sweep(samples: list[dict]) -> list[dict]:
    """`colour_errors` with the spill colour's two settings swept."""
    out = []
    for excess in COLOUR_SWEEP_EXCESS:
        for ratio in COLOUR_SWEEP_RATIO:
            e = colour_errors(recoloured(samples, excess, ratio))
            out.append({"min_excess": excess, "min_ratio": ratio, "recoloured": e["recoloured"],
                        **{k: round(v, 3) for k, v in e["spill_colour"].items()}})
    return out


COLOUR_SETTINGS = [(None, None)] + [(e, r) for e in COLOUR_SWEEP_EXCESS for r in COLOUR_SWEEP_RATIO]
# "left white" as the job's setting: an excess over the halo's background no spill reaches
LEFT_WHITE_EXCESS = 1e9


def choose_spill_colour(chosen: list[dict]) -> tuple:
    """Of COLOUR_SETTINGS ((None, None): left white), the one with the lowest energy-weighted
    colour error of the white-hot pixels over the blobs `chosen` (the first where none has any)."""
    def cost(setting):
        e = colour_errors(recoloured(chosen, *setting))
        return e["spill_colour"]["energy_weighted_deg"] if e["blobs"] else 0.0
    return min(COLOUR_SETTINGS, key=cost)


def as_job_setting(setting: tuple) -> list[float]:
    """A `choose_spill_colour` result as the reprojection prior's `spill_colour` setting."""
    excess, ratio = setting
    return [LEFT_WHITE_EXCESS, 1.0] if excess is None else [float(excess), float(ratio)]


def colour_cv(samples: list[dict]) -> dict:
    """The spill colour's two settings chosen without the room scored: per room, the sweep's
    setting (or leaving white-hot pixels white) with the lowest energy-weighted colour error on
    the other rooms' blobs (`choose_spill_colour`), and the room's blobs recoloured with it.
    Against the shipped settings and against leaving them white, on the same blobs."""
    from core.capture.highlights import SPILL_COLOUR

    by_room: dict[str, list[dict]] = {}
    for s in samples:
        by_room.setdefault(s["file"], []).append(s)
    folds = leave_one_room_out(by_room, choose_spill_colour)
    held_out = [s for room, ss in by_room.items() for s in recoloured(ss, *folds[room])]
    shipped = SPILL_COLOUR
    return {
        "chosen_per_room": {room: list(c) for room, c in folds.items()},
        "rooms_choosing_shipped": sum(tuple(c) == shipped for c in folds.values()),
        "chosen_on_all_rooms": list(choose_spill_colour(samples)),
        "held_out": colour_errors(held_out)["spill_colour"],
        "shipped": colour_errors(recoloured(samples, *shipped))["spill_colour"],
        "left_white": colour_errors(recoloured(samples, None, None))["spill_colour"],
        "blobs": len(held_out),
    }


def colour_angle_deg(a, b) -> float:
    """Degrees between two RGB vectors (core.metrics.angular_error_deg on one pixel)."""
    from core.metrics import angular_error_deg

    return angular_error_deg(torch.tensor([a], dtype=torch.float64), torch.tensor([b], dtype=torch.float64))


def colour_errors(samples: list[dict]) -> dict:
    """Colour error (degrees between RGB vectors) of the white-hot pixels' estimate: left white
    (the boost alone) vs the spill colour where the halo gives one; mean per blob and weighted
    by the pixels' true energy, over the blobs with white-hot pixels."""
    hot = [s for s in samples if s.get("hot_true_rgb") is not None]
    if not hot:
        return {"blobs": 0}
    w = np.array([s["hot_energy"] for s in hot])
    white = np.array([colour_angle_deg(s["hot_true_rgb"], (1.0, 1.0, 1.0)) for s in hot])
    spill = np.array([colour_angle_deg(s["hot_true_rgb"], s["spill_colour"] or (1.0, 1.0, 1.0)) for s in hot])
    used = np.array([s["spill_colour"] is not None for s in hot])

    def summary(e, w):
        return {
            "mean_deg": float(e.mean()),
            "median_deg": float(np.median(e)),
            "energy_weighted_deg": float((e * w).sum() / w.sum()),
        }

    return {
        "blobs": len(hot),
        "recoloured": int(used.sum()),
        "white": summary(white, w),
        "spill_colour": summary(spill, w),
        "recoloured_only": {"white": summary(white[used], w[used]), "spill_colour": summary(spill[used], w[used])}
        if used.any()
        else None,
    }


def lens_psf(sigma: float, glare: float, tail_px: float = 4.0, half: int = 15) -> torch.Tensor:
    """A lens PSF [2 half + 1]^2: Gaussian core (sigma px) plus a `glare` share of the energy in
    an exponential tail (tail_px), normalised to 1."""
    k = torch.arange(-half, half + 1, dtype=torch.float64)
    ky, kx = torch.meshgrid(k, k, indexing="ij")
    r = (ky**2 + kx**2).sqrt()
    psf = (1 - glare) * torch.exp(-(r**2) / (2 * sigma**2)) / (2 * math.pi * sigma**2) + glare * torch.exp(
        -r / tail_px
    ) / (2 * math.pi * tail_px**2)
    return psf / psf.sum()


def synthetic_lamp_samples(path: Path, curve: str = "drawn") -> list[dict]:
    """SYNTHETIC_LAMPS_PER_PANORAMA photos of the panorama, each with a disc lamp added (radiance
    2^U(1, 8) x white, radius U(1, 6) px, through lens_psf with sigma U(0.5, 1.5), glare
    U(0, 0.05)): bright point sources the 1k panoramas (area-downsampled) hardly contain."""
    from bench.panoramas import camera_rotation, load_panorama, perspective_crop
    from core.capture.highlights import clipped_mask, find_blobs, pixel_solid_angle

    rng = random.Random(f"clip-rule-lamps:{path.name}")
    pano = load_panorama(path)
    out = []
    for lamp_index in range(SYNTHETIC_LAMPS_PER_PANORAMA):
        hdr, intr = perspective_crop(
            pano, camera_rotation(rng.uniform(-180, 180), rng.uniform(-VIEW_PITCH_DEG, VIEW_PITCH_DEG))
        )
        scale = exposure_scale(hdr)
        H, W = hdr.shape[:2]
        cy, cx, radius = rng.uniform(20, H - 20), rng.uniform(20, W - 20), rng.uniform(1.0, 6.0)
        yy, xx = torch.meshgrid(
            torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij"
        )
        disc = (((yy - cy) ** 2 + (xx - cx) ** 2).sqrt() <= radius).double()
        lamp = disc * 2.0 ** rng.uniform(1.0, 8.0) / scale  # radiance in the panorama's units
        psf = lens_psf(rng.uniform(0.5, 1.5), rng.uniform(0.0, 0.05))
        lamp = torch.nn.functional.conv2d(torch.nn.functional.pad(lamp[None, None], (15,) * 4), psf[None, None])[0, 0]
        tint = torch.tensor([1.0, rng.uniform(0.8, 1.0), rng.uniform(0.6, 1.0)], dtype=torch.float64)
        true = (hdr.double() + lamp[..., None] * tint) * scale
        ldr, lin = as_loaded(true, view_curve(path.name, VIEWS_PER_PANORAMA + lamp_index, curve))
        lin = lin.numpy()
        labels, blobs = find_blobs(lin, clipped_mask(ldr).numpy(), pixel_solid_angle(intr))
        k = int(labels[int(cy), int(cx)])
        if k == 0:
            continue
        sel = labels == k
        y_true = true.numpy() @ np.asarray(LUMINANCE_WEIGHTS)
        y_lin = lin @ np.asarray(LUMINANCE_WEIGHTS)
        t = float(y_true[sel].mean()) / max(float(y_lin[sel].mean()), 1e-9)
        b = blobs[k - 1]
        out.append({"file": path.name, "features": list(b.features()), "area_px": b.area_px,
                    "halo": list(b.halo), "ring_pixels": list(b.ring_pixels), "white_fraction": b.white_fraction,
                    "true_stops": math.log2(max(t, 1e-9)), "energy": float(y_true[sel].sum()), "synthetic": True,
                    **colour_sample(true.numpy(), lin, sel, b)})
    return out


def predict_stops(features: np.ndarray, coefficients) -> np.ndarray:
    from core.capture.highlights import MAX_BOOST_STOPS

    return np.clip(features @ np.asarray(coefficients, dtype=np.float64), 0.0, MAX_BOOST_STOPS)


def errors(samples: list[dict], stops: np.ndarray) -> dict:
    true = np.array([s["true_stops"] for s in samples])
    e = np.abs(stops - true)
    w = np.array([s["energy"] for s in samples])
    return {
        "blobs": len(samples),
        "mean_abs_stops": float(e.mean()),
        "median_abs_stops": float(np.median(e)),
        "energy_weighted_abs_stops": float((e * w).sum() / w.sum()),
        "mean_signed_stops": float((stops - true).mean()),
    }


def fit(samples: list[dict], constant_only: bool = False) -> list[float]:
    """Weighted least squares in stops (targets clamped at 0 like the rule). Weights
    sqrt(energy): every blob counts, the ones carrying the light more (unweighted, the many
    marginally clipped specks win; energy-weighted, three lamps decide)."""
    X = np.array([s["features"] for s in samples])
    if constant_only:
        X = X[:, :1]
    y = np.maximum(np.array([s["true_stops"] for s in samples]), 0.0)
    w = np.sqrt(np.array([s["energy"] for s in samples]))
    w = np.sqrt(w / w.mean())[:, None]
    return [float(c) for c in np.linalg.lstsq(X * w, y * w[:, 0], rcond=None)[0]]


def evaluate(samples: list[dict], coefficients, constant_stops: float) -> dict:
    X = np.array([s["features"] for s in samples])
    return {"fixed_8x": errors(samples, np.full(len(samples), math.log2(FIXED_BOOST))),
            "best_constant": errors(samples, np.full(len(samples), constant_stops)),
            "rule": errors(samples, predict_stops(X, coefficients)),
            "colour": colour_errors(samples)}


def leave_one_room_out(samples: dict[str, list[dict]], fit_on) -> dict[str, object]:
    """{room: fit_on(the samples of every other room)}: the one fold loop of this bench."""
    return {n: fit_on([s for m, ss in samples.items() if m != n for s in ss]) for n in samples}


def cv_coefficients(rooms: list[Path], samples: dict[str, list[dict]] | None = None
                    ) -> tuple[dict[str, list[float]], list[float]]:
    """The rule's coefficients fitted on the real blobs of every room but one (room name ->
    coefficients, for scoring that room) and on all of them (what a user gets: RULE_COEFFICIENTS
    is this fit on every indoor room). `samples`: {room: blob_samples} where the caller has them."""
    from core.capture.highlights import RULE_COEFFICIENTS

    samples = samples if samples is not None else {p.name: blob_samples(p) for p in rooms}

    def fit_on(chosen):
        return fit(chosen) if chosen else [float(c) for c in RULE_COEFFICIENTS]  # no blob: nothing to fit

    return leave_one_room_out(samples, fit_on), fit_on([s for ss in samples.values() for s in ss])


def cv_spill_colour(samples: dict[str, list[dict]]) -> tuple[dict[str, list[float]], list[float]]:
    """The spill colour's settings chosen on the real blobs of every room but one (room name ->
    the prior's `spill_colour`, for scoring that room) and on all of them (what a user gets:
    SPILL_COLOUR is this choice on every indoor room)."""
    def choose_on(chosen):
        return as_job_setting(choose_spill_colour(chosen))

    return leave_one_room_out(samples, choose_on), choose_on([s for ss in samples.values() for s in ss])


def leave_one_panorama_out(samples: list[dict]) -> dict:
    """Error of the rule and of the best constant when each panorama is predicted by a fit on the others."""
    by_room: dict[str, list[dict]] = {}
    for s in samples:
        by_room.setdefault(s["file"], []).append(s)
    rules = leave_one_room_out(by_room, fit)
    consts = leave_one_room_out(by_room, lambda chosen: fit(chosen, constant_only=True)[0])
    rule = np.array([predict_stops(np.array([s["features"]]), rules[s["file"]])[0] for s in samples])
    const = np.array([consts[s["file"]] for s in samples])
    return {"rule": errors(samples, rule), "best_constant": errors(samples, const)}


def main(argv=None) -> int:
    from bench.panoramas import DEFAULT_HDRI_DIR, read_manifest
    from core.capture import highlights
    from core.sim.camera_curves import add_curve_argument

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hdri-dir", default=str(DEFAULT_HDRI_DIR))
    p.add_argument("--splits", default="dev,test,extra", help="comma-separated MANIFEST splits (default: every "
                   "indoor room)")
    p.add_argument("--fit", action="store_true", help="refit the coefficients on the splits' blobs and print them")
    p.add_argument("-o", "--out", default=None)
    p.add_argument("--colour-sweep", action="store_true", help="also sweep the spill colour's settings on dev")
    p.add_argument("--colour-cv", action="store_true", help="also choose the spill colour's settings leave-one-room-"
                   "out over the splits' real blobs (colour_cv)")
    p.add_argument("--samples-out", default=None, help="also write every blob's features and truth (JSON)")
    add_curve_argument(p, allow_all=False)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    hdri = Path(args.hdri_dir)
    rows = read_manifest(hdri)
    by_split = {}
    for split in sorted(set(args.splits.split(",")) | ({"dev"})):
        files = sorted(r["filename"] for r in rows if r.get("split") == split and (hdri / r["filename"]).is_file())
        by_split[split] = [s for f in files for s in blob_samples(hdri / f, args.curve)]
        print(f"[clip_rule] {split}: {len(files)} panoramas, {len(by_split[split])} blobs", file=sys.stderr)
    lamps = [
        s
        for f in sorted(r["filename"] for r in rows if r.get("split") == "dev" and (hdri / r["filename"]).is_file())
        for s in synthetic_lamp_samples(hdri / f, args.curve)
    ]
    print(f"[clip_rule] dev: {len(lamps)} synthetic lamps", file=sys.stderr)
    dev = by_split["dev"]
    fitted_on = [s for split in args.splits.split(",") for s in by_split[split]]
    # fitted on real blobs only: fitted to the synthetic lamps too, the linear rule got worse on
    # real blobs (0.29 -> 0.86 stops on dev) without getting good on lamps (1.45 stops)
    coefficients = fit(fitted_on) if args.fit else list(highlights.RULE_COEFFICIENTS)
    constant = fit(fitted_on, constant_only=True)[0]
    report = {"coefficients": coefficients, "fitted_now": bool(args.fit), "fitted_on_splits": args.splits,
              "curve": args.curve,
              "best_constant_stops": constant, "views_per_panorama": VIEWS_PER_PANORAMA, "splits": {}}
    if args.fit:
        report["leave_one_panorama_out"] = leave_one_panorama_out(fitted_on)
    report["dev_synthetic_lamps"] = evaluate(lamps, coefficients, constant)
    for split in args.splits.split(","):
        report["splits"][split] = evaluate(by_split[split], coefficients, constant)
    if args.colour_sweep:
        report["dev_colour_sweep"] = {"real": colour_sweep(dev), "synthetic_lamps": colour_sweep(lamps)}
    if args.colour_cv:
        report["colour_leave_one_room_out"] = colour_cv(fitted_on)
    if args.samples_out:
        Path(args.samples_out).write_text(
            json.dumps({"dev": dev, "lamps": lamps, **{k: v for k, v in by_split.items() if k != "dev"}})
        )
    text = json.dumps(report, indent=1)
    if args.out:
        Path(args.out).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
