"""The observed-surfaces layer (core.fields.components.surfaces) and the points the engine gives it
(core.engine.surface_extraction): parallax from the points, the network where nothing was seen, the photo
fit at the cameras, time knots, hard inputs, and every evaluation path answering the same."""
from __future__ import annotations

import math

import pytest
import torch

from core.capture.load import capture_from_arrays
from core.conventions import equirect_directions
from core.engine.surface_extraction import observed_surfaces
from core.envmap import SPLAT_MIN_DISTANCE, voxel_merge
from core.fields import FieldConfig, SceneBounds, build_field
from core.fields.kinds.base import EMITTER_PIXEL_SIGMA
from tests.test_fields import assert_paths_agree_and_reload

BOX = SceneBounds((-3.0, -2.0, -3.0), (3.0, 2.0, 3.0), 0.0, 3.0)
H = 16


def wall_patch(z: float = -2.5, half: float = 0.4, step: float = 0.02) -> torch.Tensor:
    """A square of points [N, 3] in the plane z, centred on the z axis (facing +z)."""
    s = torch.arange(-half, half + 1e-9, step)
    gx, gy = torch.meshgrid(s, s, indexing="ij")
    return torch.stack((gx.reshape(-1), gy.reshape(-1), torch.full((gx.numel(),), z)), -1)


def field_with_patch(radiance=(4.0, 0.5, 0.25), knots=1, uses_time=False, anchors=(), points=None):
    pts = wall_patch() if points is None else points
    cfg = FieldConfig(kind="mlp", uses_time=uses_time, surface_points=pts.shape[0] + 7, surface_knots=knots,
                      surface_height=H, view_detail_heights=(8,) if anchors else (), view_anchors=anchors)
    torch.manual_seed(0)
    field = build_field(cfg, BOX).eval()
    colours = torch.as_tensor(radiance, dtype=torch.float32).reshape(1, -1, 3).expand(pts.shape[0], knots, 3)
    field.surfaces.set_surfaces(pts, colours)
    return field


def map_at(field, x, t=None, height=32):
    with torch.no_grad():
        return field.envmaps(torch.tensor([x]), None if t is None else torch.tensor([t]), height)[0]


def brightest_direction(envmap: torch.Tensor) -> torch.Tensor:
    h = envmap.shape[0]
    k = int(envmap[..., 0].argmax())
    return equirect_directions(h).reshape(-1, 3)[k]


def test_the_patch_is_seen_where_it_is_from_each_probe_and_the_network_answers_elsewhere():
    field = field_with_patch()
    for x in ([-1.5, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, 0.0, 1.0]):
        env = map_at(field, x)
        towards = torch.tensor([0.0, 0.0, -2.5]) - torch.tensor(x)
        # parallax: the patch's direction moves with the probe, within a pixel of the splat
        angle = math.degrees(math.acos(float(brightest_direction(env) @ (towards / towards.norm()))))
        assert angle < 180.0 / H * 1.5, (x, angle)
        assert torch.allclose(env[..., 0].amax(), torch.tensor(4.0), rtol=1e-3)
    field_without = field_with_patch()
    field_without.surfaces.set_surfaces(torch.zeros(0, 3), torch.zeros(0, 1, 3))
    env, plain = map_at(field, [1.5, 0.0, 0.0]), map_at(field_without, [1.5, 0.0, 0.0])
    dirs = equirect_directions(32).reshape(32, 64, 3)
    behind = dirs[..., 2] > 0.3  # away from the patch: no point there, the network's answer
    assert torch.equal(env[behind], plain[behind])
    assert not torch.allclose(env, plain)


def test_at_a_capturing_camera_the_view_detail_answers_not_the_splat():
    """The photo fit at full resolution is better than a 16-row splat where the camera stood:
    the layer's weight is 1 - the view-detail weight, 0 at an anchor."""
    field = field_with_patch(anchors=((0.0, 0.0, 0.0),))
    field_without = field_with_patch(anchors=((0.0, 0.0, 0.0),))
    field_without.surfaces.set_surfaces(torch.zeros(0, 3), torch.zeros(0, 1, 3))
    assert torch.equal(map_at(field, [0.0, 0.0, 0.0]), map_at(field_without, [0.0, 0.0, 0.0]))
    far = map_at(field, [2.0, 0.0, 1.0])
    assert float(far[..., 0].amax()) > 3.5  # 2.2 m from the anchor: the patch


