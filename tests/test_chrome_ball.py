"""Chrome balls: placement, perspective-exact rendering, occlusion, compositing, unwrapping.

Expected values come from independent forward geometry (silhouette circles, reflection
law on a chosen surface point), never from the renderer itself.
"""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings, strategies as st

from core.camera import Camera, Intrinsics, identity_pose
from core.chrome_ball import (
    BallPlacementError,
    ball_radius,
    ball_reflection_rays,
    composite,
    composite_depth,
    place_probe,
    render_balls,
    unwrap_ball,
)
from core.conventions import tonemap
from core.envmap import envmap_from_function, sample_envmap


def make_camera(w=64, h=48, hfov=60.0, pose=None) -> Camera:
    return Camera(Intrinsics.from_hfov(w, h, hfov), identity_pose() if pose is None else pose)


def constant(value):
    v = torch.as_tensor(value, dtype=torch.float32)
    return lambda d, b: v.expand(d.shape[0], 3)


def silhouette_polygon(camera: Camera, center, radius, n=720) -> torch.Tensor:
    """Image points [n, 2] of the sphere's outline: the circle of tangency seen from the camera."""
    c = torch.as_tensor(center, dtype=torch.float64)
    o = camera.position
    to_cam = o - c
    D = to_cam.norm()
    axis = to_cam / D
    ring_centre = c + (radius**2 / D**2) * to_cam
    ring_radius = radius * math.sqrt(1.0 - radius**2 / float(D) ** 2)
    helper = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    if abs(float(axis @ helper)) > 0.9:
        helper = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    e1 = torch.linalg.cross(axis, helper)
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(axis, e1)
    a = torch.linspace(0, 2 * math.pi, n + 1, dtype=torch.float64)[:-1, None]
    pts = ring_centre + ring_radius * (torch.cos(a) * e1 + torch.sin(a) * e2)
    u, v, _ = camera.project(pts)
    return torch.stack((u, v), dim=-1)


def polygon_area(p: torch.Tensor) -> float:
    x, y = p[:, 0], p[:, 1]
    return float(0.5 * (x * y.roll(-1) - x.roll(-1) * y).sum().abs())


# ---------------------------------------------------------------------------------------
# Placement
# ---------------------------------------------------------------------------------------
def test_place_probe_centre_lies_on_pixel_ray_at_planar_depth():
    cam = make_camera()
    center, radius = place_probe(cam, (10.5, 30.25), 3.0)
    u, v, z = cam.project(center.double())
    assert float(u) == pytest.approx(10.5, abs=1e-4)
    assert float(v) == pytest.approx(30.25, abs=1e-4)
    assert float(z) == pytest.approx(3.0, rel=1e-6)
    assert 0 < radius < 3.0


@pytest.mark.parametrize("uv", [(32.0, 24.0), (5.0, 40.0), (60.0, 3.0)])
def test_ball_radius_gives_requested_projected_minor_diameter(uv):
    cam = make_camera()
    center, radius = place_probe(cam, uv, 2.5, diameter_fraction=0.25)
    poly = silhouette_polygon(cam, center, radius)
    radial = poly.mean(0) - torch.tensor([cam.intrinsics.cx, cam.intrinsics.cy], dtype=torch.float64)
    perp = (
        torch.tensor([-radial[1], radial[0]]) if radial.norm() > 1e-9 else torch.tensor([1.0, 0.0], dtype=torch.float64)
    )
    perp = perp / perp.norm()
    width = float((poly @ perp).max() - (poly @ perp).min())
    assert width == pytest.approx(0.25 * 48, rel=1e-3)


@pytest.mark.parametrize("depth", [0.0, -1.0, float("nan"), float("inf"), -float("inf")])
def test_place_probe_rejects_invalid_depth(depth):
    with pytest.raises(BallPlacementError, match="depth"):
        place_probe(make_camera(), (32, 24), depth)


def test_probe_behind_camera_is_refused():
    cam = make_camera()
    with pytest.raises(BallPlacementError, match="behind"):
        ball_radius(cam, [0.0, 0.0, 2.0])
    with pytest.raises(BallPlacementError, match="ball 1"):
        ball_reflection_rays(cam, torch.tensor([[0.0, 0.0, -2.0], [0.0, 0.0, 3.0]]), torch.tensor([0.3, 0.3]))
    # a ball that crosses the camera plane has an unbounded projection
    with pytest.raises(BallPlacementError, match="camera plane"):
        ball_reflection_rays(cam, torch.tensor([[0.5, 0.0, -0.2]]), torch.tensor([0.3]))
    with pytest.raises(BallPlacementError, match="radius"):
        ball_reflection_rays(cam, torch.tensor([[0.0, 0.0, -2.0]]), torch.tensor([float("nan")]))


