"""Emitters: small bright sources as explicit spheres (core.fields.components.emitters,
core.engine.emitter_detection)."""

from __future__ import annotations

import math

import pytest
import torch

from core.capture.load import capture_from_arrays
from core.engine.emitter_detection import find_emitters
from core.envmap import integrate
from core.exposure import luminance
from core.fields import FieldConfig, SceneBounds, build_field
from core.fields.stored.artefact import LightFieldArtefact, save_artefact

BOX = SceneBounds((-3.0, -3.0, -3.0), (3.0, 3.0, 3.0), 0.0, 2.0)


def field_with_lamp(intensity, knots=1, uses_time=False, centre=(1.5, 0.0, 0.0), radius=0.02):
    cfg = FieldConfig(kind="mlp", uses_time=uses_time, emitter_count=1, emitter_knots=knots)
    torch.manual_seed(0)
    field = build_field(cfg, BOX).eval()
    field.emitters.set_sources(torch.tensor([centre]), torch.tensor([radius]),
                               torch.tensor(intensity, dtype=torch.float32).reshape(1, knots, 3))
    return field


def lamp_energy(field, x, t, height):
    """Integral of the env map at x minus the same field with the lamp dark."""
    with torch.no_grad():
        lit = field.envmaps(torch.tensor([x]), t, height)[0]
        saved = field.emitters.log_intensity.clone()
        field.emitters.log_intensity.fill_(-60.0)
        dark = field.envmaps(torch.tensor([x]), t, height)[0]
        field.emitters.log_intensity.copy_(saved)
    return integrate(lit - dark), lit


@pytest.mark.parametrize("height", [8, 32, 128])
def test_a_lamp_has_its_energy_at_every_map_resolution(height):
    """I / d^2 whatever the map's size, even where the lamp is far narrower than a pixel."""
    field = field_with_lamp([2.0, 1.0, 0.5])
    energy, lit = lamp_energy(field, (0.0, 0.0, 0.0), None, height)
    expected = torch.tensor([2.0, 1.0, 0.5]) / 1.5 ** 2 * 0.99  # the gate starts at sigmoid(4.6)
    assert torch.allclose(energy.double(), expected.double(), rtol=0.04), (energy, expected)
    # the brightest pixel looks towards the lamp (+x)
    from core.conventions import equirect_directions

    peak = luminance(lit).flatten().argmax()
    assert float(equirect_directions(height).reshape(-1, 3)[peak] @ torch.tensor([1.0, 0.0, 0.0])) > math.cos(
        2.5 * math.pi / height
    )


def test_inside_a_lamp_and_at_extreme_intensity_the_answer_stays_finite():
    field = field_with_lamp([1e30, 1e30, 1e30])
    with torch.no_grad():
        inside = field.envmaps(torch.tensor([[1.5, 0.0, 0.0]]), None, 16)[0]
        rows = field(
            torch.tensor([[1.5, 0.0, 0.0], [0.0, 0.0, 0.0]]), None, torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
        )
    assert torch.isfinite(inside).all() and (inside > 0).all()
    with torch.no_grad():
        field.emitters.log_intensity.fill_(1e4)  # a corrupt or runaway intensity stays finite too
        far = field.envmaps(torch.tensor([[0.0, 0.0, 0.0]]), None, 16)[0]
    assert torch.isfinite(far).all()
    assert torch.isfinite(rows).all() and float(rows.max()) <= math.exp(field.config.log_radiance_max) * 1.0001


def test_a_lamp_follows_its_intensity_knots_over_time():
    field = field_with_lamp([[1.0] * 3, [0.0] * 3, [1.0] * 3], knots=3, uses_time=True)
    on, _ = lamp_energy(field, (0.0, 0.0, 0.0), torch.tensor([0.0]), 32)
    off, _ = lamp_energy(field, (0.0, 0.0, 0.0), torch.tensor([1.0]), 32)
    half, _ = lamp_energy(field, (0.0, 0.0, 0.0), torch.tensor([0.5]), 32)
    assert float(off.max()) < 1e-6 * float(on.min())
    assert float(half.mean()) == pytest.approx(0.5 * float(on.mean()), rel=0.02)


def test_a_saved_field_with_emitters_loads_with_the_same_answer(tmp_path):
    field = field_with_lamp([3.0, 2.0, 1.0])
    with torch.no_grad():
        field.emitters.gate[0, 0, :4].fill_(-5.0)  # occluded in the low-x half of the box
        before = field.envmaps(torch.tensor([[0.0, 0.0, 0.0], [-2.0, 0.0, 0.0]]), None, 16)
    save_artefact(tmp_path / "a", field)
    art = LightFieldArtefact.load(tmp_path / "a")
    after, _ = art.envmaps(torch.tensor([[0.0, 0.0, 0.0], [-2.0, 0.0, 0.0]]), None, 16)
    assert torch.allclose(before, after.to(before.dtype), rtol=1e-5, atol=1e-7)
    # the gate dims the lamp where it was closed
    assert float(integrate(after[1]).sum()) < float(integrate(after[0]).sum())


