"""The clip rule (core.capture.highlights): synthetic lamps with known radiance, exposure
brackets across frames, and degenerate frames."""
from __future__ import annotations

import math

import pytest
import torch

from core.camera import Intrinsics
from core.capture.highlights import (
    MAX_BOOST_STOPS,
    clipped_mask,
    find_blobs,
    linearise_highlights,
    recover_from_exposures,
)
from core.conventions import inverse_tonemap
from core.metrics import angular_error_deg

INTR = Intrinsics.from_hfov(128, 96, 60.0)
SYNTHETIC_LAMP_MAX_ERROR_STOPS = 1.25  # stated in docs/highlights.md (lamps up to 64x white, <= 3 px)


def lamp_scene(
    radiance: float, radius: float, wall: float = 0.05, glare: float = 0.02, sigma: float = 1.0
) -> torch.Tensor:
    """Linear [96, 128] image: a disc lamp on a wall, through a lens PSF (Gaussian core of
    `sigma` px plus a `glare` share of energy in an exponential tail of 4 px)."""
    H, W = 96, 128
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    img = torch.full((H, W), wall, dtype=torch.float64)
    img[((yy - 40) ** 2 + (xx - 60) ** 2).sqrt() <= radius] = radiance
    k = torch.arange(-15, 16, dtype=torch.float64)
    ky, kx = torch.meshgrid(k, k, indexing="ij")
    kr = (ky**2 + kx**2).sqrt()
    psf = (1 - glare) * torch.exp(-(kr**2) / (2 * sigma**2)) / (2 * math.pi * sigma**2) + glare * torch.exp(
        -kr / 4.0
    ) / (2 * math.pi * 16)
    psf = psf / psf.sum()
    padded = torch.nn.functional.pad(img[None, None], (15,) * 4, mode="replicate")
    return torch.nn.functional.conv2d(padded, psf[None, None])[0, 0]


def to_ldr(linear: torch.Tensor) -> torch.Tensor:
    rgb = linear[..., None].expand(*linear.shape, 3)
    return (torch.round(rgb.clamp(0, 1) ** (1 / 2.4) * 255) / 255).float()


@pytest.mark.parametrize("radiance,radius", [(4.0, 1.5), (4.0, 3.0), (16.0, 1.5), (16.0, 3.0), (64.0, 1.5)])
def test_synthetic_lamp_with_halo_is_estimated_within_stated_error(radiance, radius):
    true = lamp_scene(radiance, radius)
    ldr = to_ldr(true)
    clip = clipped_mask(ldr)
    assert clip.any()
    est = linearise_highlights(ldr[None], INTR, compare_frames=True)[0].double()
    true_mean = float(true[clip].mean())
    est_mean = float(est[clip][:, 1].mean())
    err = abs(math.log2(est_mean / true_mean))
    assert err <= SYNTHETIC_LAMP_MAX_ERROR_STOPS, (true_mean, est_mean)
    assert est_mean > 1.5  # a lamp is never taken for white paper


def test_very_bright_extended_lamp_is_underestimated_known_limit():
    """The rule is fitted on real dev panoramas, whose clipped blobs are at most ~5 stops over
    white: a 64x lamp of radius 6 px (~5 stops over white on average over its blob) is
    underestimated by more than 2 stops (docs/highlights.md). If this starts failing the rule
    got better here: update the docs."""
    true = lamp_scene(64.0, 6.0)
    ldr = to_ldr(true)
    clip = clipped_mask(ldr)
    est = float(linearise_highlights(ldr[None], INTR, True)[0].double()[clip][:, 1].mean())
    assert 1.5 < est < float(true[clip].mean()) / 4.0


def test_brighter_lamp_is_estimated_brighter():
    ests = []
    for radiance in (4.0, 64.0):
        ldr = to_ldr(lamp_scene(radiance, 3.0))
        clip = clipped_mask(ldr)
        ests.append(float(linearise_highlights(ldr[None], INTR, True)[0][clip].mean()))
    assert ests[1] > 1.5 * ests[0]


def test_unclipped_frames_are_just_linearised():
    ldr = torch.rand(2, 16, 20, 3) * 0.9
    assert torch.equal(linearise_highlights(ldr, INTR, True), inverse_tonemap(ldr))


def test_exposure_bracket_recovers_the_clipped_lamp():
    """Frame 0 clips the lamp; frame 1 is 3 stops darker and sees it unclipped: the recovered
    radiance of frame 0's lamp is the true one (8-bit quantisation aside)."""
    true = lamp_scene(6.0, 4.0, wall=0.4, glare=0.0)
    frames = torch.stack([to_ldr(true), to_ldr(true / 8.0)])
    lin = inverse_tonemap(frames)
    clip = clipped_mask(frames)
    rec = recover_from_exposures(lin, clip)
    centre = (40, 60)
    assert clip[0][centre] and not clip[1][centre]
    assert float(rec[0][centre][1]) == pytest.approx(6.0, rel=0.1)
    # through the full rule too (static camera): exposure evidence wins over the blob rule
    full = linearise_highlights(frames, INTR, compare_frames=True)
    assert float(full[0][centre][1]) == pytest.approx(6.0, rel=0.1)