# ---------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------
def test_uniform_environment_gives_uniform_ball():
    cam = make_camera()
    center, radius = place_probe(cam, (20.0, 20.0), 2.0, diameter_fraction=0.5)
    env = torch.full((16, 32, 3), 0.7)
    layer = render_balls(cam, center[None], torch.tensor([radius]), env[None])
    cov = layer.coverage[0]
    full = cov > 0.999
    assert full.sum() > 50
    assert torch.allclose(layer.radiance[full], torch.full_like(layer.radiance[full], 0.7), rtol=1e-5)
    # premultiplied everywhere, including anti-aliased rim pixels
    assert torch.allclose(layer.radiance, 0.7 * cov[..., None], atol=1e-6)


def test_total_coverage_matches_projected_area_off_axis():
    cam = make_camera(96, 72)
    center, radius = place_probe(cam, (75.0, 20.0), 1.5, diameter_fraction=0.3)
    layer = render_balls(cam, center[None], torch.tensor([radius]), constant(1.0), supersample=4)
    area = polygon_area(silhouette_polygon(cam, center, radius))
    assert float(layer.coverage.sum()) == pytest.approx(area, rel=0.01)


def test_bright_direction_appears_where_the_reflection_law_says():
    cam = make_camera(96, 72)
    center, radius = place_probe(cam, (60.0, 30.0), 2.0, diameter_fraction=0.5)
    c = center.double()
    o = cam.position
    # pick a visible surface point, then find by forward geometry what it reflects
    to_cam = (o - c) / (o - c).norm()
    n = to_cam + torch.tensor([0.35, -0.25, 0.0], dtype=torch.float64)
    n = n / n.norm()
    p = c + radius * n
    r = (p - o) / (p - o).norm()
    d0 = r - 2 * (r @ n) * n
    u, v, _ = cam.project(p)
    lobe = d0.float()

    def bright(d, b):
        return torch.exp(4000.0 * ((d @ lobe) - 1.0))[:, None].expand(-1, 3)

    layer = render_balls(cam, center[None], torch.tensor([radius]), bright, supersample=4)
    peak = int(layer.radiance[..., 0].argmax())
    row, col = divmod(peak, cam.intrinsics.width)
    assert abs(col + 0.5 - float(u)) <= 1.0 and abs(row + 0.5 - float(v)) <= 1.0


def test_sub_pixel_ball_keeps_its_area():
    cam = make_camera()
    center, radius = place_probe(cam, (30.3, 17.8), 4.0, diameter_fraction=0.4 / 48)  # 0.4 px across
    layer = render_balls(cam, center[None], torch.tensor([radius]), constant(2.0))
    area = polygon_area(silhouette_polygon(cam, center, radius))
    assert torch.isfinite(layer.radiance).all()
    assert float(layer.coverage.sum()) == pytest.approx(area, rel=0.05)
    assert float(layer.coverage.max()) <= 1.0


def test_ball_partly_outside_frame_equals_crop_of_larger_frame():
    small = make_camera(64, 48)
    k = small.intrinsics
    pad = 20
    big = Camera(Intrinsics(k.fx, k.fy, k.cx + pad, k.cy + pad, k.width + 2 * pad, k.height + 2 * pad), identity_pose())
    center, radius = place_probe(small, (2.0, 45.0), 2.0, diameter_fraction=0.4)
    a = render_balls(small, center[None], torch.tensor([radius]), constant(1.0))
    b = render_balls(big, center[None], torch.tensor([radius]), constant(1.0))
    crop = b.coverage[:, pad : pad + k.height, pad : pad + k.width]
    assert 0 < float(a.coverage.sum()) < float(b.coverage.sum())
    assert torch.allclose(a.coverage, crop, atol=1e-6)
    assert torch.isfinite(a.depth[a.coverage[0] > 0]).all()


def test_ball_entirely_outside_frame_renders_nothing():
    cam = make_camera()
    center, radius = place_probe(cam, (-40.0, 24.0), 2.0)
    layer = render_balls(cam, center[None], torch.tensor([radius]), constant(1.0))
    assert float(layer.coverage.sum()) == 0.0
    assert torch.isinf(layer.depth).all()


