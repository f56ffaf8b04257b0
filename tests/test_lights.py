"""Dominant light + ambient SH split."""
import json
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from core.conventions import equirect_directions
from core.envmap import irradiance, solid_angles
from core.lights import DominantLightConfig, extract_dominant_light
from core.sh import project_sh, sh_irradiance

H = 64
BACKGROUND = torch.tensor([0.2, 0.25, 0.3], dtype=torch.float64)
SQUARE = torch.tensor([800.0, 600.0, 400.0], dtype=torch.float64)


def map_with_square(rows, cols, value=SQUARE, background=BACKGROUND, height=H):
    e = background.expand(height, 2 * height, 3).clone()
    for r in rows:
        for c in cols:
            e[r, c % (2 * height)] = value
    return e


def square_truth(rows, cols, height=H):
    """Solid-angle-weighted mean direction and solid angle of the square's pixels."""
    d = equirect_directions(height, dtype=torch.float64)
    w = solid_angles(height, dtype=torch.float64)
    idx_r = torch.tensor([r for r in rows for _ in cols])
    idx_c = torch.tensor([c % (2 * height) for _ in rows for c in cols])
    mean = (d[idx_r, idx_c] * w[idx_r, idx_c, None]).sum(0)
    return mean / mean.norm(), float(w[idx_r, idx_c].sum())


def angle_deg(a, b):
    return math.degrees(math.acos(max(-1.0, min(1.0, float(a @ b / (a.norm() * b.norm()))))))


def test_small_bright_square_gives_its_direction_and_intensity():
    rows, cols = range(20, 24), range(70, 74)
    light = extract_dominant_light(map_with_square(rows, cols))
    direction, sr = square_truth(rows, cols)
    assert light.found and light.reason == ""
    assert angle_deg(light.direction.double(), direction) < 2.0
    assert light.solid_angle == pytest.approx(sr, rel=1e-6)
    assert torch.allclose(light.intensity_rgb.double(), SQUARE * sr, rtol=0.03)


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 28), st.integers(0, 63))
def test_square_anywhere_including_the_seam(row, col):
    rows, cols = range(row, row + 3), range(col - 1, col + 2)  # wraps when col is 0 or 63
    height = 32
    light = extract_dominant_light(map_with_square(rows, cols, height=height))
    direction, sr = square_truth(rows, cols, height=height)
    assert light.found
    assert angle_deg(light.direction.double(), direction) < 2.0
    assert torch.allclose(light.intensity_rgb.double(), SQUARE * sr, rtol=0.03)


def test_light_at_the_pole_is_found_whole_across_the_pole():
    e = map_with_square(range(0, 2), range(0, 2 * H))  # a polar cap two rows high
    light = extract_dominant_light(e, DominantLightConfig(max_solid_angle=1.0))
    assert light.found
    assert angle_deg(light.direction.double(), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)) < 0.5


def test_brighter_of_two_lights_wins():
    e = map_with_square(range(20, 23), range(10, 13))
    e[40:43, 100:103] = SQUARE * 3
    light = extract_dominant_light(e)
    direction, _ = square_truth(range(40, 43), range(100, 103))
    assert angle_deg(light.direction.double(), direction) < 2.0


def test_ambient_sh_excludes_the_light_and_split_reproduces_irradiance():
    rows, cols = range(20, 24), range(70, 74)
    e = map_with_square(rows, cols)
    light = extract_dominant_light(e)
    background_sh = project_sh(BACKGROUND.expand(H, 2 * H, 3).contiguous())
    assert torch.allclose(light.ambient_sh.double(), background_sh, atol=1e-3 * float(BACKGROUND.max()))
    # a directional light of the reported intensity + ambient SH light a diffuse surface like the map
    normals = torch.nn.functional.normalize(torch.randn(16, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64), dim=-1)
    split = sh_irradiance(light.ambient_sh.double(), normals) + (normals @ light.direction.double()).clamp_min(0)[:, None] * light.intensity_rgb.double()
    full = irradiance(e, normals)
    assert torch.allclose(split, full, rtol=0.03, atol=0.02 * float(full.max()))


def test_uniform_map_has_no_dominant_light():
    e = torch.full((16, 32, 3), 0.7)
    light = extract_dominant_light(e)
    assert not light.found and "no dominant light" in light.reason
    assert float(light.intensity_rgb.abs().sum()) == 0.0 and light.solid_angle == 0.0
    assert torch.isfinite(light.direction).all() and torch.isfinite(light.ambient_sh).all()
    assert torch.allclose(light.ambient_sh, project_sh(e))


def test_low_contrast_bump_is_not_a_light():
    e = map_with_square(range(20, 23), range(10, 13), value=BACKGROUND * 3)  # above the 0.5 x peak threshold, below min_contrast 4
    light = extract_dominant_light(e)
    assert not light.found and "min_contrast" in light.reason


@pytest.mark.parametrize("height", [1, 2, 8])
def test_all_zero_map(height):
    light = extract_dominant_light(torch.zeros(height, 2 * height, 3))
    assert not light.found and "zero" in light.reason
    for t in (light.direction, light.intensity_rgb, light.ambient_sh):
        assert torch.isfinite(t).all()
    assert float(light.ambient_sh.abs().sum()) == 0.0


def test_non_finite_and_negative_radiance_is_ignored():
    e = map_with_square(range(20, 23), range(10, 13))
    e[5, 5] = float("nan")
    e[6, 6] = float("inf")
    e[7, 7] = -1e9
    light = extract_dominant_light(e)
    direction, _ = square_truth(range(20, 23), range(10, 13))
    assert light.found and angle_deg(light.direction.double(), direction) < 2.0
    assert torch.isfinite(light.ambient_sh).all()


def test_huge_dynamic_range():
    e = map_with_square(range(30, 32), range(60, 62), value=torch.full((3,), 1e6, dtype=torch.float64), background=torch.full((3,), 1e-6, dtype=torch.float64)).float()
    light = extract_dominant_light(e)
    _, sr = square_truth(range(30, 32), range(60, 62))
    assert light.found and torch.isfinite(light.ambient_sh).all()
    assert float(light.intensity_rgb[0]) == pytest.approx(1e6 * sr, rel=1e-3)


def test_to_dict_is_json_with_arcore_layout():
    light = extract_dominant_light(map_with_square(range(20, 23), range(10, 13)))
    payload = json.loads(json.dumps(light.to_dict()))
    assert len(payload["ambient_sh_arcore27"]) == 27 and len(payload["direction"]) == 3


def test_config_validation():
    with pytest.raises(ValueError, match="threshold_fraction"):
        DominantLightConfig(threshold_fraction=1.5)
