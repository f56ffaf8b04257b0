"""Known and reprojection priors: exact targets, untouched background, reprojected lights."""
import math

import pytest
import torch

from core.camera import Camera, Intrinsics
from core.capture.load import capture_from_arrays
from core.chrome_ball import ball_reflection_rays, composite, place_probe, render_balls
from core.conventions import direction_to_theta_phi, inverse_tonemap, tonemap
from core.priors.base import PriorError, PriorRequest, ProbeGeometry
from core.priors.known import KnownRadiancePrior
from core.priors.registry import build_prior
from core.priors.reprojection import CLIP_BOOST, ReprojectionPrior, linearise, push_pull_fill

H, W = 48, 64


def _request(capture, frame=0, pixels=((20.0, 24.0), (44.0, 30.0)), depth_frac=0.6, ev=0.0):
    cam = capture.camera(frame)
    placed = [place_probe(cam, uv, depth_frac * float(capture.depth[frame, int(uv[1]), int(uv[0])])) for uv in pixels]
    centers = torch.stack([c for c, _ in placed])
    radii = torch.tensor([r for _, r in placed])
    rays = ball_reflection_rays(cam, centers, radii, supersample=1)
    bg = inverse_tonemap(capture.frames[frame])
    layer = render_balls(cam, centers, radii, lambda d, b: torch.full((d.shape[0], 3), 0.5), rays=rays)
    image = tonemap(composite(bg, layer), ev).permute(2, 0, 1)
    probes = ProbeGeometry(centers, radii, torch.tensor(pixels), cam, frame, float(capture.times[frame]))
    req = PriorRequest(image, layer.coverage, capture.depth[frame], ev, 1.0, 10, 12.5, probes,
                       extras={"frame_linear": bg, "ball_rays": rays})
    return req, layer


def _capture(frames=None, depth=3.0):
    frames = torch.full((1, H, W, 3), 0.5) if frames is None else frames
    return capture_from_arrays(frames, torch.full((frames.shape[0], H, W), depth), fps=1)


def test_known_prior_renders_the_function_and_keeps_background():
    cap = _capture(torch.rand(1, H, W, 3))
    def up(x, t, d):  # brighter towards +y, same at every x
        return (0.1 + d[:, 1:2].clamp_min(0) * 3.0).expand(-1, 3)

    req, layer = _request(cap, ev=-1.0)
    target = KnownRadiancePrior(up)(req)
    inside = layer.total_coverage > 0
    assert torch.equal(target[:, ~inside], req.image[:, ~inside])
    # a fully covered pixel's value is the tone-mapped function averaged over its sample(s)
    full = layer.total_coverage > 0.999
    rays = req.extras["ball_rays"]
    expect = torch.zeros(H * W, 3).index_add(
        0, rays.pixel_index, up(None, None, rays.direction) * rays.sample_weight[:, None]
    )
    expect = tonemap(expect.view(H, W, 3), -1.0).permute(2, 0, 1)
    assert torch.allclose(target[:, full], expect[:, full], atol=1e-5)


def test_uniform_scene_gives_uniform_ball():
    """A room of one colour looks the same from every probe: the ball is that colour (plain
    pull-push fill; the indoor fill's elevation gain is tested in test_indoor_fill_*)."""
    cap = _capture(torch.full((1, H, W, 3), 0.4))
    prior = ReprojectionPrior(env_height=16, unseen_fill="push-pull")
    prior.bind(cap)
    req, layer = _request(cap, ev=-2.0)
    target = prior(req)
    full = layer.total_coverage > 0.999
    expect = tonemap(inverse_tonemap(torch.tensor(0.4)), -2.0)
    assert torch.allclose(target[:, full], expect, atol=1e-4)
    outside = layer.total_coverage == 0
    assert torch.equal(target[:, outside], req.image[:, outside])


