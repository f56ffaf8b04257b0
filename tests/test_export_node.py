"""Our outputs through real JavaScript consumers (tests/node: three.js r187, Khronos glTF
validator), installed by `npm ci` from the project's own lock file."""
from __future__ import annotations

import json
import math

import numpy as np
import torch

from core.envmap import irradiance
from core.export.sh_layouts import to_arcore_27
from core.sh import eval_sh, project_sh, sh_irradiance
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
    from core.export.products import probe_glb

    env = lamp_map(32) * 10
    mips = [m.numpy() for m in prefiltered_cubemap(env, 16, levels=3)]
    (tmp_path / "probe.glb").write_bytes(build_glb(mips, project_sh(env).numpy(), (0.5, 1.0, -2.0), 0.25))
    report = run_consumer("gltf", tmp_path / "probe.glb")
    assert_valid_glb(report)
    # with the main light: KHR_lights_punctual is a Khronos extension the validator checks in full
    (tmp_path / "lit.glb").write_bytes(probe_glb(env.float(), (0.5, 1.0, -2.0), 0.25, size=16))
    report = run_consumer("gltf", tmp_path / "lit.glb")
    assert_valid_glb(report)
    assert "KHR_lights_punctual" in report["info"]["extensionsUsed"]


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
        assert (ktx["vkFormat"], ktx["typeSize"], ktx["pixelWidth"], ktx["faceCount"], ktx["levelCount"]) == (
            vk,
            type_size,
            8,
            6,
            3,
        )
        assert ktx["dfd"]["colorPrimaries"] == 1 and ktx["dfd"]["transferFunction"] == 1  # BT.709, linear
        assert ktx["dfd"]["bytesPlane"][0] == 4 * type_size
        for mine, theirs in zip(mips, ktx["levels"]):
            got = np.asarray(theirs, np.float32).reshape(*mine.shape[:3], 4)
            np.testing.assert_allclose(got[..., :3], mine, rtol=1e-3, atol=1e-4 * scale)


# ------------------------------------------------------------------------------ Babylon.js
AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}
LUMA = np.array([0.2126, 0.7152, 0.0722])


def simulated_rooms():
    """Ground-truth env maps of two simulated rooms (core.sim), at probes with a clear lamp."""
    from core.sim.render import render_envmap
    from core.sim.suites import suite

    spatial, hard = suite("spatial"), suite("hard")
    return {"spatial probe 0": render_envmap(spatial, spatial.probes[0].x, 0.0, height=64).float(),
            "hard probe 1": render_envmap(hard, hard.probes[1].x, 0.0, height=64).float()}


def babylon_irradiance(tmp_path, glb: bytes, env: torch.Tensor, size: int = 64) -> dict:
    """Babylon.js' own numbers for a .glb and the map it was made from (tests/node/consumers.mjs
    `babylon`): E(n) from the loader's polynomial and from Babylon's projection of the map's cube."""
    from core.cubemap import equirect_to_cubemap

    normals = list(AXES.values()) + random_dirs(32, seed=7).tolist()
    (tmp_path / "probe.glb").write_bytes(glb)
    equirect_to_cubemap(env, size).numpy().astype("<f4").tofile(tmp_path / "faces.f32")
    (tmp_path / "req.json").write_text(
        json.dumps(
            {"glb": str(tmp_path / "probe.glb"), "faces": str(tmp_path / "faces.f32"), "size": size, "normals": normals}
        )
    )
    out = run_consumer("babylon", tmp_path / "req.json")
    out["normals"] = np.asarray(normals, np.float64)
    return out


def axis_errors(got: np.ndarray, want: np.ndarray, of_peak: bool = False) -> dict[str, float]:
    """Luminance error of irradiance along each axis (the first six normals), relative to the
    irradiance there, or with `of_peak` to the brightest irradiance over all the normals (where
    the irradiance along an axis is near 0)."""
    g, w = got @ LUMA, want @ LUMA
    return {name: float((g[i] - w[i]) / (np.abs(w).max() if of_peak else w[i])) for i, name in enumerate(AXES)}


def _fmt(errors: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:+.1%}" for k, v in errors.items())