def test_nearer_ball_occludes_farther_one():
    cam = make_camera(96, 72)
    near_c, near_r = place_probe(cam, (48.0, 36.0), 2.0, diameter_fraction=0.3)
    far_c, far_r = place_probe(cam, (56.0, 36.0), 4.0, diameter_fraction=0.5)
    colours = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    centers = torch.stack((far_c, near_c))  # deliberately far first
    layer = render_balls(cam, centers, torch.tensor([far_r, near_r]), lambda d, b: colours[b], supersample=3)
    assert float(layer.coverage[1, 36, 48]) == 1.0 and float(layer.coverage[0, 36, 48]) == 0.0
    assert torch.allclose(layer.radiance[36, 48], colours[1])
    assert float(layer.total_coverage.max()) <= 1.0 + 1e-6
    # the pixel centre ray hits the near ball's front, nearly at z - R
    assert float(layer.depth[36, 48]) == pytest.approx(2.0 - near_r, rel=0.02)
    # the far ball is still visible where the near one does not cover it
    assert float(layer.coverage[0].sum()) > 10


def test_composite_and_composite_depth():
    cam = make_camera()
    center, radius = place_probe(cam, (32.0, 24.0), 2.0, diameter_fraction=0.5)
    layer = render_balls(cam, center[None], torch.tensor([radius]), constant(5.0))
    frame = torch.full((48, 64, 3), 0.25)
    out = composite(frame, layer)
    cov = layer.total_coverage[..., None]
    assert torch.allclose(out, 0.25 * (1 - cov) + 5.0 * cov, atol=1e-5)

    scene = torch.full((48, 64), 10.0)
    scene[24, :] = float("nan")
    scene[:, 0] = 0.0
    depth = composite_depth(scene, layer)
    covered = layer.total_coverage > 0.5
    assert torch.allclose(depth[covered], layer.depth[covered])
    assert torch.isfinite(depth[covered]).all() and (depth[covered] < 2.0).all()
    untouched = ~covered
    assert torch.equal(depth[untouched].nan_to_num(-1), scene[untouched].nan_to_num(-1))
    # a wall in front of the ball wins
    wall = torch.full((48, 64), 0.5)
    assert torch.equal(composite_depth(wall, layer), wall)


def test_extreme_radiance_and_exposure_stay_finite():
    cam = make_camera()
    center, radius = place_probe(cam, (32.0, 24.0), 2.0)
    env = envmap_from_function(lambda d: torch.pow(10.0, 6.0 * d[..., 1:2].expand(*d.shape[:-1], 3)), 32)
    assert float(env.min()) < 2e-6 and float(env.max()) > 5e5
    layer = render_balls(cam, center[None], torch.tensor([radius]), env[None])
    out = composite(torch.zeros(48, 64, 3), layer)
    assert torch.isfinite(out).all()
    for ev in (-10.0, -5.0, 0.0, 5.0):
        ldr = tonemap(out, ev)
        assert torch.isfinite(ldr).all() and float(ldr.min()) >= 0 and float(ldr.max()) <= 1


def test_gradient_flows_from_pixels_to_radiance():
    cam = make_camera()
    center, radius = place_probe(cam, (32.0, 24.0), 2.0)
    colour = torch.tensor([0.5, 1.0, 2.0], requires_grad=True)
    layer = render_balls(cam, center[None], torch.tensor([radius]), lambda d, b: colour.expand(d.shape[0], 3))
    layer.radiance.sum().backward()
    expected = float(layer.total_coverage.sum())
    assert torch.allclose(colour.grad, torch.full((3,), expected), rtol=1e-5)

    env = torch.rand(16, 32, 3, requires_grad=True)
    layer = render_balls(cam, center[None], torch.tensor([radius]), env[None])
    layer.radiance.sum().backward()
    assert env.grad is not None and float(env.grad.sum()) == pytest.approx(
        3 * float(layer.total_coverage.sum()), rel=1e-4
    )


@settings(max_examples=25, deadline=None)
@given(
    u=st.floats(-10, 74),
    v=st.floats(-10, 58),
    depth=st.floats(0.05, 50.0),
    frac=st.floats(0.01, 0.9),
)
def test_rays_are_finite_unit_and_obey_reflection_law(u, v, depth, frac):
    cam = make_camera()
    center, radius = place_probe(cam, (u, v), depth, diameter_fraction=frac)
    rays = ball_reflection_rays(cam, center[None], torch.tensor([radius]))
    if rays.pixel_index.numel() == 0:
        return
    assert torch.isfinite(rays.direction).all() and torch.isfinite(rays.depth).all()
    assert torch.allclose(rays.direction.norm(dim=-1), torch.ones(1), atol=1e-5)
    # grazing rim samples included: reflection keeps the ray on the mirror side (d.n >= 0)
    assert float((rays.direction * rays.normal).sum(-1).min()) >= -1e-4
    assert (rays.depth > 0).all() and (rays.depth <= depth + radius + 1e-3).all()
    cov = torch.zeros(48 * 64).index_add(0, rays.pixel_index, rays.sample_weight)
    assert float(cov.max()) <= 1.0 + 1e-6