def test_bright_patch_is_seen_in_its_true_direction():
    frames = torch.full((1, H, W, 3), 0.3)
    frames[0, 8:12, 40:44] = 1.0  # a clipped source on the back wall
    cap = _capture(frames)
    prior = ReprojectionPrior(env_height=32)
    prior.bind(cap)
    center = torch.tensor([[-0.4, -0.3, -1.5]])
    env = prior.envmaps(center, 0.0, 32)[0]
    lum = env.sum(-1)
    i, j = divmod(int(lum.argmax()), lum.shape[1])
    # direction of the patch centre from the probe
    patch = cap.camera(0).unproject(cap.depth[0])[10, 42]
    d = patch - center[0]
    theta, phi = direction_to_theta_phi(d)
    h = 32
    assert abs((i + 0.5) * math.pi / h - float(theta)) < 2.5 * math.pi / h
    assert abs((j + 0.5) * 2 * math.pi / (2 * h) - math.pi - float(phi)) < 2.5 * math.pi / h
    # the clipped patch (a lamp on a dim wall) is estimated well above linearised white (1.0)
    assert float(env.max()) > 2.0


def test_observed_envmaps_are_the_splat_before_the_fill_in_the_nearest_frame():
    frames = torch.rand(3, H, W, 3)
    cap = _capture(frames)  # fps 1: frames at 0, 1, 2 s
    prior = ReprojectionPrior(env_height=16)
    prior.bind(cap)
    center = torch.tensor([[0.2, -0.1, -1.0]])
    assert [prior.frame_at(t) for t in (-5.0, 0.4, 0.6, 1.9, 9.0)] == [0, 0, 1, 2, 2]
    env, seen = prior.observed_envmaps(center, 1.2)
    assert env.shape == (1, 16, 32, 3) and seen.shape == (1, 16, 32)
    assert 0 < int(seen.sum()) < seen.numel()  # the frame covers part of the sphere, not all
    filled = prior.envmaps(center, 1.2, 16)
    assert torch.allclose(env[seen], filled[seen], rtol=1e-5)  # the fill keeps what was seen
    assert torch.equal(env[~seen], torch.zeros_like(env[~seen]))
    assert not torch.equal(env, prior.observed_envmaps(center, 0.0)[0])  # another frame, other colours


def test_point_cloud_is_built_once_for_a_static_camera():
    cap = _capture(torch.rand(3, H, W, 3))
    prior = ReprojectionPrior(env_height=8)
    prior.bind(cap)
    for i in range(3):
        prior.envmaps_at_frame(torch.zeros(1, 3) + torch.tensor([0, 0, -1.0]), i)
    assert prior.point_cloud_builds == 1
    # but the colours follow the frame
    a = prior.envmaps(torch.tensor([[0, 0, -1.0]]), 0.0, 8)
    b = prior.envmaps(torch.tensor([[0, 0, -1.0]]), 1.0, 8)
    assert not torch.equal(a, b)


def test_push_pull_keeps_observed_and_fills_within_range():
    g = torch.Generator().manual_seed(0)
    env = torch.rand(2, 8, 16, 3, generator=g) + 0.5
    mask = torch.rand(2, 8, 16, generator=g) > 0.7
    out = push_pull_fill(torch.where(mask[..., None], env, 0.0), mask)
    assert torch.equal(out[mask], env[mask])
    assert (out >= 0.5 - 1e-6).all() and (out <= 1.5 + 1e-6).all()