def test_babylon_lights_the_glb_like_its_own_projection_of_the_map(node_consumers, tmp_path):
    """Babylon's glTF loader turns our irradianceCoefficients into the diffuse light Babylon's own
    cube -> SH projection gives for the same map (per axis), and the pre-fix coefficients (no
    Condon-Shortley phase) are measurably mirrored."""
    from core.export.gltf import read_glb
    from core.export.products import probe_glb

    for room, env in simulated_rooms().items():
        glb = probe_glb(env, (0, 1, 0), 0.0, size=32, main_light=False)
        doc, _ = read_glb(glb)
        scale = doc["nodes"][0]["extras"]["radianceScale"]
        out = babylon_irradiance(tmp_path, glb, env)
        assert out["environment"] and out["level"] == 1.0 and out["lights"] == []
        ours, theirs = np.asarray(out["glb"]) * scale, np.asarray(out["cube"])
        # the loader reads the coefficients as the irradiance we meant (Babylon's numbers are E / pi)
        want = sh_irradiance(project_sh(env.double()), torch.from_numpy(out["normals"])).numpy() / math.pi
        np.testing.assert_allclose(ours, want, rtol=1e-5, atol=1e-6 * np.abs(want).max())
        errors = axis_errors(ours, theirs)
        print(f"\nBabylon.js, {room}: glb irradiance vs Babylon's projection of the map, per axis: {_fmt(errors)}")
        # what remains is Babylon sampling the map on a 64-texel cube against our exact per-pixel projection
        assert max(abs(e) for e in errors.values()) < 0.03, errors
        # what the writer did before (our signs, no phase): Babylon mirrors the light in x and y
        unphased = _rewrite_coefficients(glb, lambda c: c * np.array([1, -1, 1, -1, 1, -1, 1, -1, 1.0])[:, None])
        wrong = axis_errors(
            np.asarray(babylon_irradiance(tmp_path, unphased, env)["glb"]) * scale, theirs, of_peak=True
        )
        print(f"Babylon.js, {room}: the same without the Condon-Shortley phase (of the peak): {_fmt(wrong)}")
        assert max(abs(wrong[a]) for a in ("+x", "-x", "+y", "-y")) > 0.1


def _rewrite_coefficients(glb: bytes, change) -> bytes:
    import pygltflib

    doc = pygltflib.GLTF2.load_from_bytes(glb)
    light = doc.extensions["EXT_lights_image_based"]["lights"][0]
    light["irradianceCoefficients"] = change(np.asarray(light["irradianceCoefficients"])).tolist()
    return b"".join(doc.save_to_bytes())


def test_babylon_main_light_plus_ambient_sh_give_the_maps_irradiance(node_consumers, tmp_path):
    """With the main light: Babylon's DirectionalLight (KHR_lights_punctual) + the ambient SH add up
    to Babylon's own projection of the whole map, and the light shines from the lamp."""
    from core.export.gltf import read_glb
    from core.export.products import probe_glb
    from core.lights import extract_dominant_light

    for room, env in simulated_rooms().items():
        light = extract_dominant_light(env.double())
        assert light.found, light.reason
        glb = probe_glb(env, (0, 1, 0), 0.0, size=32)
        scale = read_glb(glb)[0]["nodes"][0]["extras"]["radianceScale"]
        out = babylon_irradiance(tmp_path, glb, env)
        (sun,) = out["lights"]
        assert sun["type"] == "DirectionalLight"
        np.testing.assert_allclose(sun["travels"], -light.direction.double().numpy(), atol=1e-6)
        np.testing.assert_allclose(
            np.multiply(sun["diffuse"], sun["intensity"]) * scale, light.intensity_rgb.double().numpy(), rtol=1e-5
        )
        facing = np.clip(out["normals"] @ -np.asarray(sun["travels"]), 0, None)[:, None]
        # Babylon's diffuse IBL is E / pi; the directional light gives E = intensity x cos
        split = (
            np.asarray(out["glb"]) * scale * math.pi + facing * np.multiply(sun["diffuse"], sun["intensity"]) * scale
        )
        truth = irradiance(env.double(), torch.from_numpy(out["normals"])).numpy()  # the map's, by quadrature
        sh_only = np.asarray(out["cube"]) * math.pi  # Babylon's 9 coefficients of the whole map
        errors, sh_errors = axis_errors(split, truth, of_peak=True), axis_errors(sh_only, truth, of_peak=True)
        print(f"\nBabylon.js, {room}: ambient SH + main light vs the map's irradiance, per axis (of the peak): "
              f"{_fmt(errors)}; Babylon's own SH of the whole map: {_fmt(sh_errors)}")
        worst = float(np.abs((split - truth) @ LUMA).max() / np.abs(truth @ LUMA).max())
        assert worst < max(0.05, 2 * light.irradiance_error), (worst, errors)
