"""Simulator outputs: spec round trip, capture directory, training export, oracle prior, CLI."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from core.sim.capture import parse_probes, write_capture
from core.sim.render import ProbeError, geometry, render_envmap, render_frame
from core.sim.spec import Box, CameraSpec, Lamp, Room, SceneSpec, SceneSpecError
from core.sim.suites import SUITES, suite

SMALL = (40, 30)


def small(name: str, frames: int | None = None) -> SceneSpec:
    s = suite(name)
    update = {"resolution": SMALL, "quality": s.quality.model_copy(update={"area_samples": 4, "indirect_samples": 4})}
    if frames is not None:
        update["frames"] = frames
        update["probes"] = [p for p in s.probes if p.t <= (frames - 1) / s.fps]
    return s.model_copy(update=update)


@pytest.mark.parametrize("name", sorted(SUITES))
def test_suites_round_trip_and_declare_free_probes(name):
    s = suite(name)
    assert SceneSpec.model_validate_json(s.model_dump_json()) == s
    assert s.frames <= 24 and s.resolution == (192, 144)
    assert s.probes, "every suite declares held-out probes"
    geom = geometry(s)
    x = torch.tensor([p.x for p in s.probes])
    assert bool(geom.inside_room(x).all()) and not bool(geom.inside_furniture(x).any())


def test_spec_rejects_bad_input_with_field_names():
    base = suite("static").model_dump()
    with pytest.raises(ValidationError, match="colour"):
        SceneSpec.model_validate({**base, "colour": 1})
    with pytest.raises(ValidationError, match="lo < hi"):
        Box(lo=(0, 0, 0), hi=(1, -1, 1))
    with pytest.raises(ValidationError, match="effects"):
        SceneSpec.model_validate({**base, "effects": ["emission", "caustics"]})
    with pytest.raises(SceneSpecError, match="unknown suite"):
        suite("nope")


def test_probe_outside_free_space_is_refused():
    s = suite("static")
    with pytest.raises(ProbeError, match="outside the room"):
        render_envmap(s, (10.0, 1.0, 1.0), 0.0, height=4)
    table_top = s.furniture[0].box
    inside = tuple((l + h) / 2 for l, h in zip(table_top.lo, table_top.hi))
    with pytest.raises(ProbeError, match="inside furniture"):
        render_envmap(s, inside, 0.0, height=4)


def test_parse_probes():
    p = parse_probes("1,2,3@0.5; 0,1,0")
    assert [q.x for q in p] == [(1.0, 2.0, 3.0), (0.0, 1.0, 0.0)] and [q.t for q in p] == [0.5, 0.0]
    with pytest.raises(SceneSpecError, match="three coordinates"):
        parse_probes("1,2@0")


def test_planar_depth_of_a_wall_facing_camera_is_analytic():
    s = SceneSpec(
        room=Room(boxes=[Box(lo=(0, 0, 0), hi=(4, 3, 5))]),
        camera=CameraSpec(position=(2.0, 1.5, 3.0), hfov_deg=60.0),
        resolution=(16, 12),
        effects=frozenset({"emission"}),
    )
    depth = render_frame(s, 0).depth
    # every pixel sees the wall z = 0 head-on: planar depth is the camera's z everywhere
    torch.testing.assert_close(depth, torch.full_like(depth, 3.0), rtol=1e-5, atol=1e-5)


def test_write_capture_parses_with_consistent_shapes(tmp_path):
    from core.io.exr import read_exr
    from core.io.images import read_image

    s = small("temporal", frames=4)
    doc = write_capture(s, tmp_path, envmap_height=8)
    on_disk = json.loads((tmp_path / "capture.json").read_text())
    assert on_disk["format"] == "lightfield-capture" and on_disk["version"] == 1
    t, (w, h) = s.frames, SMALL
    assert on_disk["frame_count"] == t and len(on_disk["frames"]) == t and len(on_disk["hdr_frames"]) == t
    assert len(on_disk["poses"]) == t and all(len(p) == 16 for p in on_disk["poses"])
    k = on_disk["intrinsics"]
    assert (k["width"], k["height"]) == (w, h)
    assert read_image(tmp_path / on_disk["frames"][0]).shape == (h, w, 3)
    assert read_exr(tmp_path / on_disk["hdr_frames"][-1]).shape == (h, w, 3)
    depth = np.load(tmp_path / on_disk["depth"])["depth"]
    assert depth.shape == (t, h, w) and depth.dtype == np.float32 and np.isfinite(depth).all()
    assert SceneSpec.model_validate_json((tmp_path / on_disk["scene"]).read_text()) == s
    assert (tmp_path / on_disk["video"]).stat().st_size > 0
    assert len(on_disk["probes"]) == len(s.probes)
    for p, spec_p in zip(on_disk["probes"], s.probes):
        env = read_exr(tmp_path / p["envmap"])
        assert env.shape == (8, 16, 3)
        np.testing.assert_allclose(env, render_envmap(s, spec_p.x, spec_p.t, 8).numpy(), rtol=1e-3)
    # the last row of each pose is (0, 0, 0, 1), and depth unprojects onto the room's surfaces
    from core.camera import Camera, Intrinsics

    pose = torch.tensor(on_disk["poses"][0], dtype=torch.float64).reshape(4, 4)
    assert pose[3].tolist() == [0.0, 0.0, 0.0, 1.0]
    pts = Camera(Intrinsics(**k), pose).unproject(torch.from_numpy(depth[0]))
    lo, hi = torch.tensor(s.room.boxes[0].lo), torch.tensor(s.room.boxes[0].hi)
    assert bool(((pts >= lo - 1e-3) & (pts <= hi + 1e-3)).all())
    assert doc["cost"]["rays"]["primary"] >= t * w * h


def test_engine_loads_simulated_capture_unchanged(tmp_path):
    capture_mod = pytest.importorskip("core.capture.prepare")
    s = small("moving-camera", frames=3)
    write_capture(s, tmp_path, envmap_height=4)
    cap = capture_mod.load_prepared_capture(tmp_path)
    assert tuple(cap.frames.shape) == (3, SMALL[1], SMALL[0], 3)
    doc = json.loads((tmp_path / "capture.json").read_text())
    torch.testing.assert_close(cap.poses.reshape(3, 16), torch.tensor(doc["poses"], dtype=torch.float64))
    torch.testing.assert_close(cap.times, torch.arange(3, dtype=torch.float32) / s.fps)


def test_training_export_balls_are_valid(tmp_path):
    from core.io.exr import read_exr
    from core.io.images import read_image
    from core.sim.training import write_training_export

    s = small("static").model_copy(update={"resolution": (64, 48)}).with_effects({"emission", "direct", "shadows"})
    ds = write_training_export(s, tmp_path, views=3)
    assert json.loads((tmp_path / "dataset.json").read_text()) == ds
    assert ds["format"] == "lightfield-balls" and ds["count"] == 3 and ds["resolution"] == [48, 64]
    geom = geometry(s)
    for i in range(3):
        d = tmp_path / "samples" / f"{i:06d}"
        meta = json.loads((d / "meta.json").read_text())
        balls = meta["balls"]
        assert 1 <= len(balls) <= 9
        c = torch.tensor([b["center"] for b in balls])
        r = torch.tensor([b["radius"] for b in balls])
        assert bool((geom.distance_to_furniture(c) > r).all())
        assert bool(geom.inside_room(c).all()) and bool((geom.distance_to_room_walls(c) > r).all())
        gap = (c[:, None] - c[None]).norm(dim=-1) - (r[:, None] + r[None])
        assert bool((gap + torch.eye(len(balls)) * 1e9 > 0).all()), "balls intersect each other"
        mask = read_image(d / "ball_mask.png")
        mask = mask[..., 0] if mask.ndim == 3 else mask
        assert ((mask > 0) & (mask < 1)).any(), "ball edges carry fractional coverage"
        mask = mask > 0  # any coverage
        with_balls, bg = read_exr(d / "image_with_balls.exr"), read_exr(d / "background.exr")
        assert mask.any()
        np.testing.assert_array_equal(with_balls[~mask], bg[~mask])
        for b in balls:  # each ball's centre pixel is covered by the mask
            u, v = b["pixel"]
            assert mask[int(v), int(u)]
        depth = np.load(d / "depth_with_balls.npz")["depth"]
        assert depth.shape == (48, 64) and np.isfinite(depth[mask]).all()
        assert len(meta["c2w"]) == 16 and meta["intrinsics"]["width"] == 64


def test_oracle_prior_keeps_pixels_outside_masks_and_matches_ground_truth():
    from core.camera import Camera
    from core.chrome_ball import ball_reflection_rays
    from core.conventions import tonemap
    from core.priors.base import PriorRequest, ProbeGeometry
    from core.sim.oracle import OracleSimPrior
    from core.sim.render import radiance

    s = small("spatial")
    frame = render_frame(s, 0)
    cam: Camera = frame.camera
    centers = torch.tensor([[1.6, 1.0, 2.6], [2.4, 1.2, 2.2]])
    radii = torch.tensor([0.12, 0.1])
    u, v, _ = cam.project(centers.double())
    rays = ball_reflection_rays(cam, centers, radii, supersample=1)
    masks = torch.zeros(2, SMALL[1] * SMALL[0]).index_put_(
        (rays.ball_index, rays.pixel_index), rays.sample_weight, accumulate=True
    )
    masks = masks.reshape(2, SMALL[1], SMALL[0])
    image = torch.rand(3, SMALL[1], SMALL[0], generator=torch.Generator().manual_seed(0))
    req = PriorRequest(
        image=image,
        ball_masks=masks,
        depth=frame.depth,
        ev=-1.0,
        tau=0.5,
        steps=5,
        guidance_scale=1.0,
        probes=ProbeGeometry(
            centers=centers, radii=radii, pixels=torch.stack([u, v], -1).float(), camera=cam, frame_index=0, time=0.0
        ),
        extras={"ball_rays": rays, "frame_linear": frame.hdr},
    )
    prior = OracleSimPrior(s)
    out = prior(req)
    outside = masks.sum(0) == 0
    assert torch.equal(out[:, outside], image[:, outside])
    # a fully covered pixel shows the mean ground truth over its samples at the ball centre
    full = torch.nonzero(masks[0].reshape(-1) >= 1.0 - 1e-6).squeeze(1)
    assert len(full) > 0
    pix = int(full[0])
    sel = (rays.ball_index == 0) & (rays.pixel_index == pix)
    gt = radiance(s, centers[0:1].expand(int(sel.sum()), 3), torch.zeros(int(sel.sum())), rays.direction[sel]).mean(0)
    r_, c_ = divmod(pix, SMALL[0])
    torch.testing.assert_close(out[:, r_, c_], tonemap(gt, -1.0), rtol=1e-4, atol=1e-4)
    assert prior.describe()["oracle"] is True


def test_cli_simulate_writes_capture_and_reports_errors(tmp_path, capsys):
    from cli.main import main

    spec = small("spatial").model_copy(update={"resolution": (16, 12)})
    path = tmp_path / "spec.json"
    path.write_text(spec.model_dump_json())
    out = tmp_path / "cap"
    assert main(["simulate", str(path), "-o", str(out), "--height", "4", "--probes", "1,1,1@0", "--no-video"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["probes"] == 1 and (out / "capture.json").is_file()
    assert main(["simulate", "no-such-suite", "-o", str(tmp_path / "x")]) == 2
    assert "no-such-suite" in capsys.readouterr().err


def test_envmap_conserves_a_tiny_lamps_energy_at_any_resolution():
    from core.envmap import solid_angles

    le, r, dist = 1e4, 0.01, 1.5
    s = SceneSpec(
        room=Room(boxes=[Box(lo=(0, 0, 0), hi=(4, 3, 4))]),
        camera=CameraSpec(position=(2, 1.5, 3.5)),
        emitters=[Lamp(center=(2.0 + dist, 1.5, 2.0), radius=r, radiance=(le,) * 3)],
        effects=frozenset({"emission"}),
    )
    expected = le * 2 * math.pi * (1 - math.sqrt(1 - (r / dist) ** 2))
    for height in (8, 32):
        env = render_envmap(s, (2.0, 1.5, 2.0), 0.0, height)
        power = float((env[..., 0] * solid_angles(height)).sum())
        assert power == pytest.approx(expected, rel=0.03)


def test_hard_suite_has_what_it_promises():
    s = small("hard")
    frame = render_frame(s, 0)
    lamp = next(e for e in s.emitters if e.kind == "lamp")
    assert min(lamp.radiance) >= 1e4 * float(frame.hdr.mean(-1).median())
    windows = [e for e in s.emitters if e.kind == "window"]
    assert windows and all(min(w.radiance) * 2.0 ** s.sensor.ev >= 1.0 for w in windows)  # saturate in LDR
    top = next(f.box for f in s.furniture if f.name.endswith("top"))
    assert any(
        top.lo[0] < p.x[0] < top.hi[0] and top.lo[2] < p.x[2] < top.hi[2] and p.x[1] < top.lo[1] for p in s.probes
    )


def test_diffusion_trainer_reads_the_training_export(tmp_path):
    data = pytest.importorskip("core.training.diffusion.data")
    from core.sim.training import write_training_export

    s = small("spatial").model_copy(update={"resolution": (32, 24)}).with_effects({"emission", "direct"})
    write_training_export(s, tmp_path, views=2)
    ds = data.BallDataset(tmp_path, (16, 16))
    item = ds[1]
    assert len(ds) == 2 and tuple(item["hdr"].shape) == (3, 16, 16)
    assert 0.0 < float(item["coverage"].max()) <= 1.0


def test_spec_refuses_lights_and_cameras_in_walls():
    base = suite("static").model_dump()
    lamp = {"kind": "lamp", "center": [9.0, 1.0, 1.0], "radius": 0.05, "radiance": [1, 1, 1]}
    with pytest.raises(ValidationError, match=r"emitters\[2\].*outside the room"):
        SceneSpec.model_validate({**base, "emitters": [*base["emitters"], lamp]})
    window = {**base["emitters"][1], "facing": "-x"}  # on the x = 0 wall but facing out of the room
    with pytest.raises(ValidationError, match=r"emitters\[0\].*does not face into the room"):
        SceneSpec.model_validate({**base, "emitters": [window]})
    with pytest.raises(ValidationError, match="camera.position"):
        # inside the table top
        SceneSpec.model_validate({**base, "camera": {**base["camera"], "position": [2.3, 0.73, 1.6]}})