@pytest.mark.parametrize("h", [8, 24, 32])  # 24: odd sizes down the pyramid (3 -> 2 -> 1)
def test_push_pull_fills_far_holes_with_the_observed_value_not_black(h):
    """A constant patch seen in one quarter of the sphere: every hole gets that constant (the
    old pyramid stopped at 1 x 2 pixels and faded the unseen half towards 0)."""
    env = torch.zeros(1, h, 2 * h, 3)
    seen = torch.zeros(1, h, 2 * h, dtype=torch.bool)
    seen[0, h // 3 : 2 * h // 3, h // 2 : h] = True
    env[seen] = 2.0
    out = push_pull_fill(env, seen)
    assert torch.allclose(out, torch.full_like(out, 2.0), atol=1e-5)


def test_push_pull_wraps_around_the_seam():
    """Observations on both sides of phi = +-pi: the hole between them (across the seam) is
    filled symmetrically, as if there were no seam."""
    h = 16
    env = torch.zeros(1, h, 2 * h, 3)
    seen = torch.zeros(1, h, 2 * h, dtype=torch.bool)
    seen[0, :, 2] = True  # just right of the seam
    seen[0, :, 2 * h - 3] = True  # just left of it
    env[0, :, 2] = 1.0
    env[0, :, 2 * h - 3] = 3.0
    out = push_pull_fill(env, seen)[0, h // 2, :, 0]
    across = torch.cat([out[2 * h - 3 :], out[:3]])  # 3, ?, ?, ?, ?, 1 going across the seam
    assert float(across[1:-1].min()) >= 1.0 - 1e-6 and float(across[1:-1].max()) <= 3.0 + 1e-6
    # the seam pixels lie between the two observations, closer values nearer each side
    assert float(out[2 * h - 2]) > float(out[1])


def test_push_pull_hole_takes_the_weighted_mean_of_its_neighbourhood():
    """Pull is a weighted average: a hole surrounded by 3 pixels of 1 and 1 pixel of 5 gets
    a value between them, not the value of any single level's first pixel."""
    env = torch.zeros(1, 2, 4, 3)
    seen = torch.ones(1, 2, 4, dtype=torch.bool)
    seen[0, 0, 0] = False
    env[0] = 1.0
    env[0, 1, 1] = 5.0
    out = push_pull_fill(env, seen)
    assert 1.0 < float(out[0, 0, 0, 0]) < 5.0
    assert torch.equal(out[seen], env[seen])


def test_push_pull_with_nothing_observed_is_zero():
    out = push_pull_fill(torch.rand(1, 8, 16, 3), torch.zeros(1, 8, 16, dtype=torch.bool))
    assert torch.equal(out, torch.zeros_like(out))


def test_linearise_boosts_only_clipped_pixels():
    x = torch.tensor([[0.5, 0.5, 0.5], [1.0, 0.2, 0.2]])
    lin = linearise(x)
    assert torch.allclose(lin[0], inverse_tonemap(x[0]))
    assert torch.allclose(lin[1], inverse_tonemap(x[1]) * CLIP_BOOST)


@pytest.mark.parametrize("back_faces", ["front", "dark"])
def test_hard_frames_stay_finite(back_faces):
    for frame in (torch.zeros(1, H, W, 3), torch.ones(1, H, W, 3)):
        cap = _capture(frame)
        prior = ReprojectionPrior(env_height=8, back_faces=back_faces)
        prior.bind(cap)
        req, _ = _request(cap, ev=-5.0)
        out = prior(req)
        assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1


def test_back_faces_on_degenerate_depth_stay_finite():
    """A single pixel of valid depth, a depth of zero, a 1-pixel-wide frame: the normals are NaN
    or degenerate there and such points count as front faces (never darkened), the maps finite."""
    from core.capture.depth import surface_normals

    cam = Camera(Intrinsics.from_hfov(W, H, 60.0), torch.eye(4, dtype=torch.float64))
    for depth in (torch.zeros(H, W), torch.full((H, W), float("nan")), torch.full((H, W), 1e-9)):
        n = surface_normals(cam.unproject(depth), torch.zeros(3))
        assert n.shape == (H, W, 3) and not torch.isinf(n).any()
    one_column = surface_normals(torch.rand(H, 1, 3), torch.zeros(3))
    assert one_column.shape == (H, 1, 3) and not torch.isinf(one_column).any()
    frames = torch.rand(1, H, W, 3)
    depth = torch.full((1, H, W), float("nan"))
    depth[0, H // 2, W // 2] = 2.0  # one valid pixel: filled to a constant depth by the loader
    cap = capture_from_arrays(frames, depth, fps=1)
    prior = ReprojectionPrior(env_height=8, back_faces="dark")
    prior.bind(cap)
    env = prior.envmaps(torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -50.0]]), 0.0, 8)
    assert torch.isfinite(env).all() and env.min() >= 0


