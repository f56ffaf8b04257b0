"""`lightfield estimate` / `preview` end to end on tiny inputs, and object insertion."""
import json
import math

import numpy as np
import pytest
import torch

from cli.main import main
from core.camera import Camera, Intrinsics
from core.conventions import inverse_tonemap, tonemap
from core.insertion import ALBEDO, InsertionError, InsertionPoint, insert_objects, parse_points, place_objects
from core.io import read_image, write_png
from core.transfer import SRGB

H, W = 36, 48


@pytest.fixture(scope="module")
def estimated(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cli")
    write_png(tmp / "in.png", np.random.default_rng(0).uniform(0.2, 0.8, (H, W, 3)).astype(np.float32))
    code = main(["estimate", str(tmp / "in.png"), "-o", str(tmp / "out"), "--iterations", "4", "--quiet",
                 "--params", '{"intrinsics": {"hfov_deg": 50}, "seed": 3}'])
    return tmp, code


def test_estimate_writes_artefact_and_summary(estimated, capsys):
    tmp, code = estimated
    assert code == 0
    meta = json.loads((tmp / "out" / "lightfield.json").read_text())
    assert meta["capture"]["intrinsics"]["fx"] == pytest.approx(0.5 * W / math.tan(math.radians(25)))
    assert meta["params"]["seed"] == 3 and meta["training"]["iterations"] == 4
    assert not (tmp / "out.checkpoint").exists()  # removed after success


def test_estimate_bad_params_exit_2_naming_the_field(tmp_path, capsys):
    write_png(tmp_path / "in.png", np.full((H, W, 3), 0.5, np.float32))
    code = main(["estimate", str(tmp_path / "in.png"), "-o", str(tmp_path / "o"), "--params", '{"fps": -1}'])
    assert code == 2 and "fps" in capsys.readouterr().err
    np.savez(tmp_path / "d.npz", depth=np.ones((5, 5), np.float32))
    code = main(
        ["estimate", str(tmp_path / "in.png"), "-o", str(tmp_path / "o"), "--depth", str(tmp_path / "d.npz"), "--quiet"]
    )
    err = capsys.readouterr().err
    assert code == 2 and "depth" in err and "5x5" in err
    assert not (tmp_path / "o").exists()


def test_preview_png_changes_only_the_objects(estimated, tmp_path):
    tmp, _ = estimated
    code = main(["preview", str(tmp / "out"), "--input", str(tmp / "in.png"), "--points", "0.3,0.5;0.6,0.6,1.5",
                 "-o", str(tmp_path / "p.png")])
    assert code == 0
    before, after = read_image(tmp / "in.png"), read_image(tmp_path / "p.png")
    changed = np.abs(after - before).max(-1) > 1.5 / 255
    assert 0.03 < changed.mean() < 0.6  # two balls + two spheres, not the whole frame


def test_preview_rejects_bad_points(estimated, tmp_path, capsys):
    tmp, _ = estimated
    code = main(
        [
            "preview",
            str(tmp / "out"),
            "--input",
            str(tmp / "in.png"),
            "--points",
            "2,0.5",
            "-o",
            str(tmp_path / "p.png"),
        ]
    )
    assert code == 2 and "points[0]" in capsys.readouterr().err


@pytest.mark.parametrize("text", ["a,b", "0.5", "0.5,0.5,-1", "0.5,nan", ";"])
def test_parse_points_errors(text):
    with pytest.raises(InsertionError):
        parse_points(text)


def test_parse_points_defaults_and_values():
    assert len(parse_points(None)) == 2
    assert parse_points("0.1,0.2,3; 0.5,0.5") == [InsertionPoint(0.1, 0.2, 3.0), InsertionPoint(0.5, 0.5, None)]


def test_insertion_under_uniform_light_is_analytic():
    """Uniform radiance L: the mirror ball shows L, the Lambertian sphere albedo * L."""
    k = Intrinsics.from_hfov(96, 72, 60.0)
    cam = Camera(k, torch.eye(4, dtype=torch.float64))
    depth = torch.full((72, 96), 4.0)
    frame = torch.full((72, 96, 3), 0.2)
    L = 0.3

    def envmaps_at(xs, t):
        return torch.full((xs.shape[0], 16, 32, 3), L)

    pts = [InsertionPoint(0.3, 0.5, 2.0)]
    out = insert_objects(frame, depth, cam, envmaps_at, None, pts)
    centers, radii = place_objects(cam, depth, pts)
    u_ball, v_ball, _ = cam.project(centers.double())
    ball = out[int(v_ball[0]), int(u_ball[0])]
    sphere = out[int(v_ball[1]), int(u_ball[1])]
    assert torch.allclose(ball, tonemap(torch.tensor(L)), atol=2e-3)
    assert torch.allclose(sphere, tonemap(torch.tensor(ALBEDO * L)), atol=1e-2)
    far = out[5, 90]
    assert torch.allclose(far, frame[5, 90], atol=1e-6)
    # scene geometry in front of an object hides it
    hidden = insert_objects(frame, torch.full((72, 96), 1.0), cam, envmaps_at, None, pts)
    assert torch.allclose(hidden, tonemap(inverse_tonemap(frame)), atol=1e-6)


def test_preview_mp4(estimated, tmp_path):
    from core.io import read_video

    tmp, _ = estimated
    assert main(["preview", str(tmp / "out"), "--input", str(tmp / "in.png"), "-o", str(tmp_path / "p.mp4")]) == 0
    video = read_video(tmp_path / "p.mp4")
    assert video.frames.shape[0] == 1 and video.frames.shape[1:3] == (H, W)


def test_estimate_takes_each_frames_exposure(tmp_path, capsys):
    from core.io import write_video

    yy, xx = np.meshgrid(np.linspace(0, 1, H), np.linspace(0, 1, W), indexing="ij")
    room = (0.05 + 0.3 * xx + 0.1 * yy)[..., None] * np.array([1.0, 0.9, 0.8])
    # a camera's file: the sRGB curve of each exposure (untagged: read as sRGB)
    frames = np.stack([SRGB.from_linear(torch.from_numpy(room).float() * 2.0**ev).numpy() for ev in (0.0, -1.0, -2.0)])
    write_video(tmp_path / "ae.mp4", frames, fps=4.0)
    code = main(["estimate", str(tmp_path / "ae.mp4"), "-o", str(tmp_path / "out"), "--iterations", "4", "--quiet",
                 "--frame-ev", "0,-1,-2"])
    assert code == 0
    meta = json.loads((tmp_path / "out" / "lightfield.json").read_text())
    assert meta["capture"]["frame_ev"] == [0.0, -1.0, -2.0] and not meta["temporal"]["uses_time"]
    assert main(["preview", str(tmp_path / "out"), "--input", str(tmp_path / "ae.mp4"), "--frame", "2",
                 "-o", str(tmp_path / "p.png")]) == 0  # the preview renders frame 2 at its own exposure
    code = main(["estimate", str(tmp_path / "ae.mp4"), "-o", str(tmp_path / "o2"), "--frame-ev", "0,-1,x"])
    assert code == 2 and "--frame-ev" in capsys.readouterr().err
    code = main(["estimate", str(tmp_path / "ae.mp4"), "-o", str(tmp_path / "o3"), "--frame-ev", "0,-1", "--quiet"])
    assert code == 2 and "frame_ev" in capsys.readouterr().err and not (tmp_path / "o3").exists()