def test_a_probe_reads_the_knot_nearest_its_time():
    pts = wall_patch()
    cfg = FieldConfig(kind="mlp", uses_time=True, surface_points=pts.shape[0], surface_knots=3, surface_height=H)
    field = build_field(cfg, BOX).eval()
    colours = torch.tensor([[1.0] * 3, [10.0] * 3, [100.0] * 3]).expand(pts.shape[0], 3, 3)
    field.surfaces.set_surfaces(pts, colours)
    for t, expected in ((0.0, 1.0), (0.7, 1.0), (0.8, 10.0), (1.5, 10.0), (2.9, 100.0), (99.0, 100.0)):
        assert float(map_at(field, [0.0, 0.0, 0.0], t)[..., 0].amax()) == pytest.approx(expected, rel=1e-5), t


def test_every_path_answers_the_same_and_the_artefact_reloads(tmp_path):
    g = torch.Generator().manual_seed(1)
    pts = torch.rand(600, 3, generator=g) * 5.0 - 2.5
    cfg = FieldConfig(kind="mlp", uses_time=True, surface_points=640, surface_knots=4, surface_height=12,
                      view_detail_heights=(8,), view_anchors=((0.0, 0.0, 0.0),), emitter_count=1,
                      emitter_sigma_floor=EMITTER_PIXEL_SIGMA * math.pi / 8)  # the lobe width `envmaps` gives 8 rows
    field = build_field(cfg, BOX)
    field.surfaces.set_surfaces(pts, torch.rand(600, 4, 3, generator=g) * 5.0)
    field.emitters.set_sources(torch.tensor([[1.0, 1.0, 1.0]]), torch.tensor([0.05]), torch.full((1, 1, 3), 2.0))
    xs = torch.tensor([[0.1, 0.2, -1.0], [1.0, 0.5, -1.5], [0.0, 0.0, 0.0], [0.1, 0.0, 0.1]])
    maps = assert_paths_agree_and_reload(field.eval(), xs, torch.tensor([0.4, 2.9, 1.0, 1.6]), 8, tmp_path)
    assert torch.isfinite(maps).all()


def test_the_layer_costs_16_bytes_per_point_plus_12_per_knot_in_the_artefact(tmp_path):
    """docs/engine.md's artefact-size figure ("Observed surfaces"): points (12) + used flag (4) + colours
    (12 per knot)."""
    from core.fields.stored.artefact import save_artefact

    sizes = {}
    for points, knots in ((0, 1), (4096, 1), (4096, 3)):
        cfg = FieldConfig(kind="mlp", uses_time=True, surface_points=points, surface_knots=knots)
        art = save_artefact(tmp_path / f"a{points}_{knots}", build_field(cfg, BOX), {})
        sizes[points, knots] = (art.path / "field.safetensors").stat().st_size
    assert abs(sizes[4096, 1] - sizes[0, 1] - 4096 * 28) < 1024
    assert abs(sizes[4096, 3] - sizes[4096, 1] - 4096 * 24) < 1024


def test_black_blinding_and_coincident_points_stay_finite_within_the_field_range():
    pts = torch.cat((wall_patch(), torch.zeros(1, 3), wall_patch(z=2.5)))
    colours = torch.cat((torch.zeros(wall_patch().shape[0], 1, 3), torch.full((1, 1, 3), 1e30),
                         torch.full((wall_patch().shape[0], 1, 3), 1e30)))
    field = field_with_patch(points=pts)
    field.surfaces.set_surfaces(pts, colours)
    env = map_at(field, [0.0, 0.0, 0.0])  # a point exactly at the probe: skipped (SPLAT_MIN_DISTANCE)
    assert SPLAT_MIN_DISTANCE > 0 and torch.isfinite(env).all()
    lo, hi = field.config.log_radiance_min, field.config.log_radiance_max
    assert float(env.amin()) >= math.exp(lo) * 0.999 and float(env.amax()) <= math.exp(hi) * 1.001
    dirs = equirect_directions(32).reshape(32, 64, 3)
    assert float(env[dirs[..., 2] < -0.99].amax()) < 1e-5  # the black patch ahead
    assert float(env[dirs[..., 2] > 0.99].amin()) > 1e5  # the blinding one behind
    # non-finite points or colours never enter the layer
    field.surfaces.set_surfaces(torch.tensor([[float("nan"), 0.0, 0.0], [0.0, 0.0, -1.0]]),
                                torch.tensor([[[1.0, 1.0, 1.0]], [[float("inf"), 0.0, 0.0]]]))
    assert field.surfaces.is_empty()