def test_registry():
    assert isinstance(build_prior("reprojection", {"env_height": 8}), ReprojectionPrior)
    assert isinstance(build_prior("known", {"fn": lambda x, t, d: d.abs()}), KnownRadiancePrior)
    with pytest.raises(PriorError, match="unknown prior"):
        build_prior("magic")
    with pytest.raises(PriorError, match="fn: Field required"):
        build_prior("known")
    with pytest.raises(PriorError, match="env_height"):
        build_prior("reprojection", {"env_height": 2})
    with pytest.raises(PriorError, match="evn_height"):
        build_prior("reprojection", {"evn_height": 8})
    with pytest.raises(PriorError):
        ReprojectionPrior(env_height=8).envmaps(torch.zeros(1, 3), 0.0, 8)  # not bound
    with pytest.raises(PriorError, match="weights"):
        build_prior("diffusion")  # needs a local model directory


def test_merged_views_let_a_moving_camera_see_what_other_frames_saw():
    """Frame 1 looks 90 degrees to the right at a bright wall; with merge_views=2 a request for
    frame 0 sees that wall in the +x direction, without merging it cannot."""
    frames = torch.full((2, H, W, 3), 0.3)
    frames[1] = 0.95
    # looks along +x
    yaw = torch.tensor([[0.0, 0, -1, 0], [0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1]], dtype=torch.float64)
    poses = torch.stack([torch.eye(4, dtype=torch.float64), yaw])
    cap = capture_from_arrays(frames, torch.full((2, H, W), 3.0), poses=poses)
    right = torch.tensor([[1.0, 0.0, 0.0]])
    h = 16
    from core.envmap import sample_envmap

    seen = {}
    for merge in (1, 2):
        prior = ReprojectionPrior(env_height=h, merge_views=merge)
        prior.bind(cap)
        env = prior.envmaps(torch.zeros(1, 3), 0.0, h)[0]
        seen[merge] = float(sample_envmap(env, right)[0, 0])
        assert [v for v, _ in prior.views_for(0)] == ([0] if merge == 1 else [0, 1])
    assert seen[2] > 3 * seen[1]
    assert seen[2] == pytest.approx(float(inverse_tonemap(torch.tensor(0.95))), rel=0.05)


def test_indoor_fill_keeps_seen_pixels_and_shapes_unseen_by_elevation_and_colour():
    from core.exposure import luminance
    from core.priors.indoor_fill import elevation_gain, fill_unseen

    h = 24
    env = torch.zeros(1, h, 2 * h, 3)
    seen = torch.zeros(1, h, 2 * h, dtype=torch.bool)
    seen[0, 10:14, 20:28] = True  # a horizon band patch, reddish
    env[seen] = torch.tensor([0.6, 0.3, 0.3])
    filled = push_pull_fill(env, seen)
    out = fill_unseen(filled, env, seen)
    assert torch.equal(out[seen], env[seen])
    gain = elevation_gain(h)
    y = luminance(out[0])  # [h, w]
    # unseen luminance follows the gain profile relative to the seen rows
    seen_gain = gain[10:14].mean()
    expect = luminance(env[0, 12, 24]) * gain / seen_gain
    assert torch.allclose(y[:, 0].double(), expect.to(torch.float64), rtol=1e-4)
    # unseen colour: the seen mean chromaticity (the constant map's colour, not moved towards grey)
    c_seen = env[0, 12, 24] / luminance(env[0, 12, 24])
    unseen = ~seen[0]
    c = out[0][unseen] / luminance(out[0][unseen])[:, None]
    assert torch.allclose(c, c_seen.expand_as(c), atol=1e-5)
    # nothing seen: unchanged (zeros); everything finite
    none = torch.zeros_like(seen)
    assert torch.equal(fill_unseen(filled, env, none), filled)
    assert torch.isfinite(out).all()


