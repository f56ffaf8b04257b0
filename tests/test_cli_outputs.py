"""The hand-off commands (`sh`, `cubemap`, `gltf`, `usd`, `sequence`) and `envmap`'s format rules,
on a tiny random artefact: each writes what the artefact answers, in the consumer's format."""
from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest
import torch

from cli.main import build_parser, main
from core.fields import FieldConfig, SceneBounds, build_field
from core.fields.kinds.mlp import MLPSettings
from core.fields.stored.artefact import LightFieldArtefact, save_artefact
from core.lights import extract_dominant_light

BOUNDS = SceneBounds((-1.0, -1.0, -3.0), (1.0, 1.0, 0.0), t0=0.0, t1=2.0)
X = "0.1,0.2,-1"


@pytest.fixture(scope="module")
def artefact_dir(tmp_path_factory):
    field = build_field(FieldConfig(kind="mlp", mlp=MLPSettings(width=8, layers=2, skip_layer=None)), BOUNDS)
    with torch.no_grad():
        for p in field.parameters():
            p.normal_(0, 0.5, generator=torch.Generator().manual_seed(3))
    return save_artefact(tmp_path_factory.mktemp("lf") / "lf", field, {}).path


def envmap_at(artefact_dir, t, height):
    return LightFieldArtefact.load(artefact_dir).envmap((0.1, 0.2, -1.0), t, height)[0]


@pytest.mark.parametrize("name, argv, message", [
    ("env.jpg", [], "cannot tell the format"),
    ("env.exr", ["--format", "png"], "has extension .exr but the format is png"),
    ("env", [], "cannot tell the format"),
])
def test_envmap_refuses_a_file_name_that_disagrees_with_the_format(artefact_dir, tmp_path, capsys, name, argv, message):
    assert (
        main(["envmap", str(artefact_dir), "--x", X, "--t", "1", "--height", "4", *argv, "-o", str(tmp_path / name)])
        == 2
    )
    assert message in capsys.readouterr().err and not (tmp_path / name).exists()
    assert main(["envmap", str(artefact_dir), "--x", X, "--t", "1", "--height", "4", "--format", "png",
                 "-o", str(tmp_path / "ok.png")]) == 0


def test_envmap_exr_carries_metadata(artefact_dir, tmp_path):
    from core.io.exr import read_exr_header

    out = tmp_path / "e.exr"
    assert main(["envmap", str(artefact_dir), "--x", X, "--t", "0.5", "--height", "4", "-o", str(out)]) == 0
    header = read_exr_header(out)
    np.testing.assert_allclose(header["lightfield:probePosition"], [0.1, 0.2, -1.0], rtol=1e-6)
    assert header["lightfield:time"] == 0.5
    assert header["lightfield:artefactId"] == LightFieldArtefact.load(artefact_dir).weights_sha256
    assert "chromaticities" in header


def test_help_shows_defaults():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    text = " ".join(sub.choices["envmap"].format_help().split())
    assert "(default: 64)" in text and "(default: 0.0)" in text
    assert "(default: None)" not in text and "(default: False)" not in text
    assert "(default: 64)" in " ".join(sub.choices["cubemap"].format_help().split())