def test_a_light_switching_off_is_not_mistaken_for_an_exposure_change():
    """Frame 1 has the lamp off (darker than white there): it must not pull frame 0's lamp down."""
    on = lamp_scene(8.0, 4.0, wall=0.2, glare=0.0)
    off = lamp_scene(0.2, 4.0, wall=0.2, glare=0.0)
    frames = torch.stack([to_ldr(on), to_ldr(off)])
    out = linearise_highlights(frames, INTR, compare_frames=True)
    assert float(out[0][40, 60][1]) > 1.0


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_degenerate_frames_stay_finite_and_bounded(value):
    ldr = torch.full((1, 24, 32, 3), value)
    out = linearise_highlights(ldr, INTR, True)
    assert torch.isfinite(out).all()
    assert float(out.max()) <= 2.0**MAX_BOOST_STOPS + 1e-3


def test_blobs_are_eight_connected_and_counted():
    lin = torch.full((10, 10, 3), 0.1).numpy()
    clip = torch.zeros(10, 10, dtype=torch.bool)
    clip[2, 2] = clip[3, 3] = True  # diagonal neighbours: one blob
    clip[7, 7] = True
    labels, blobs = find_blobs(lin, clip.numpy(), 1e-4)
    assert len(blobs) == 2 and sorted(b.area_px for b in blobs) == [1, 2]


def test_prior_compares_frames_only_for_a_static_camera_under_static_lighting():
    """Through the reprojection prior: with the engine's 'lighting changes' decision the
    darker frame is not used as an exposure bracket (its lamp may simply be dimmer)."""
    from core.capture.load import capture_from_arrays
    from core.priors.reprojection import linear_frames

    true = lamp_scene(6.0, 4.0, wall=0.4, glare=0.0)
    frames = torch.stack([to_ldr(true), to_ldr(true / 8.0)])
    cap = capture_from_arrays(frames, None)
    static = linear_frames(cap, lighting_changes=False)
    changing = linear_frames(cap, lighting_changes=True)
    assert float(static[0, 40, 60, 1]) == pytest.approx(6.0, rel=0.1)
    assert float(changing[0, 40, 60, 1]) != pytest.approx(6.0, rel=0.1)


def colour_angle(a: torch.Tensor, b: torch.Tensor) -> float:
    return angular_error_deg(a.double()[None], b.double()[None])


def test_white_hot_lamp_takes_its_halos_colour():
    """Every channel of a warm lamp clips, so the blob itself says "white"; its halo's excess
    over the wall carries the lamp's colour (Blob.spill_colour). The estimate is closer to the
    lamp's colour than white is (not equal: the grey wall's light is in the halo too),
    and no channel of a recoloured pixel falls below white."""
    tint = torch.tensor([1.0, 0.75, 0.5], dtype=torch.float64)
    lamp = lamp_scene(16.0, 2.0, wall=0.0, glare=0.05)
    true = lamp[..., None] * tint + 0.05  # a grey wall lit by the room, plus the lamp's light
    ldr = (torch.round(true.clamp(0, 1) ** (1 / 2.4) * 255) / 255).float()
    hot = ldr.amin(-1) >= 0.99
    assert hot.sum() > 4
    est = linearise_highlights(ldr[None], INTR, compare_frames=False)[0].double()
    colour = est[hot].mean(0)
    assert colour_angle(colour, tint) < 0.6 * colour_angle(torch.ones(3), tint)
    assert bool((est[hot] >= inverse_tonemap(torch.tensor(0.99)).item() - 1e-6).all())