def test_cap_sources_caps_only_what_is_above_the_multiple_of_the_seen_median():
    from core.exposure import luminance
    from core.priors.indoor_fill import cap_sources

    env = torch.zeros(2, 8, 16, 3)
    seen = torch.zeros(2, 8, 16, dtype=torch.bool)
    seen[:, 3:5, 4:10] = True
    env[seen] = torch.tensor([0.5, 0.4, 0.3])
    env[0, 4, 6] = torch.tensor([900.0, 600.0, 300.0])  # a lamp in map 0
    out = cap_sources(env, seen, 2.0)
    median = float(luminance(torch.tensor([0.5, 0.4, 0.3])))
    assert float(luminance(out[0, 4, 6])) == pytest.approx(2.0 * median, rel=1e-5)
    assert torch.allclose(out[0, 4, 6] / out[0, 4, 6].sum(), env[0, 4, 6] / env[0, 4, 6].sum())  # colour kept
    keep = torch.ones(2, 8, 16, dtype=torch.bool)
    keep[0, 4, 6] = False
    assert torch.equal(out[keep], env[keep])  # walls, map 1 and the unseen zeros untouched
    assert torch.equal(cap_sources(env, torch.zeros_like(seen), 2.0), env)  # nothing seen: nothing to cap against
    assert torch.equal(cap_sources(env, seen, None), env)