def test_a_config_cannot_ask_for_more_surface_values_than_the_cap():
    from core.fields.kinds.config import MAX_SURFACE_VALUES

    FieldConfig(surface_points=1 << 16, surface_knots=MAX_SURFACE_VALUES >> 16)
    with pytest.raises(ValueError, match="surface_points x surface_knots"):
        FieldConfig(surface_points=1 << 16, surface_knots=(MAX_SURFACE_VALUES >> 16) + 1)


def test_voxel_merge_keeps_the_bound_and_the_mean_colour():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(5000, 3, generator=g, dtype=torch.float64) * 4.0
    cols = torch.rand(5000, 2, 3, generator=g, dtype=torch.float64)
    merged_pts, merged_cols = voxel_merge(pts, cols, 700)
    assert 100 < merged_pts.shape[0] <= 700 and merged_cols.shape[1:] == (2, 3)
    assert merged_pts.amin() >= 0.0 and merged_pts.amax() <= 4.0
    assert abs(float(merged_cols.mean()) - float(cols.mean())) < 0.02
    same_pts, same_cols = voxel_merge(pts[:10], cols[:10], 700)
    assert torch.equal(same_pts, pts[:10]) and torch.equal(same_cols, cols[:10])


def capture(T=4, moving=False):
    frames = torch.full((T, 12, 16, 3), 0.5)
    poses = torch.eye(4, dtype=torch.float64).repeat(T, 1, 1)
    if moving:
        poses[:, 0, 3] = torch.linspace(0.0, 0.6, T, dtype=torch.float64)
    return capture_from_arrays(frames, torch.full((T, 12, 16), 2.0), poses=poses, fps=1.0)


def test_the_engine_keeps_one_view_with_radiance_per_knot_for_a_static_camera():
    cap = capture(T=4)
    bounds = SceneBounds((-3.0, -3.0, -3.0), (3.0, 3.0, 3.0), 0.0, 3.0)
    radiance = lambda i: torch.full((12, 16, 3), float(i + 1))  # noqa: E731 (frame i: radiance i + 1)
    timed = observed_surfaces(cap, radiance, bounds, max_points=4096, uses_time=True, knots=4)
    assert timed.count == 12 * 16 and timed.knots == 4
    assert timed.colors[0, :, 0].tolist() == [1.0, 2.0, 3.0, 4.0]
    assert cap.nearest_frames(bounds.knot_times(7)).tolist() == [0, 0, 1, 1, 2, 2, 3]  # a tie: the earlier frame
    static = observed_surfaces(cap, radiance, bounds, max_points=4096, uses_time=False, knots=4)
    assert static.knots == 1 and float(static.colors[0, 0, 0]) == 2.5  # the frames' mean
    assert torch.allclose(static.points[:, 2], torch.tensor(-2.0))  # on the depth plane, in front of the camera


def test_a_moving_camera_merges_its_views_and_carries_them_over_time_when_the_lighting_changes():
    cap = capture(T=5, moving=True)
    bounds = SceneBounds((-3.0, -3.0, -3.0), (3.0, 3.0, 3.0), 0.0, 4.0)
    radiance = lambda i: torch.full((12, 16, 3), 1.0)  # noqa: E731
    merged = observed_surfaces(cap, radiance, bounds, max_points=300, uses_time=False, knots=5)
    assert merged is not None and merged.count <= 300 and merged.knots == 1
    assert torch.allclose(merged.colors, torch.ones_like(merged.colors))
    # the room brightens 2x at frame 3: every surface, seen before or after, follows it at each knot
    brightening = lambda i: torch.full((12, 16, 3), 1.0 if i < 3 else 2.0)  # noqa: E731
    timed = observed_surfaces(cap, brightening, bounds, max_points=300, uses_time=True, knots=5)
    assert timed is not None and timed.count <= 300 and timed.knots == 5
    assert torch.allclose(timed.colors[:, :3], torch.ones_like(timed.colors[:, :3]), rtol=1e-3)
    assert torch.allclose(timed.colors[:, 3:], torch.full_like(timed.colors[:, 3:], 2.0), rtol=1e-3)
    assert observed_surfaces(cap, radiance, bounds, max_points=0, uses_time=False, knots=5) is None


def test_spread_frames_are_distinct_and_span_the_capture():
    from core.capture.load import capture_from_arrays

    cap = capture_from_arrays(torch.full((20, 12, 16, 3), 0.5), torch.full((20, 12, 16), 2.0), fps=1.0)
    picked = cap.spread_frames(16).tolist()
    assert len(picked) == 16 and len(set(picked)) == 16 and picked == sorted(picked)
    assert picked[0] == 0 and picked[-1] == 19
    assert cap.spread_frames(1).tolist() == [0]
    assert cap.spread_frames(50).tolist() == list(range(20))