def test_sh_batch_in_both_layouts(artefact_dir, tmp_path, capsys):
    from core.export.sh_layouts import to_arcore_27

    queries = tmp_path / "q.json"
    queries.write_text(json.dumps([{"x": [0.1, 0.2, -1.0], "t": 0.5}, {"x": [0.0, 0.0, -2.0], "t": 1.5}]))
    assert main(["sh", str(artefact_dir), "--queries", str(queries), "--layout", "threejs"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out) == 2 and out[0]["layout"] == "threejs"
    light = extract_dominant_light(envmap_at(artefact_dir, 0.5, 128))
    np.testing.assert_allclose(out[0]["coefficients"], light.ambient_sh.reshape(-1).tolist(), rtol=1e-5, atol=1e-7)
    assert main(["sh", str(artefact_dir), "--x", X, "--t", "0.5"]) == 0
    one = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(one["coefficients"], to_arcore_27(light.ambient_sh), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("layout", ["arcore", "threejs", "babylon", "unity", "arkit"])
def test_sh_json_is_the_apis_model_in_every_layout(artefact_dir, capsys, layout):
    """The CLI prints exactly the API's /sh model (core.export.schema.SphericalHarmonics): same fields,
    same names (`intensity`, `solid_angle`, `extrapolated` {x, t}), so the docs' recipes read both."""
    from core.export.schema import SphericalHarmonics
    from core.export.sh_layouts import unpack

    assert main(["sh", str(artefact_dir), "--x", X, "--t", "0.5", "--layout", layout]) == 0
    raw = json.loads(capsys.readouterr().out)
    doc = SphericalHarmonics.model_validate(raw)
    assert set(raw) == set(SphericalHarmonics.model_fields)
    assert set(raw["dominant_light"]) == set(SphericalHarmonics.model_fields["dominant_light"].annotation.model_fields)
    assert doc.layout == layout and doc.extrapolated.x is False and doc.t == 0.5
    light = extract_dominant_light(envmap_at(artefact_dir, 0.5, 128))
    np.testing.assert_allclose(
        unpack(doc.coefficients, layout), light.ambient_sh.double().numpy(), rtol=1e-5, atol=1e-7
    )
    np.testing.assert_allclose(doc.dominant_light.intensity, light.intensity_rgb.tolist(), rtol=1e-5)


def test_cubemap_ktx2_holds_prefiltered_mips(artefact_dir, tmp_path):
    from core.cubemap import equirect_to_cubemap
    from core.export.ktx2 import decode_ktx2_cubemap

    out = tmp_path / "cube.ktx2"
    assert main(["cubemap", str(artefact_dir), "--x", X, "--t", "1", "--size", "8", "-o", str(out)]) == 0
    levels = decode_ktx2_cubemap(out.read_bytes())
    assert [lv.shape[1] for lv in levels] == [8, 4]  # default: down to the smallest face of 4 texels
    mirror = equirect_to_cubemap(envmap_at(artefact_dir, 1.0, 16), 8).numpy()
    np.testing.assert_allclose(levels[0][..., :3], mirror, rtol=2e-3, atol=1e-4)
    assert (
        main(["cubemap", str(artefact_dir), "--x", X, "--t", "1", "--size", "6", "-o", str(tmp_path / "c.ktx2")]) == 2
    )
    assert main(["cubemap", str(artefact_dir), "--x", X, "--t", "1", "--size", "4", "-o", str(tmp_path / "faces")]) == 0
    assert sorted(p.name for p in (tmp_path / "faces").iterdir()) == sorted(
        f"{n}.exr" for n in ("px", "nx", "py", "ny", "pz", "nz")
    )


def test_gltf_command_writes_a_glb_the_khronos_validator_accepts(artefact_dir, tmp_path, node_consumers):
    from node_consumers import run_consumer
    from test_export_node import assert_valid_glb

    out = tmp_path / "probe.glb"
    assert main(["gltf", str(artefact_dir), "--x", X, "--t", "1", "--size", "16", "-o", str(out)]) == 0
    assert_valid_glb(run_consumer("gltf", out))
    assert main(["gltf", str(artefact_dir), "--x", X, "--t", "1", "-o", str(tmp_path / "probe.gltf")]) == 2


def test_usd_command_writes_a_stage_usd_core_opens(artefact_dir, tmp_path):
    pytest.importorskip("pxr", reason="usd-core is a dev dependency")
    from pxr import Usd, UsdLux

    for name in ("probe.usdz", "probe.usda"):
        out = tmp_path / name
        assert main(["usd", str(artefact_dir), "--x", X, "--t", "1", "--height", "8", "-o", str(out)]) == 0
        stage = Usd.Stage.Open(str(out))
        dome = UsdLux.DomeLight(stage.GetPrimAtPath("/Probe/EnvLight"))
        assert dome.GetTextureFormatAttr().Get() == "latlong"
        assert stage.GetRootLayer().customLayerData["lightfield:grade"] == "unchecked"  # made without a self-check
    assert (tmp_path / "probe.exr").is_file()  # the .usda's texture, beside it


def test_sequence_command_writes_frames_over_time(artefact_dir, tmp_path):
    from core.io.exr import read_exr, read_exr_header

    out = tmp_path / "shot.zip"
    assert main(["sequence", str(artefact_dir), "--x", X, "--t0", "0", "--t1", "2", "--frames", "3", "--height", "4",
                 "-o", str(out)]) == 0
    with zipfile.ZipFile(io.BytesIO(out.read_bytes())) as z:
        index = json.loads(z.read("sequence.json"))
        assert [f["t"] for f in index["frames"]] == [0.0, 1.0, 2.0]
        for f in index["frames"]:
            data = z.read(f["file"])
            np.testing.assert_allclose(read_exr(data), envmap_at(artefact_dir, f["t"], 4).numpy(), rtol=1e-6)
            assert read_exr_header(data)["lightfield:time"] == f["t"]
    assert (
        main(
            [
                "sequence",
                str(artefact_dir),
                "--x",
                X,
                "--t0",
                "2",
                "--t1",
                "1",
                "--frames",
                "2",
                "-o",
                str(tmp_path / "d"),
            ]
        )
        == 2
    )


def test_unity_command_writes_a_probe_grid_in_unitys_convention(artefact_dir, tmp_path, capsys):
    from core.export.coverage import covered_region
    from core.export.schema import UnityProbeGrid
    from core.export.unity import unity_sh, unity_shade_sh9

    out = tmp_path / "probes.json"
    assert main(["unity", str(artefact_dir), "--grid", "2,1,2", "--t", "1", "-o", str(out)]) == 0
    doc = UnityProbeGrid.model_validate_json(out.read_text())
    assert len(doc.probes) == 4 and all(np.shape(p.sh) == (3, 9) for p in doc.probes)
    assert doc.grade.grade == "unchecked"  # the test's artefact was made without the job's self-check
    for p in doc.probes:
        assert p.position_unity == pytest.approx((p.position[0], p.position[1], -p.position[2]))
    x = doc.probes[0].position
    env = LightFieldArtefact.load(artefact_dir).envmap(x, 1.0, 32)[0].numpy()
    np.testing.assert_allclose(doc.probes[0].sh, unity_sh(env), rtol=1e-6)
    assert np.isfinite(unity_shade_sh9(doc.probes[0].sh, np.array([0.0, 1.0, 0.0]))).all()
    # the default grid: cell centres of the region the captures cover, none flagged, none on its faces
    lo, hi, _ = covered_region(BOUNDS)
    positions = np.array([p.position for p in doc.probes])
    assert (positions > lo).all() and (positions < hi).all() and doc.extrapolated_probes == 0
    assert "outside" not in capsys.readouterr().err
    # a grid over the whole padded box: the corners are outside what the captures cover, and say so
    assert main(["unity", str(artefact_dir), "--grid", "2,2,2", "--t", "1", "--lo=-1,-1,-3", "--hi=1,1,0",
                 "-o", str(out)]) == 0
    doc = UnityProbeGrid.model_validate_json(out.read_text())
    assert doc.extrapolated_probes == 8 and all(p.extrapolated.x for p in doc.probes)
    assert "8 of 8 probes lie outside" in capsys.readouterr().err


def test_arkit_command_writes_metal_slices_and_sh_planes(artefact_dir, tmp_path):
    import base64

    from core.cubemap import equirect_to_cubemap
    from core.export.products import cube_source_height
    from core.export.schema import ArkitProbe
    from core.export.sh_layouts import unpack

    out = tmp_path / "arkit.json"
    assert main(["arkit", str(artefact_dir), "--x", X, "--t", "0.5", "--size", "8", "-o", str(out)]) == 0
    doc = ArkitProbe.model_validate_json(out.read_text())
    assert (doc.size, doc.bytes_per_row, doc.bytes_per_image, len(doc.slices_base64)) == (8, 64, 512, 6)
    env = envmap_at(artefact_dir, 0.5, cube_source_height(8))
    faces = equirect_to_cubemap(env, 8).numpy()
    got = np.stack([np.frombuffer(base64.b64decode(s), "<f2").reshape(8, 8, 4) for s in doc.slices_base64])
    np.testing.assert_allclose(got[..., :3].astype(np.float32), np.clip(faces, 0, 65504), rtol=2e-3, atol=1e-4)
    light = extract_dominant_light(env)
    np.testing.assert_allclose(unpack(doc.sh_planes, "arkit"), light.ambient_sh.double().numpy(), rtol=1e-5, atol=1e-7)


def test_usd_without_usd_core_says_which_extra_to_install(artefact_dir, tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "pxr", None)  # as if usd-core were not installed: `import pxr` fails
    assert main(["usd", str(artefact_dir), "--x", X, "--t", "1", "--height", "4", "-o", str(tmp_path / "p.usdz")]) == 2
    err = capsys.readouterr().err
    assert "usd-core" in err and "lightfield[usd]" in err and not (tmp_path / "p.usdz").exists()