def test_a_bright_lamp_in_view_does_not_glow_across_the_unseen_sphere():
    """Pull-push spreads each seen pixel into the holes around it: a lamp 2000x the walls, in
    view, would light the unseen directions as if the room were full of lamps. The indoor fill
    extrapolates the seen radiance capped at SOURCE_CAP x its median (the lamp keeps its value
    where it was seen); the unseen directions then stay at the walls' level times the elevation
    gain, and in the walls' colour, as they are without the lamp."""
    from core.exposure import luminance
    from core.priors.indoor_fill import ELEVATION_GAIN, SOURCE_CAP

    cap_frames = torch.full((1, H, W, 3), 0.5)
    env = {}
    for lamp in (False, True):
        prior = ReprojectionPrior(env_height=16)
        prior.bind(_capture(cap_frames))
        raw, seen = prior.observed_envmaps(torch.zeros(1, 3), 0.0)
        if lamp:  # a lamp's radiance straight into the splat (the clip rule's estimate is tested elsewhere)
            lit = raw.clone()
            r, c = seen[0].nonzero()[len(seen[0].nonzero()) // 2].tolist()
            lit[0, r, c] = 2000.0 * raw[0, r, c] * torch.tensor([1.0, 0.2, 0.05])  # a warm, almost red lamp
            prior._splat_seen = lambda centers, frame, lit=lit, seen=seen: (lit, seen)
        env[lamp] = prior.envmaps(torch.zeros(1, 3), 0.0, 16)[0]
    unseen = ~seen[0]
    walls = float(luminance(raw[0][seen[0]]).median())
    assert torch.equal(env[True][~unseen], lit[0][~unseen])  # seen: kept
    y = luminance(env[True])[unseen]
    # the unseen colour is the walls' (grey here; the capped lamp pixel, one of the seen pixels,
    # tints the seen mean by 0.03 now that it is no longer halved towards grey), not the lamp's
    chroma = env[True][unseen] / env[True][unseen].sum(-1, keepdim=True)
    assert torch.allclose(chroma, torch.full_like(chroma, 1 / 3), atol=0.04)
    assert float(y.max()) <= SOURCE_CAP * walls * max(ELEVATION_GAIN) / min(ELEVATION_GAIN)
    assert float(y.mean()) <= 1.5 * float(luminance(env[False])[unseen].mean())
    plain = ReprojectionPrior(env_height=16, fill_source_cap=None)
    plain.bind(_capture(cap_frames))
    plain._splat_seen = lambda centers, frame: (lit, seen)
    glow = plain.envmaps(torch.zeros(1, 3), 0.0, 16)[0][unseen]
    assert float(luminance(glow).mean()) > 10 * float(y.mean())
    assert float((glow[:, 0] / glow.sum(-1)).mean()) > 0.45  # uncapped, the fill takes the lamp's red


def test_linear_frames_see_clipping_at_full_resolution():
    """A 1-pixel clipped lamp disappears from a 4x downsampled LDR frame (area averaging), but
    the prior linearises at the full resolution first, so its light survives the resize."""
    from core.priors.reprojection import linear_frames

    frames = torch.full((1, 96, 128, 3), 0.2)
    frames[0, 40, 60] = 1.0
    cap = capture_from_arrays(frames, None)
    work = cap.resized(24)
    lin = linear_frames(work)
    naive = inverse_tonemap(work.frames)
    assert float(lin.sum()) > float(naive.sum()) + 0.5 / 16  # the lamp's boosted energy (>= 1 px of white / 16)
    fixed = linear_frames(work, "fixed", 8.0)
    assert float(fixed[0].sum() - naive[0].sum()) > 0.0


def test_the_clip_rule_coefficients_a_job_passes_are_the_ones_used():
    """Benches pass the clip rule refitted without the scored room: the setting must reach the
    linearisation (a constant rule of 3 stops makes a clipped blob 8x its linearised value)."""
    from core.priors.reprojection import ReprojectionPrior

    frames = torch.full((1, 24, 32, 3), 0.2)
    frames[0, 10:13, 14:18] = 1.0
    cap = capture_from_arrays(frames, None)
    prior = ReprojectionPrior(env_height=8, clip_coefficients=(3.0, 0.0, 0.0, 0.0, 0.0))
    prior.bind(cap)
    lamp = prior._colors[0, 10:13, 14:18]
    torch.testing.assert_close(lamp, torch.full_like(lamp, 8.0))
    assert prior.describe()["clip_coefficients"] == [3.0, 0.0, 0.0, 0.0, 0.0]
    with pytest.raises(PriorError):
        ReprojectionPrior(clip_coefficients=(1.0, 2.0))  # five features, five coefficients


def test_surface_normals_face_the_camera_and_ignore_depth_edges():
    from core.capture.depth import surface_normals

    cam = Camera(Intrinsics.from_hfov(W, H, 60.0), torch.eye(4, dtype=torch.float64))
    depth = torch.full((H, W), 2.0)
    depth[:, W // 2:] = 5.0  # a step: a near panel beside a far wall, both facing the camera
    depth[5, 5] = float("nan")
    n = surface_normals(cam.unproject(depth), torch.zeros(3))
    ok = torch.isfinite(n).all(-1)
    assert not bool(ok[5, 5]) and int((~ok).sum()) == 1  # only the invalid pixel
    # every valid pixel, the ones on the step included, is its own plane's normal (+z: towards the camera)
    assert torch.allclose(n[ok], torch.tensor([0.0, 0.0, 1.0]).expand(int(ok.sum()), 3), atol=1e-5)


def test_a_probe_behind_a_seen_surface_sees_its_back_dark_not_its_front():
    """Under a table whose top the camera sees, the top's radiance is that of its observed
    side: a probe beneath sees the unobserved underside. 'dark' makes it an occluder of
    radiance 0; 'front' (the old rule) paints the lit top over the probe."""
    from core.envmap import sample_envmap

    frames = torch.zeros(1, H, W, 3)
    frames[0, :, : W // 2] = torch.tensor([0.8, 0.2, 0.2])  # a near red panel (left half, 2 m)
    frames[0, :, W // 2:] = torch.tensor([0.2, 0.8, 0.2])  # a far green wall (right half, 6 m)
    depth = torch.full((1, H, W), 6.0)
    depth[0, :, : W // 2] = 2.0
    cap = capture_from_arrays(frames, depth, fps=1)
    panel = cap.camera(0).unproject(depth[0])[H // 2, W // 4].float()
    wall = cap.camera(0).unproject(depth[0])[H // 2, 3 * W // 4].float()
    behind = (panel + torch.tensor([0.0, 0.0, -1.0]))[None]  # 1 m behind the panel, in front of the wall
    in_front = (panel + torch.tensor([0.0, 0.0, 0.5]))[None]
    env = {}
    for mode in ("dark", "front"):
        prior = ReprojectionPrior(env_height=32, unseen_fill="push-pull", back_faces=mode)
        prior.bind(cap)
        env[mode] = {"behind": prior.envmaps(behind, 0.0, 32)[0], "in_front": prior.envmaps(in_front, 0.0, 32)[0]}
        assert prior.describe()["back_faces"] == mode
    to_panel = torch.nn.functional.normalize(panel[None] - behind, dim=-1)
    to_wall = torch.nn.functional.normalize(wall[None] - behind, dim=-1)
    red = inverse_tonemap(torch.tensor([0.8, 0.2, 0.2]))
    green = inverse_tonemap(torch.tensor([0.2, 0.8, 0.2]))
    # behind the panel: its back is dark with 'dark', red with 'front'; the wall ahead is green in both
    assert float(sample_envmap(env["dark"]["behind"], to_panel).max()) < 0.05 * float(red.max())
    assert torch.allclose(sample_envmap(env["front"]["behind"], to_panel)[0], red, rtol=0.05)
    for mode in ("dark", "front"):
        assert torch.allclose(sample_envmap(env[mode]["behind"], to_wall)[0], green, rtol=0.05)
    # in front of the panel nothing changes: the frame saw the side the probe sees
    assert torch.equal(env["dark"]["in_front"], env["front"]["in_front"])


def test_the_elevation_profile_is_a_setting():
    """`elevation_gain` replaces ELEVATION_GAIN for one prior (a bench's fold refits it without
    the scored room): a flat profile leaves the unseen fill at pull-push's luminance."""
    from core.exposure import luminance
    from core.priors.indoor_fill import ELEVATION_GAIN

    frames = torch.full((1, H, W, 3), 0.5)
    envs = {}
    for gain in (None, tuple(ELEVATION_GAIN), (1.0, 1.0)):
        prior = ReprojectionPrior(env_height=16, elevation_gain=gain)
        prior.bind(_capture(frames))
        envs[gain] = prior.envmaps(torch.zeros(1, 3), 0.0, 16)[0]
    assert torch.equal(envs[None], envs[tuple(ELEVATION_GAIN)])
    plain = ReprojectionPrior(env_height=16, unseen_fill="push-pull")
    plain.bind(_capture(frames))
    assert torch.allclose(
        luminance(envs[(1.0, 1.0)]), luminance(plain.envmaps(torch.zeros(1, 3), 0.0, 16)[0]), rtol=1e-4
    )
    assert not torch.allclose(envs[None], envs[(1.0, 1.0)])
    with pytest.raises(PriorError):
        ReprojectionPrior(elevation_gain=(1.0, 0.0))


def test_the_unseen_fill_is_the_lights_colour_where_bright_and_the_walls_where_dim():
    """Rule 4 of core.priors.indoor_fill: unseen pixels at or below the fill's median keep the
    walls' colour, those at (1 + knee) x the median and above take the light's, in between a
    log-chromaticity blend; luminance is never changed. No light (or no knee) or a flat frame's
    zero light: the walls' colour everywhere."""
    from core.exposure import luminance
    from core.priors.indoor_fill import fill_unseen

    h = 16
    env = torch.zeros(1, h, 2 * h, 3, dtype=torch.float64)
    seen = torch.zeros(1, h, 2 * h, dtype=torch.bool)
    seen[0, 6:10, 8:16] = True
    walls = torch.tensor([0.6, 0.4, 0.2], dtype=torch.float64)  # warm walls
    env[seen] = walls
    filled = push_pull_fill(env, seen)
    filled[0, 1, 20:24] *= 10.0  # a bright unseen patch (the fill is bright where the gain or a source makes it)
    filled[0, 14, 20:24] *= 1e-12  # and a nearly black one (grazing the floor)
    light = torch.tensor([0.2, 0.3, 0.6], dtype=torch.float64)  # bluish light (any scale)
    out = fill_unseen(filled, env, seen, light=light, light_knee=1.0)
    plain = fill_unseen(filled, env, seen)
    assert torch.equal(out[seen], env[seen])
    assert torch.allclose(luminance(out), luminance(plain), rtol=1e-9)  # colour only

    def chroma(x):
        return x / luminance(x)[..., None]

    unseen = ~seen[0]
    y = luminance(plain[0])
    median = y[unseen].median()
    dim, bright = unseen & (y <= median), unseen & (y >= 2.0 * median)
    assert dim.any() and bright.any()
    assert torch.allclose(chroma(out[0][dim]), chroma(walls).expand(int(dim.sum()), 3), atol=1e-9)
    assert torch.allclose(chroma(out[0][bright]), chroma(light).expand(int(bright.sum()), 3), atol=1e-9)
    between = unseen & (y > 1.05 * median) & (y < 1.95 * median)
    assert between.any()  # the elevation gain makes part of the fill just above its median
    b = chroma(out[0][between])[:, 2]  # bluer than the walls, not yet the light
    assert bool(((b > chroma(walls)[2]) & (b < chroma(light)[2])).all())
    assert torch.equal(fill_unseen(filled, env, seen, light=light, light_knee=None), plain)
    assert torch.equal(fill_unseen(filled, env, seen, light=torch.zeros(3, dtype=torch.float64), light_knee=1.0), plain)
    assert torch.isfinite(out).all()


def test_grey_edge_reads_the_lights_colour_where_the_walls_mean_colour_does_not():
    """Walls of a red-tinted albedo (grey texture plus a red offset) under a bluish light: the
    photo's mean colour is the tint times the light, its grey-edge (edges cancel the offset) is
    the light's colour. Flat and black frames give no light (zero), never NaN."""
    from core.conventions import tonemap
    from core.exposure import luminance
    from core.priors.indoor_fill import grey_edge

    g = torch.Generator().manual_seed(0)
    texture = torch.rand(1, 48, 64, 1, generator=g, dtype=torch.float64) * 0.6
    albedo = texture + torch.tensor([0.35, 0.0, 0.0], dtype=torch.float64)
    light = torch.tensor([0.5, 0.7, 1.0], dtype=torch.float64)
    frames = tonemap(albedo * light).clamp(0, 1)
    est = grey_edge(frames)[0]

    def chroma(x):
        return x / luminance(x)

    def angle(a, b):
        return float(torch.rad2deg(torch.arccos(torch.nn.functional.cosine_similarity(a, b, dim=0).clamp(-1, 1))))

    mean = (albedo * light).reshape(-1, 3).mean(0)
    assert angle(chroma(est), chroma(light)) < 1.0
    assert angle(chroma(mean), chroma(light)) > 10.0
    assert torch.equal(grey_edge(torch.full((2, 8, 8, 3), 0.5)), torch.zeros(2, 3, dtype=torch.float64))
    assert torch.equal(grey_edge(torch.zeros(1, 8, 8, 3)), torch.zeros(1, 3, dtype=torch.float64))


def test_the_prior_reports_the_light_colour_knee_and_null_turns_rule_4_off():
    from core.priors.indoor_fill import LIGHT_COLOUR_KNEE

    g = torch.Generator().manual_seed(1)
    frames = (0.2 + 0.5 * torch.rand(1, H, W, 1, generator=g)) * torch.tensor([1.0, 0.8, 0.5])  # textured, warm
    maps = {}
    for knee in (LIGHT_COLOUR_KNEE, None):
        prior = ReprojectionPrior(env_height=16, light_colour_knee=knee)
        prior.bind(_capture(frames))
        assert prior.describe()["light_colour_knee"] == knee
        maps[knee] = prior.envmaps(torch.zeros(1, 3), 0.0, 16)[0]
    _, seen = prior.observed_envmaps(torch.zeros(1, 3), 0.0)
    assert torch.equal(maps[None][seen[0]], maps[LIGHT_COLOUR_KNEE][seen[0]])  # what was seen is kept
    assert not torch.equal(maps[None], maps[LIGHT_COLOUR_KNEE])
    with pytest.raises(PriorError):
        ReprojectionPrior(light_colour_knee=0.0)
