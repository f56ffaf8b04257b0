"""Our outputs through real JavaScript consumers (tests/node: three.js r187, Khronos glTF
validator), installed by `npm ci` from the project's own lock file."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from core.sh import eval_sh, project_sh, sh_irradiance, to_arcore_27
from node_consumers import run_consumer
from test_export import lamp_map, random_dirs


def test_threejs_spherical_harmonics3_reads_the_threejs_layout(node_consumers, tmp_path):
    from core.export.threejs import threejs_sh

    sh = project_sh(lamp_map(32))
    normals = random_dirs(24, seed=5)
    req = tmp_path / "sh.json"
    req.write_text(json.dumps({"coefficients": threejs_sh(sh), "normals": normals.tolist()}))
    three = run_consumer("sh", req)
    np.testing.assert_allclose(three["at"], eval_sh(sh, normals).numpy(), rtol=1e-5, atol=1e-5)
    want = sh_irradiance(sh, normals).numpy()
    np.testing.assert_allclose(three["irradiance"], want, rtol=2e-5, atol=1e-5)  # three's constants have 6 digits
    # the trap the docs used to set: ARCore's signs in three.js mirror the light in x and y
    req.write_text(json.dumps({"coefficients": to_arcore_27(sh), "normals": normals.tolist()}))
    wrong = np.asarray(run_consumer("sh", req)["irradiance"])
    assert np.abs(wrong - want).max() > 0.3 * np.abs(want).max()


def test_threejs_exrloader_reads_our_exr_bottom_up_as_linear_srgb(node_consumers, tmp_path):
    from core.export.metadata import envmap_attributes
    from core.io.envmap_io import encode_envmap

    env = lamp_map(8).float().numpy()
    data, _ = encode_envmap(env, "exr", attributes=envmap_attributes((0, 1, 2), 0.5, "job"))
    (tmp_path / "env.exr").write_bytes(data)
    tex = run_consumer("exr", tmp_path / "env.exr")
    assert (tex["width"], tex["height"]) == (16, 8)
    assert tex["flipY"] is False and tex["colorSpace"] == "srgb-linear"
    rgba = np.asarray(tex["data"], np.float32).reshape(8, 16, 4)
    # EXRLoader hands rows to WebGL bottom row first (and flipY = false): row 0 is our last row
    np.testing.assert_allclose(rgba[::-1, :, :3], env, rtol=1e-6)


def test_khronos_validator_accepts_our_glb(node_consumers, tmp_path):
    from core.export.gltf import build_glb
    from core.export.prefilter import prefiltered_cubemap

    env = lamp_map(32) * 10
    mips = [m.numpy() for m in prefiltered_cubemap(env, 16, levels=3)]
    (tmp_path / "probe.glb").write_bytes(build_glb(mips, project_sh(env).numpy(), (0.5, 1.0, -2.0), 0.25))
    report = run_consumer("gltf", tmp_path / "probe.glb")
    assert_valid_glb(report)


def assert_valid_glb(report: dict) -> None:
    issues = report["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:10]
    codes = {m["code"] for m in issues["messages"]}
    # infos only: the validator does not know the vendor extension, so it cannot see that it uses the images
    assert codes <= {"UNSUPPORTED_EXTENSION", "UNUSED_OBJECT"}, codes
    assert report["mimeType"] == "model/gltf-binary"


def test_ktx2_cube_mips_parse_in_threes_ktx_parse(node_consumers, tmp_path):
    from core.export.ktx2 import encode_ktx2_cubemap
    from core.export.prefilter import prefiltered_cubemap

    for scale, vk, type_size in ((1.0, 97, 2), (1e4, 109, 4)):  # half, then float32 beyond the half range
        mips = [m.numpy() * scale for m in prefiltered_cubemap(lamp_map(16), 8, levels=3)]
        (tmp_path / "cube.ktx2").write_bytes(encode_ktx2_cubemap(mips))
        ktx = run_consumer("ktx2", tmp_path / "cube.ktx2")
        assert (ktx["vkFormat"], ktx["typeSize"], ktx["pixelWidth"], ktx["faceCount"], ktx["levelCount"]) == (vk, type_size, 8, 6, 3)
        assert ktx["dfd"]["colorPrimaries"] == 1 and ktx["dfd"]["transferFunction"] == 1  # BT.709, linear
        assert ktx["dfd"]["bytesPlane"][0] == 4 * type_size
        for mine, theirs in zip(mips, ktx["levels"]):
            got = np.asarray(theirs, np.float32).reshape(*mine.shape[:3], 4)
            np.testing.assert_allclose(got[..., :3], mine, rtol=1e-3, atol=1e-4 * scale)