# ---------------------------------------------------------------------------------------
# Unwrapping
# ---------------------------------------------------------------------------------------
def smooth_env(height):
    return envmap_from_function(
        lambda d: torch.stack((1.2 + 0.8 * d[..., 0], 1.0 + 0.6 * d[..., 1], 1.1 - 0.7 * d[..., 2]), -1), height
    )


def test_unwrap_recovers_environment_and_round_trips():
    cam = make_camera(128, 128, hfov=50.0)
    center, radius = place_probe(cam, (70.0, 58.0), 2.0, diameter_fraction=0.6)
    env = smooth_env(32)
    image = render_balls(cam, center[None], torch.tensor([radius]), env[None], supersample=3).radiance
    unwrapped, valid = unwrap_ball(image, cam, center, radius, 32)
    # the ball shows most of the sphere: all but a cone behind it
    assert 0.6 < float(valid.float().mean()) < 0.99
    rel = ((unwrapped[valid] - env[valid]).abs() / env[valid]).amax(-1)
    # exact up to resampling: the last valid texels near the rim are spread over few pixels
    assert float(rel.quantile(0.99)) < 0.03 and float(rel.max()) < 0.1
    assert float(unwrapped[~valid].abs().max()) == 0.0

    again = render_balls(cam, center[None], torch.tensor([radius]), unwrapped[None], supersample=3).radiance
    rays = ball_reflection_rays(cam, center[None], torch.tensor([radius]), supersample=3)
    hit_valid = sample_envmap(valid.float()[..., None].expand(-1, -1, 3).contiguous(), rays.direction)[:, 0] > 0.999
    good = torch.ones(128 * 128, dtype=torch.bool).index_put((rays.pixel_index[~hit_valid],), torch.tensor(False))
    cov = render_balls(cam, center[None], torch.tensor([radius]), constant(1.0), supersample=3).coverage[0].reshape(-1)
    good &= cov > 0.999
    assert good.sum() > 2000
    assert torch.allclose(again.reshape(-1, 3)[good], image.reshape(-1, 3)[good], rtol=0.03)


def test_unwrap_invalid_behind_the_ball():
    cam = make_camera(128, 128)
    center, radius = place_probe(cam, (64.0, 64.0), 2.0, diameter_fraction=0.5)
    image = torch.ones(128, 128, 3)
    _, valid = unwrap_ball(image, cam, center, radius, 16)
    # the env-map direction straight behind the ball (away from the camera, -z) is hidden;
    # the direction back towards the camera (+z) is seen at the ball's centre
    from core.conventions import direction_to_equirect_pixel

    row, col = direction_to_equirect_pixel(torch.tensor([0.0, 0.0, -1.0]), 16)
    assert not bool(valid[int(row), int(col) % 32])
    row, col = direction_to_equirect_pixel(torch.tensor([0.0, 0.0, 1.0]), 16)
    assert bool(valid[int(row), int(col) % 32])


def test_posed_camera_renders_the_same_image_with_rotated_directions():
    still = make_camera()
    angle = 0.7
    pose = identity_pose()
    pose[:3, :3] = torch.tensor(
        [[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]],
        dtype=torch.float64,
    )
    pose[:3, 3] = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    moved = make_camera(pose=pose)
    c0, r0 = place_probe(still, (20.0, 30.0), 3.0)
    c1, r1 = place_probe(moved, (20.0, 30.0), 3.0)
    assert r1 == pytest.approx(r0, rel=1e-6)
    assert torch.allclose(c1.double(), pose[:3, :3] @ c0.double() + pose[:3, 3], atol=1e-5)
    a = ball_reflection_rays(still, c0[None], torch.tensor([r0]))
    b = ball_reflection_rays(moved, c1[None], torch.tensor([r1]))
    assert torch.equal(a.pixel_index, b.pixel_index)
    assert torch.allclose(b.direction, a.direction @ pose[:3, :3].T.float(), atol=1e-4)
    assert torch.allclose(b.depth, a.depth, rtol=1e-4)
