"""Cube maps: GL face order/orientation and round trips with equirect maps."""
import math

import pytest
import torch
from hypothesis import given, settings, strategies as st

from core.cubemap import (
    CUBE_FACES,
    CubemapError,
    cubemap_directions,
    cubemap_to_equirect,
    direction_to_cube_texel,
    equirect_to_cubemap,
    sample_cubemap,
)
from core.envmap import envmap_from_function, integrate


def smooth(d):
    x, y, z = d.unbind(-1)
    return torch.stack((1.0 + 0.5 * x + 0.2 * y * z, 1.0 + 0.3 * y - 0.2 * x * z, 1.2 - 0.4 * z + 0.1 * x * x), dim=-1)


AXES = {"+X": (1, 0, 0), "-X": (-1, 0, 0), "+Y": (0, 1, 0), "-Y": (0, -1, 0), "+Z": (0, 0, 1), "-Z": (0, 0, -1)}


def test_face_order_and_centres():
    assert CUBE_FACES == ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
    d = cubemap_directions(2, dtype=torch.float64)  # the face centre is the corner shared by the 4 texels
    for f, name in enumerate(CUBE_FACES):
        centre = d[f].reshape(-1, 3).mean(0)
        assert torch.allclose(centre / centre.norm(), torch.tensor(AXES[name], dtype=torch.float64), atol=1e-12)


# (face, axis the image's +column points along, axis the image's +row points along): GL spec table
GL_ORIENTATION = [
    ("+X", (0, 0, -1), (0, -1, 0)),
    ("-X", (0, 0, 1), (0, -1, 0)),
    ("+Y", (1, 0, 0), (0, 0, 1)),
    ("-Y", (1, 0, 0), (0, 0, -1)),
    ("+Z", (1, 0, 0), (0, -1, 0)),
    ("-Z", (-1, 0, 0), (0, -1, 0)),
]


@pytest.mark.parametrize("name,right,down", GL_ORIENTATION)
def test_face_orientation_is_the_gl_convention(name, right, down):
    size = 8
    d = cubemap_directions(size, dtype=torch.float64)[CUBE_FACES.index(name)]
    right = torch.tensor(right, dtype=torch.float64)
    down = torch.tensor(down, dtype=torch.float64)
    assert ((d[:, 1:] - d[:, :-1]) @ right > 0).all()  # moving right along a row
    assert ((d[1:, :] - d[:-1, :]) @ down > 0).all()  # moving down a column


def test_texel_centres_round_trip_to_their_texels():
    size = 5
    d = cubemap_directions(size, dtype=torch.float64)
    face, row, col = direction_to_cube_texel(d, size)
    f_exp, r_exp, c_exp = torch.meshgrid(torch.arange(6), torch.arange(size), torch.arange(size), indexing="ij")
    assert torch.equal(face, f_exp)
    assert torch.allclose(row, r_exp.double(), atol=1e-9) and torch.allclose(col, c_exp.double(), atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(lambda v: max(map(abs, v)) > 1e-3))
def test_any_direction_lands_on_a_texel_that_looks_back_along_it(v):
    """Exact texel coordinates within the face, including edges and corners."""
    size = 16
    d = torch.tensor(v, dtype=torch.float64)
    face, row, col = direction_to_cube_texel(d, size)
    assert -0.5 - 1e-9 <= float(row) <= size - 0.5 + 1e-9 and -0.5 - 1e-9 <= float(col) <= size - 0.5 + 1e-9
    # rebuild the direction through cubemap_directions' own formula on a 1-texel-per-unit grid
    tc = (float(row) + 0.5) / size * 2 - 1
    sc = (float(col) + 0.5) / size * 2 - 1
    table = [(1, -tc, -sc), (-1, -tc, sc), (sc, 1, tc), (sc, -1, -tc), (sc, -tc, 1), (-sc, -tc, -1)]
    back = torch.tensor(table[int(face)], dtype=torch.float64)
    assert torch.allclose(back / back.norm(), d / d.norm(), atol=1e-9)


def test_equirect_to_cubemap_matches_the_function():
    e = envmap_from_function(smooth, 128, dtype=torch.float64)
    faces = equirect_to_cubemap(e, 32)
    assert faces.shape == (6, 32, 32, 3)
    assert (faces - smooth(cubemap_directions(32, dtype=torch.float64))).abs().max() < 0.02


def test_bright_lobe_lands_on_its_face():
    e = envmap_from_function(lambda d: (d[..., 1]).clamp_min(0) ** 50, 64)
    faces = equirect_to_cubemap(e, 16)
    per_face = faces[..., 0].sum(dim=(1, 2))
    assert int(per_face.argmax()) == CUBE_FACES.index("+Y")