def test_the_spill_colour_settings_reach_the_jobs_linearisation():
    """The reprojection prior's `spill_colour` setting (what the benches choose per fold) decides
    the white-hot pixels' colour: the shipped settings give the warm lamp its halo's colour, an
    excess no spill reaches leaves it white; the prior reports the settings it used."""
    from core.capture.highlights import SPILL_COLOUR
    from core.capture.load import capture_from_arrays
    from core.priors.reprojection import ReprojectionPrior, linear_frames

    tint = torch.tensor([1.0, 0.75, 0.5], dtype=torch.float64)
    true = lamp_scene(16.0, 2.0, wall=0.0, glare=0.05)[..., None] * tint + 0.05
    ldr = (torch.round(true.clamp(0, 1) ** (1 / 2.4) * 255) / 255).float()
    hot = ldr.amin(-1) >= 0.99
    cap = capture_from_arrays(ldr[None], None)
    shipped = linear_frames(cap)[0][hot].double().mean(0)
    white = linear_frames(cap, spill_colour=(1e9, 1.0))[0][hot].double().mean(0)
    assert colour_angle(shipped, tint) < 0.6 * colour_angle(torch.ones(3), tint)
    assert colour_angle(white, torch.ones(3)) < 1e-6
    assert ReprojectionPrior().describe()["spill_colour"] == list(SPILL_COLOUR)
    assert ReprojectionPrior(spill_colour=[1e9, 1.0]).describe()["spill_colour"] == [1e9, 1.0]


def test_lamp_without_halo_stays_white():
    """A hard-edged lamp on a uniform wall: no excess in its halo, so no colour is invented."""
    H, W = 96, 128
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    true = torch.full((H, W, 3), 0.05, dtype=torch.float64)
    true[((yy - 40) ** 2 + (xx - 60) ** 2) <= 9] = torch.tensor([16.0, 8.0, 4.0], dtype=torch.float64)
    ldr = (torch.round(true.clamp(0, 1) ** (1 / 2.4) * 255) / 255).float()
    labels, blobs = find_blobs(inverse_tonemap(ldr).numpy(), clipped_mask(ldr).numpy(), 1e-4)
    assert len(blobs) == 1 and blobs[0].spill_colour() is None
    est = linearise_highlights(ldr[None], INTR, compare_frames=False)[0]
    hot = clipped_mask(ldr)
    assert torch.allclose(est[hot][:, 0], est[hot][:, 2])


def dimming_lamp_clip(scales=(1.0, 0.8, 0.6, 0.4)) -> torch.Tensor:
    """LDR frames [T, 96, 128, 3] of a static camera: a 16x-white lamp dimming by `scales`, on a
    wall lit by it (an inverse-square pool around it) and by a fixed dim fill."""
    yy, xx = torch.meshgrid(
        torch.arange(96, dtype=torch.float64), torch.arange(128, dtype=torch.float64), indexing="ij"
    )
    pool = 0.6 / (1.0 + (((yy - 40) ** 2 + (xx - 60) ** 2) / 36.0))
    return torch.stack([to_ldr(lamp_scene(16.0 * s, 3.0, wall=0.05) + s * pool) for s in scales])


def test_a_dimming_lamp_seen_by_a_static_camera_is_estimated_dimming():
    """The rule alone reads the lamp's own darker surround as a sign of a brighter source, so
    frame by frame a dimming lamp came out brightening. Followed over the frames
    (static_camera), its level is one and its changes are its surround's."""
    scales = (1.0, 0.8, 0.6, 0.4)
    frames = dimming_lamp_clip(scales)
    core = clipped_mask(frames).all(0)
    assert core[40, 60] and int(core.sum()) >= 9  # clipped in every frame
    followed = linearise_highlights(frames, INTR, compare_frames=False, static_camera=True)
    per_frame = linearise_highlights(frames, INTR, compare_frames=False)
    lamp = [float(followed[t][core][:, 1].mean()) for t in range(len(scales))]
    rule = [float(per_frame[t][core][:, 1].mean()) for t in range(len(scales))]
    assert all(a > b for a, b in zip(lamp, lamp[1:])), lamp
    # the last frame is 0.4x the first: estimated within half a stop of it
    assert abs(math.log2(lamp[-1] / lamp[0]) - math.log2(scales[-1])) < 0.5, lamp
    assert rule[-1] >= rule[0], rule  # what the rule alone does (the failure this fixes)
    # a single frame keeps the rule's own estimate, as every frame of a moving camera does (per_frame)
    assert torch.equal(linearise_highlights(frames[:1], INTR, False, static_camera=True), per_frame[:1])


def test_source_tracks_follow_overlapping_blobs_and_start_new_ones():
    import numpy as np

    from core.capture.highlights import source_tracks

    a = np.zeros((12, 12), dtype=np.int32)
    a[2:5, 2:5] = 1  # a source
    b = np.zeros_like(a)
    b[3:5, 3:5] = 2  # the same source, shrunk (and listed second)
    b[8:10, 8:10] = 1  # a new one
    c = np.zeros_like(a)
    c[8:10, 9:11] = 1  # the new one, shifted by one pixel (half overlap)
    tracks = source_tracks([a, b, c], [1, 2, 1])
    assert sorted(tracks) == [[(0, 0), (1, 1)], [(1, 0), (2, 0)]]
    # below the overlap share a blob starts its own track
    assert len(source_tracks([a, c], [1, 1])) == 2
