"""`lightfield envmap`: writes exactly what the artefact answers; user errors exit 2 with a message."""
import json

import numpy as np
import pytest
import torch

from cli.main import main
from core.fields import FieldConfig, SceneBounds, build_field
from core.fields.kinds.mlp import MLPSettings
from core.fields.stored.artefact import LightFieldArtefact, save_artefact
from core.io.envmap_io import load_envmap

BOUNDS = SceneBounds((-1.0, -1.0, -3.0), (1.0, 1.0, 0.0), t0=0.0, t1=2.0)


@pytest.fixture
def artefact_dir(tmp_path):
    field = build_field(FieldConfig(kind="mlp", mlp=MLPSettings(width=8, layers=2, skip_layer=None)), BOUNDS)
    with torch.no_grad():
        for p in field.parameters():
            p.normal_(0, 0.5, generator=torch.Generator().manual_seed(3))
    return save_artefact(tmp_path / "lf", field, {}).path


def test_npy_output_equals_the_query_api(artefact_dir, tmp_path, capsys):
    out = tmp_path / "env.npy"
    assert main(["envmap", str(artefact_dir), "--x", "0.1,0.2,-1", "--t", "0.5", "--height", "8", "-o", str(out)]) == 0
    expected, _ = LightFieldArtefact.load(artefact_dir).envmap((0.1, 0.2, -1.0), 0.5, 8)
    np.testing.assert_array_equal(load_envmap(out), expected.numpy())
    report = json.loads(capsys.readouterr().out)
    assert report["format"] == "npy" and report["extrapolated_x"] is False


def test_exr_default_and_png_preview(artefact_dir, tmp_path, capsys):
    exr = tmp_path / "env.exr"
    assert main(["envmap", str(artefact_dir), "--x", "0,0,-1", "--t", "1", "--height", "4", "-o", str(exr)]) == 0
    expected, _ = LightFieldArtefact.load(artefact_dir).envmap((0.0, 0.0, -1.0), 1.0, 4)
    np.testing.assert_allclose(load_envmap(exr), expected.numpy(), rtol=1e-6)  # float32 EXR by default
    png = tmp_path / "env.png"
    assert (
        main(["envmap", str(artefact_dir), "--x", "0,0,-1", "--t", "1", "--height", "4", "--ev", "-2", "-o", str(png)])
        == 0
    )
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_extrapolated_query_warns(artefact_dir, tmp_path, capsys):
    out = tmp_path / "e.npy"
    assert main(["envmap", str(artefact_dir), "--x", "5,0,0", "--t", "9", "--height", "2", "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert "outside the estimated x and t range" in captured.err
    assert json.loads(captured.out)["extrapolated_t"] is True


def test_fast_path_answers_from_the_stored_bake(artefact_dir, tmp_path):
    from core.fields.stored.bake import load_or_bake

    art = LightFieldArtefact.load(artefact_dir)
    baked = load_or_bake(art, grid=(2, 2, 2), times=2, height=4)  # small, so the test stays fast
    out = tmp_path / "f.npy"
    assert (
        main(["envmap", str(artefact_dir), "--x", "0,0,-1", "--t", "1", "--height", "4", "--fast", "-o", str(out)]) == 0
    )
    np.testing.assert_array_equal(load_envmap(out), baked.envmap((0.0, 0.0, -1.0), 1.0, 4)[0].numpy())


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--x", "0,0,-1", "--height", "4"], "t is required"),
        (["--x", "0,0,-1", "--t", "0", "--height", "0"], "height"),
    ],
)
def test_user_errors_exit_2_with_message(artefact_dir, tmp_path, capsys, argv, message):
    assert main(["envmap", str(artefact_dir), *argv, "-o", str(tmp_path / "x.npy")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.npy").exists()


def test_missing_artefact_and_bad_position(tmp_path, capsys):
    assert main(["envmap", str(tmp_path / "nope"), "--x", "0,0,0", "-o", str(tmp_path / "x.npy")]) == 2
    assert "does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["envmap", str(tmp_path), "--x", "0,nan,0", "-o", str(tmp_path / "x.npy")])
    assert exc.value.code == 2
    assert "three finite numbers" in capsys.readouterr().err