def test_cube_equirect_cube_round_trip_on_smooth_maps():
    size = 32
    faces = smooth(cubemap_directions(size, dtype=torch.float64))
    e = cubemap_to_equirect(faces, 96)
    assert (e - envmap_from_function(smooth, 96, dtype=torch.float64)).abs().max() < 0.03
    back = equirect_to_cubemap(e, size)
    assert (back - faces).abs().max() < 0.03
    assert (back - faces).abs().mean() < 3e-3


def test_equirect_cube_equirect_round_trip_on_smooth_maps():
    e = envmap_from_function(smooth, 64, dtype=torch.float64)
    back = cubemap_to_equirect(equirect_to_cubemap(e, 48), 64)
    assert (back - e).abs().max() < 0.03
    assert torch.allclose(integrate(back), integrate(e), rtol=2e-3)


def test_coarse_equirect_from_fine_cube_integrates_the_faces():
    """Downsampling path: the integral of a fine cube's content survives."""
    e = envmap_from_function(lambda d: 1e4 * (d[..., 0] > 0.999).double() + 1e-3, 128, dtype=torch.float64)
    faces = equirect_to_cubemap(e, 64)
    coarse = cubemap_to_equirect(faces, 8)
    fine = cubemap_to_equirect(faces, 128)
    assert torch.isfinite(coarse).all()
    assert torch.allclose(integrate(coarse), integrate(fine), rtol=1e-6)


def test_sample_cubemap_handles_edges_and_corners():
    faces = torch.ones(6, 4, 4, 3)
    corners = torch.tensor([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [1.0, 0.0, 1.0], [0.0, 1e-30, 0.0]])
    assert torch.allclose(sample_cubemap(faces, corners), torch.ones(4, 3))


@pytest.mark.parametrize("shape", [(5, 4, 4, 3), (6, 4, 5, 3), (6, 4, 4)])
def test_malformed_faces_raise(shape):
    with pytest.raises(CubemapError, match="faces"):
        cubemap_to_equirect(torch.zeros(shape), 8)


def test_bad_size_raises():
    with pytest.raises(CubemapError, match="size"):
        cubemap_directions(0)
    assert math.isfinite(float(equirect_to_cubemap(torch.ones(4, 8, 3), 1).sum()))


# --- conversions documented in docs/conventions.md -------------------------------------
def _bilinear_uv(img, u, v):
    """Sample an [H, W, 3] image at texture coords (u right, v up from the bottom row), wrapping u."""
    h, w = img.shape[:2]
    col = u * w - 0.5
    row = (1.0 - v) * h - 0.5
    c0 = torch.floor(col)
    r0 = torch.floor(row).clamp(0, h - 2)
    tc, tr = (col - c0)[..., None], (row - r0).clamp(0, 1)[..., None]
    c0 = c0.long() % w
    c1 = (c0 + 1) % w
    r0 = r0.long()
    r1 = r0 + 1
    return (img[r0, c0] * (1 - tc) + img[r0, c1] * tc) * (1 - tr) + (img[r1, c0] * (1 - tc) + img[r1, c1] * tc) * tr


def test_threejs_equirect_conversion_is_a_quarter_turn_roll():
    """three.js equirectUv: u = atan2(z, x)/2pi + 1/2, v = asin(y)/pi + 1/2 (flipY: row 0 = top)."""
    h = 32
    e = envmap_from_function(smooth, h, dtype=torch.float64)
    three_img = torch.roll(e, shifts=-(2 * h) // 4, dims=1)
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(200, 3, generator=g, dtype=torch.float64), dim=-1)
    d = d[d[:, 1].abs() < 0.9]  # away from the pole rows (this sampler has no pole handling)
    u = torch.atan2(d[:, 2], d[:, 0]) / (2 * math.pi) + 0.5
    v = torch.asin(d[:, 1]) / math.pi + 0.5
    assert (_bilinear_uv(three_img, u, v) - smooth(d)).abs().max() < 0.01


@pytest.mark.parametrize("axis,lookup", [("x", (-1, 1, 1)), ("z", (1, 1, -1))])
def test_mirrored_cube_maps_for_threejs_and_unity(axis, lookup):
    """three.js CubeTexture samples (-x, y, z); Unity samples its own (x, y, -z): both see L(d)."""
    from core.envmap import mirror_envmap

    e = envmap_from_function(smooth, 64, dtype=torch.float64)
    faces = equirect_to_cubemap(mirror_envmap(e, axis), 32)
    g = torch.Generator().manual_seed(1)
    d = torch.nn.functional.normalize(torch.randn(100, 3, generator=g, dtype=torch.float64), dim=-1)
    seen = sample_cubemap(faces, d * torch.tensor(lookup, dtype=torch.float64))
    assert (seen - smooth(d)).abs().max() < 0.03