def test_a_small_lamp_is_found_placed_and_measured_and_a_window_is_left_to_the_network():
    """Linear frames (static camera, depth 2 m): a 3x3-pixel lamp of radiance 100 on in frames
    0-1 and off in 2-3, and a 20x20-pixel bright window (too wide for an emitter) with a brighter
    spot (not cut out of it as a lamp)."""
    T, H, W = 4, 48, 64
    linear = torch.full((T, H, W, 3), 0.05)
    linear[:2, 10:13, 40:43] = 100.0
    linear[:, 25:45, 5:25] = 50.0
    linear[:, 30:32, 10:12] = 120.0  # a brighter spot in the window is not a lamp either
    cap = capture_from_arrays(torch.full((T, H, W, 3), 0.2), torch.full((T, H, W), 2.0), fps=2.0)
    bounds = SceneBounds((-3.0, -3.0, -3.0), (3.0, 3.0, 3.0), float(cap.times[0]), float(cap.times[-1]))
    found = find_emitters(cap, lambda i: linear[i], count=4, contrast=50.0, max_radius=0.3, bounds=bounds, knots=T)
    assert found is not None and found.count == 1
    cam = cap.camera(0)
    centre = cam.unproject(torch.full((H, W), 2.0, dtype=torch.float64))[11, 41]
    # along the blob's mean ray at its nearest pixel's distance (the lamp is the near surface)
    assert torch.allclose(found.centres[0].double(), centre, atol=0.03)
    k = cam.intrinsics
    pixel_area = 2.0 ** 2 / (k.fx * k.fy)  # near the optical axis
    assert float(found.intensity[0, 0, 0]) == pytest.approx(100.0 * 9 * pixel_area, rel=0.1)
    # off in view: what the footprint shows (the 0.05 background), not the last value held
    assert float(found.intensity[0, 3, 0]) < 0.01 * float(found.intensity[0, 0, 0])
    assert float(found.radii[0]) == pytest.approx(math.sqrt(9 * pixel_area / math.pi), rel=0.1)


def test_no_bright_blob_no_emitters():
    cap = capture_from_arrays(torch.full((2, 24, 32, 3), 0.3), torch.full((2, 24, 32), 2.0))
    bounds = SceneBounds((-3.0, -3.0, -3.0), (3.0, 3.0, 3.0), 0.0, 1.0)
    assert find_emitters(cap, lambda i: torch.full((24, 32, 3), 0.3), count=4, contrast=50.0, max_radius=0.3,
                         bounds=bounds, knots=2) is None


def test_one_lamp_split_into_two_sources_by_depth_noise_does_not_count_twice():
    """The same 3x3 blob at 2.0 m in frame 0 and 2.6 m in frame 1 (noisy depth): two sources,
    but each frame's light is taken once."""
    T, H, W = 2, 48, 64
    linear = torch.full((T, H, W, 3), 0.05)
    linear[:, 10:13, 40:43] = 100.0
    depth = torch.full((T, H, W), 2.0)
    depth[1, 10:13, 40:43] = 2.6
    cap = capture_from_arrays(torch.full((T, H, W, 3), 0.2), depth, fps=2.0)
    bounds = SceneBounds((-3.0, -3.0, -3.0), (3.0, 3.0, 3.0), float(cap.times[0]), float(cap.times[-1]))
    found = find_emitters(cap, lambda i: linear[i], count=4, contrast=50.0, max_radius=0.3, bounds=bounds, knots=T)
    assert found is not None and found.count == 2
    for frame in range(T):
        shares = sorted(float(found.intensity[k, frame, 0]) for k in range(2))
        assert shares[0] < 0.05 * shares[1], (frame, shares)


def test_a_lamp_whose_depth_blends_with_the_wall_behind_is_placed_at_its_near_surface():
    """A downsampled depth map mixes a small lamp (1.5 m) with the wall (3 m) at its edge pixels:
    the source sits at the lamp, not in between."""
    T, H, W = 1, 48, 64
    linear = torch.full((T, H, W, 3), 0.05)
    linear[0, 20:24, 30:34] = 80.0
    depth = torch.full((T, H, W), 3.0)
    depth[0, 21:23, 31:33] = 1.5
    depth[0, 20:24, 30:34] = torch.where(depth[0, 20:24, 30:34] == 1.5, 1.5, 2.25)  # blended edge
    cap = capture_from_arrays(torch.full((T, H, W, 3), 0.2), depth)
    bounds = SceneBounds((-4.0, -4.0, -4.0), (4.0, 4.0, 4.0), 0.0, 0.0)
    found = find_emitters(cap, lambda i: linear[i], count=4, contrast=50.0, max_radius=0.3, bounds=bounds, knots=1)
    assert found is not None and found.count == 1
    distance = float((found.centres[0].double() - cap.camera(0).position).norm())
    assert distance == pytest.approx(1.5, abs=0.05)


def test_a_sparkly_frame_keeps_its_brightest_lamps():
    """40 one-pixel sparkles of rising radiance (a bounded number of blobs is looked at per
    frame): the 4 sources kept are the 4 brightest."""
    H, W = 48, 64
    linear = torch.full((H, W, 3), 0.05)
    spots = [(4 + 5 * (k // 10), 4 + 6 * (k % 10)) for k in range(40)]
    for k, (r, c) in enumerate(spots):
        linear[r, c] = 10.0 * 1.3 ** k  # far apart in energy, whatever each pixel's footprint
    cap = capture_from_arrays(torch.full((1, H, W, 3), 0.2), torch.full((1, H, W), 2.0))
    bounds = SceneBounds((-3.0, -3.0, -3.0), (3.0, 3.0, 3.0), 0.0, 0.0)
    found = find_emitters(cap, lambda i: linear, count=4, contrast=50.0, max_radius=0.3, bounds=bounds, knots=1)
    assert found is not None and found.count == 4
    points = cap.camera(0).unproject(torch.full((H, W), 2.0, dtype=torch.float64))
    expected = torch.stack([points[r, c] for r, c in spots[-4:]])
    for centre in found.centres.double():
        assert float((expected - centre).norm(dim=-1).min()) < 0.05
