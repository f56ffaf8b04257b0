"""core/export: each consumer's conventions, tested numerically (real consumers: usd-core here,
three.js and the Khronos glTF validator in tests/test_export_node.py)."""
from __future__ import annotations

import io
import math
import zipfile

import numpy as np
import pytest
import torch

from core.conventions import equirect_directions
from core.cubemap import cubemap_directions, sample_cubemap
from core.envmap import sample_envmap, solid_angles
from core.sh import eval_sh, project_sh, sh_irradiance

H = 32


def lamp_map(height=H, direction=(0.4, 0.5, -0.75), kappa=200.0, peak=80.0):
    """Grey ambient + a sharp lobe: an env map with a clear main light."""
    d = equirect_directions(height, dtype=torch.float64)
    mu = torch.nn.functional.normalize(torch.tensor(direction, dtype=torch.float64), dim=0)
    lobe = peak * torch.exp(kappa * (d @ mu - 1.0))
    return (0.3 + lobe)[..., None] * torch.tensor([1.0, 0.8, 0.6], dtype=torch.float64)


def random_dirs(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)


def sample_np(img: np.ndarray, u: np.ndarray, v_from_top: np.ndarray) -> np.ndarray:
    """Nearest-pixel lookup at continuous (u, v) in [0, 1] (v from the top row)."""
    h, w = img.shape[:2]
    c = np.clip(np.floor(u * w).astype(int) % w, 0, w - 1)
    r = np.clip(np.floor(v_from_top * h).astype(int), 0, h - 1)
    return img[r, c]


# ------------------------------------------------------------------------------ prefilter
def test_prefiltered_levels_match_direct_quadrature_of_the_ggx_kernel():
    from core.export.prefilter import lobe_weight, prefiltered_cubemap, roughness_of_level

    env = lamp_map(64)
    mips = prefiltered_cubemap(env, 32, levels=4)
    assert [m.shape for m in mips] == [(6, 32, 32, 3), (6, 16, 16, 3), (6, 8, 8, 3), (6, 4, 4, 3)]
    assert torch.allclose(mips[0], sample_cubemap(mips[0], cubemap_directions(32)), atol=1e-6)
    d = equirect_directions(64, dtype=torch.float64).reshape(-1, 3)
    w_pix = solid_angles(64, dtype=torch.float64).reshape(-1)
    for i in range(1, 4):
        n = cubemap_directions(mips[i].shape[1], dtype=torch.float64).reshape(-1, 3)
        w = lobe_weight(n @ d.T, roughness_of_level(i, 4)) * w_pix
        ref = (w @ env.reshape(-1, 3)) / w.sum(1, keepdim=True)
        got = mips[i].reshape(-1, 3).double()
        assert float((got - ref).abs().sum() / ref.abs().sum()) < 0.02, i
    # rougher levels are blurrier: the peak falls, energy spreads
    peaks = [float(m.max()) for m in mips]
    assert peaks == sorted(peaks, reverse=True)


def test_prefilter_keeps_a_constant_map_constant_and_samples_sharp_levels():
    from core.export.prefilter import prefiltered_cubemap

    mips = prefiltered_cubemap(torch.full((32, 64, 3), 0.7), 128, levels=3, samples=16)
    for m in mips:
        assert torch.allclose(m, torch.full_like(m, 0.7), atol=1e-5)
    with pytest.raises(ValueError, match="power of two"):
        prefiltered_cubemap(torch.ones(8, 16, 3), 24)


# ------------------------------------------------------------------------------ KTX2
def test_ktx2_cube_round_trip_and_header():
    import struct

    from core.export.ktx2 import IDENTIFIER, decode_ktx2_cubemap, encode_ktx2_cubemap

    levels = [np.random.default_rng(0).random((6, s, s, 3), np.float32) * 100 for s in (8, 4, 2)]
    blob = encode_ktx2_cubemap(levels)
    assert blob.startswith(IDENTIFIER)
    vk, type_size, w, h, depth, layers, faces, count, scheme = struct.unpack_from("<9I", blob, 12)
    assert (vk, type_size, w, h, depth, layers, faces, count, scheme) == (97, 2, 8, 8, 0, 0, 6, 3, 0)
    for lv, got in zip(levels, decode_ktx2_cubemap(blob)):
        np.testing.assert_allclose(got[..., :3], lv, rtol=1e-3)
        assert (got[..., 3] == 1).all()
        off = struct.unpack_from("<Q", blob, 80)[0]
        assert off % 8 == 0
    # beyond the half range (a bright lamp): float32 automatically, nothing clamped
    bright = [lv * 1e4 for lv in levels]
    blob = encode_ktx2_cubemap(bright)
    assert struct.unpack_from("<2I", blob, 12) == (109, 4)
    for lv, got in zip(bright, decode_ktx2_cubemap(blob)):
        np.testing.assert_array_equal(got[..., :3], lv)


# ------------------------------------------------------------------------------ glTF
def test_glb_structure_rgbd_round_trip_and_irradiance_sh():
    from core.export.gltf import build_glb, read_glb, rgbd_decode

    env = lamp_map(32) * 10  # peak 800 > RGBD's 255: the intensity multiplier must carry it
    from core.export.prefilter import prefiltered_cubemap

    mips = [m.numpy() for m in prefiltered_cubemap(env, 16, levels=3)]
    sh = project_sh(env)
    doc, blob = read_glb(build_glb(mips, sh.numpy(), (1.0, 2.0, 3.0), 0.5, extras={"artefact": "abc"}))
    light = doc["extensions"]["EXT_lights_image_based"]["lights"][0]
    assert doc["extensionsUsed"] == ["EXT_lights_image_based"]
    assert doc["scenes"][0]["extensions"]["EXT_lights_image_based"]["light"] == 0
    assert light["specularImageSize"] == 16 and len(light["specularImages"]) == 3
    assert light["intensity"] == 1.0  # the scale RGBD needs is in extras (Babylon applies intensity twice)
    radiance_scale = doc["nodes"][0]["extras"]["radianceScale"]
    assert radiance_scale > 1.0
    # irradiance SH in Babylon's basis (Condon-Shortley phase): E(n) = sum E_k Y_k^CS(n) is our irradiance
    e_k = torch.tensor(light["irradianceCoefficients"], dtype=torch.float64) * radiance_scale
    cs = torch.tensor([1.0, -1, 1, -1, 1, -1, 1, -1, 1], dtype=torch.float64)[:, None]
    n = random_dirs(16)
    assert torch.allclose(eval_sh(e_k * cs, n), sh_irradiance(sh, n), rtol=1e-6)
    # a face decodes back (RGBD, un-mirrored, times intensity) to the float face
    view = doc["bufferViews"][doc["images"][light["specularImages"][1][4]]["bufferView"]]
    png = blob[view["byteOffset"]:view["byteOffset"] + view["byteLength"]]
    rgbd = _png_rgba(png)
    face = rgbd_decode(rgbd)[:, ::-1] * radiance_scale
    np.testing.assert_allclose(face, mips[1][4], rtol=0.05, atol=0.02 * float(mips[1][4].max()))


def _png_rgba(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGBA"))


# ------------------------------------------------------------------------------ EXR metadata
def test_envmap_exr_carries_colour_space_probe_time_units_and_artefact():
    from core.export.metadata import REC709_CHROMATICITIES, envmap_attributes
    from core.io.envmap_io import encode_envmap, load_envmap
    from core.io.exr import read_exr_header

    env = lamp_map(8).float().numpy()
    data, _ = encode_envmap(env, "exr", attributes=envmap_attributes((1, 2, 3), 0.25, "job-1", extrapolated="x"))
    header = read_exr_header(data)
    np.testing.assert_allclose(header["chromaticities"], REC709_CHROMATICITIES, rtol=1e-6)
    np.testing.assert_allclose(header["lightfield:probePosition"], [1, 2, 3])
    assert header["lightfield:time"] == 0.25 and header["lightfield:artefactId"] == "job-1"
    assert "relative" in header["lightfield:units"] and header["lightfield:extrapolated"] == "x"
    np.testing.assert_array_equal(load_envmap(data), env)
    with pytest.raises(ValueError, match="reserved"):
        encode_envmap(env, "exr", attributes={"dataWindow": 1})


# ------------------------------------------------------------------------------ USD (usd-core)
def test_usdz_opens_in_usd_core_with_a_dome_light_in_openexr_latlong():
    """The .usdz usd-core packaged (UsdUtils.CreateNewARKitUsdzPackage) opens in usd-core, passes all
    its validators, and its DomeLight's texture is our map in OpenEXR's latlong layout."""
    pytest.importorskip("pxr", reason="usd-core is a dev dependency (pip install usd-core)")
    from pxr import Usd, UsdLux, UsdValidation

    from core.export.usd import openexr_latlong_direction, usdz
    from core.io.exr import read_exr, read_exr_header

    env = lamp_map(16).float()
    grade = {"grade": "partly explained", "seen_share": 0.4, "filled_share": 0.6, "residual_ratio": 0.7,
             "fallback": None}
    blob = usdz(env.numpy(), (0.5, 1.2, -2.0), 0.75, "job-9", grade)
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "probe.usdz"
        path.write_bytes(blob)
        stage = Usd.Stage.Open(str(path))
        assert stage is not None
        dome = UsdLux.DomeLight(stage.GetPrimAtPath("/Probe/EnvLight"))
        assert dome and dome.GetTextureFormatAttr().Get() == "latlong"
        texture = dome.GetTextureFileAttr().Get().path
        assert texture.endswith("envmap.exr")
        from pxr import UsdGeom

        assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
        layer_data = dict(stage.GetRootLayer().customLayerData)  # the job's grade: the nulls left out
        assert layer_data == {"lightfield:grade": "partly explained", "lightfield:seen_share": 0.4,
                              "lightfield:filled_share": 0.6, "lightfield:residual_ratio": 0.7}, layer_data
        xf = UsdGeom.Xformable(stage.GetPrimAtPath("/Probe")).ComputeLocalToWorldTransform(0)
        np.testing.assert_allclose(list(xf.ExtractTranslation()), [0.5, 1.2, -2.0])
        # usd-core's own validators (usdz package rules: stored, 64-byte aligned; references; stage metadata)
        validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
        errors = UsdValidation.ValidationContext(validators).Validate(stage)
        assert not errors, [(e.GetName(), e.GetMessage()) for e in errors]
    with zipfile.ZipFile(io.BytesIO(blob)) as z:
        assert z.namelist() == ["probe.usdc", texture]  # one flattened layer first, then its texture
        tex = z.read(texture)
        for info in z.infolist():  # usdz: stored, data 64-byte aligned; no restrictive mode bits
            assert info.compress_type == zipfile.ZIP_STORED
            assert (info.header_offset + 30 + len(info.filename) + len(info.extra)) % 64 == 0
            assert info.external_attr >> 16 in (0, 0o100644)
    header = read_exr_header(tex)
    assert str(header["envmap"]).endswith("LATLONG") and header["lightfield:artefactId"] == "job-9"
    assert "lightfield:t" not in header  # (the stage's customData carries t; the EXR its own time attribute)
    assert header["lightfield:time"] == 0.75
    img = read_exr(tex)
    rows, cols = np.meshgrid(np.arange(16), np.arange(32), indexing="ij")
    d = torch.from_numpy(openexr_latlong_direction(rows, cols, 16))  # where OpenEXR/UsdLux says each texel looks
    np.testing.assert_allclose(img, sample_envmap(env.double(), d).numpy(), rtol=1e-4, atol=1e-4)


# ------------------------------------------------------------------------------ Blender / Unity / ARKit / three.js
def test_blender_texture_read_with_cycles_mapping_gives_our_radiance():
    from core.export.blender import blender_equirect_uv, equirect_for_blender, to_blender

    env = lamp_map(64)
    tex = equirect_for_blender(env.numpy())
    d = random_dirs(200, seed=1)
    uv = blender_equirect_uv(to_blender(d.numpy()))
    got = sample_np(tex, uv[:, 0], 1.0 - uv[:, 1])
    want = sample_np(env.numpy(), *(_our_uv(d.numpy())))
    np.testing.assert_allclose(got, want, rtol=1e-9)
    # the image centre is +X in Blender, which is our +x: not our forward (-z -> Blender +Y)
    np.testing.assert_allclose(to_blender(np.array([0.0, 0.0, -1.0])), [0.0, 1.0, 0.0])


def _our_uv(d):
    theta = np.arccos(np.clip(d[:, 1], -1, 1))
    phi = np.arctan2(d[:, 0], -d[:, 2])
    return (phi + np.pi) / (2 * np.pi), theta / np.pi


def test_threejs_equirect_layout_matches_equirect_uv():
    from core.export.threejs import equirect_for_threejs, threejs_equirect_uv

    env = lamp_map(64).numpy()
    tex = equirect_for_threejs(env)
    d = random_dirs(200, seed=2).numpy()
    uv = threejs_equirect_uv(d)
    np.testing.assert_allclose(sample_np(tex, uv[:, 0], 1.0 - uv[:, 1]), sample_np(env, *_our_uv(d)), rtol=1e-9)


def test_unity_sh_through_unitys_shader_formula_gives_lambertian_radiance():
    from core.export.unity import probe_grid, to_unity, unity_sh, unity_shade_sh9

    env = lamp_map(32)
    sh = unity_sh(env.numpy())
    n = random_dirs(32, seed=3)
    got = unity_shade_sh9(sh, to_unity(n.numpy()))  # Unity evaluates with Unity-axis normals
    want = (sh_irradiance(project_sh(env), n) / math.pi).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9)
    # AddAmbientLight(c) adds c to k0: a uniform map of radiance c gives exactly k0 = c
    uniform = unity_sh(np.full((16, 32, 3), 0.25))
    np.testing.assert_allclose([ch[0] for ch in uniform], 0.25, rtol=1e-9)
    np.testing.assert_allclose([ch[1:] for ch in uniform], 0.0, atol=1e-9)
    assert probe_grid((0, 0, 0), (1, 2, 3), (2, 3, 1)).shape == (6, 3)


def test_arkit_slices_follow_the_metal_cube_table():
    from core.cubemap import equirect_to_cubemap
    from core.export.arkit import arkit_sh_planes, metal_cube_slices

    env = lamp_map(16).float()
    faces = equirect_to_cubemap(env, 8)
    slices = metal_cube_slices(faces.numpy())
    assert len(slices) == 6 and all(len(s) == 8 * 8 * 8 for s in slices)
    back = np.stack([np.frombuffer(s, "<f2").reshape(8, 8, 4) for s in slices]).astype(np.float32)
    np.testing.assert_allclose(back[..., :3], faces.numpy(), rtol=2e-3)
    srgb = metal_cube_slices(faces.numpy(), "rgba8Unorm_srgb", exposure_ev=-6)
    assert len(srgb[0]) == 8 * 8 * 4
    sh = project_sh(env.double())
    planes = arkit_sh_planes(sh.numpy())
    assert planes[:9] == pytest.approx(sh[:, 0].tolist()) and planes[18:] == pytest.approx(sh[:, 2].tolist())


def test_threejs_sh_is_ours_unsigned_and_arcore_differs_by_odd_m():
    from core.export.sh_layouts import to_arcore_27
    from core.export.threejs import threejs_sh

    sh = project_sh(lamp_map(16))
    three = np.array(threejs_sh(sh)).reshape(9, 3)
    arcore = np.array(to_arcore_27(sh)).reshape(9, 3)
    np.testing.assert_allclose(three, sh.numpy())
    np.testing.assert_allclose(three[[1, 3, 5, 7]], -arcore[[1, 3, 5, 7]])


# ------------------------------------------------------------------------------ sequences
def test_sequence_zip_streams_frames_with_metadata():
    from core.export.sequence import sequence_members, sequence_times, zip_stream
    from core.io.exr import read_exr, read_exr_header

    times = sequence_times(0.0, 1.0, 3)
    maps = [(t, np.full((4, 8, 3), t + 1, np.float32)) for t in times]
    chunks = list(zip_stream(sequence_members(maps, (0, 1, 2), "job-3")))
    assert len(chunks) >= 3  # streamed member by member, not built at the end
    with zipfile.ZipFile(io.BytesIO(b"".join(chunks))) as z:
        names = z.namelist()
        assert names == ["envmap.0001.exr", "envmap.0002.exr", "envmap.0003.exr", "sequence.json"]
        for (t, m), name in zip(maps, names):
            data = z.read(name)
            np.testing.assert_array_equal(read_exr(data), m)
            assert read_exr_header(data)["lightfield:time"] == pytest.approx(t)
    with pytest.raises(ValueError):
        sequence_times(0, 1, 0)


def test_openimageio_reads_the_sequence_with_time_code_rate_and_acescg_chromaticities(tmp_path):
    """OpenImageIO (the VFX tools' image library) reads the unzipped sequence: frame rate, SMPTE
    time code, AP1 chromaticities, and pixels equal to OIIO's own Rec. 709 -> ACEScg conversion."""
    oiio = pytest.importorskip("OpenImageIO", reason="OpenImageIO is a dev dependency (pip install OpenImageIO)")
    from core.export.metadata import ACESCG_CHROMATICITIES
    from core.export.sequence import sequence_fps, sequence_members, sequence_times, zip_stream
    from core.io.exr import read_exr_header

    times = sequence_times(0.0, 2.0, 49)  # 24 frames per second
    maps = [(t, lamp_map(8).float().numpy() * (1 + t)) for t in times]
    blob = b"".join(zip_stream(sequence_members(maps, (0, 1, 2), "job", fps=sequence_fps(times), colour="acescg")))
    with zipfile.ZipFile(io.BytesIO(blob)) as z:
        assert all(info.external_attr >> 16 == 0o100644 for info in z.infolist())  # regular files, rw-r--r--
        z.extractall(tmp_path)
    assert (tmp_path / "envmap.0030.exr").stat().st_mode & 0o777 == 0o644
    frame = 30  # t = 29 / 24 s = 00:00:01 frame 05 at 24 fps
    path = str(tmp_path / f"envmap.{frame:04d}.exr")
    spec = oiio.ImageInput.open(path).spec()
    assert spec.getattribute("framesPerSecond") == (24, 1)
    np.testing.assert_allclose(spec.getattribute("chromaticities"), ACESCG_CHROMATICITIES, rtol=1e-6)
    code = read_exr_header(path)["timeCode"]
    assert (code.hours, code.minutes, code.seconds, code.frame) == (0, 0, 1, 5)
    # OIIO's own colour management (its built-in OCIO config) converts our Rec. 709 map to ACEScg like ours
    src = oiio.ImageBuf(oiio.ImageSpec(16, 8, 3, oiio.FLOAT))
    src.set_pixels(oiio.ROI(), np.ascontiguousarray(maps[frame - 1][1], np.float32))
    theirs = oiio.ImageBufAlgo.colorconvert(src, "Linear Rec.709 (sRGB)", "ACEScg").get_pixels(oiio.FLOAT)
    ours = oiio.ImageBuf(path).get_pixels(oiio.FLOAT)
    np.testing.assert_allclose(ours, theirs, rtol=2e-4, atol=1e-6)
    # and every frame reads back as a sequence of the documented name pattern
    assert sorted(p.name for p in tmp_path.glob("envmap.*.exr"))[::24] == ["envmap.0001.exr", "envmap.0025.exr",
                                                                            "envmap.0049.exr"]


# ------------------------------------------------------------------ the SH layout table
@pytest.mark.parametrize("name", ["arcore", "threejs", "babylon", "unity", "arkit", "gltf"])
def test_every_sh_layout_round_trips_and_says_what_it_is(name):
    from core.export.sh_layouts import get_layout, pack, to_layout, unpack

    sh = project_sh(lamp_map(16))
    np.testing.assert_allclose(unpack(pack(sh, name), name), sh.numpy(), rtol=1e-12, atol=1e-12)
    layout = get_layout(name)
    values = to_layout(sh, name)
    flat = np.asarray(pack(sh, name))
    np.testing.assert_allclose(flat, (values.T if layout.packing == "channel_planes" else values).reshape(-1))
    assert layout.reads_it and layout.checked_by and layout.name in layout.describe()


def test_unity_row_is_the_z_mirrored_maps_projection():
    """The table's Unity signs (k = 2, 5, 7) equal re-projecting the map mirrored in z, as Unity's
    left-handed axes see it."""
    from core.envmap import mirror_envmap
    from core.export.sh_layouts import get_layout
    from core.export.unity import unity_sh

    env = lamp_map(32)
    mirrored = project_sh(mirror_envmap(env, "z")).numpy()
    unity = get_layout("unity")
    np.testing.assert_allclose(np.asarray(unity_sh(env.numpy())).T, mirrored * np.asarray(unity.scale)[:, None],
                               rtol=1e-9, atol=1e-12)
    assert [k for k, s in enumerate(unity.signs) if s < 0] == [2, 5, 7]


def test_covered_region_undoes_the_fields_margin_and_the_default_grid_stays_inside():
    from core.export.coverage import cell_centre_grid, covered_region, inside
    from core.fields.components.normalization import SceneBounds

    points = torch.tensor([[0.0, 0.0, -4.0], [5.0, 2.8, 0.0]] * 50, dtype=torch.float64)
    bounds = SceneBounds.from_points(points)  # the room [0, 5] x [0, 2.8] x [-4, 0], padded 10 % per side
    lo, hi, source = covered_region(bounds)
    np.testing.assert_allclose(lo, [0.0, 0.0, -4.0], atol=0.06)
    np.testing.assert_allclose(hi, [5.0, 2.8, 0.0], atol=0.06)
    grid = cell_centre_grid(lo, hi, (3, 2, 3))
    assert grid.shape == (18, 3) and inside(lo, hi, grid).all() and "margin" in source
    assert not inside(lo, hi, [bounds.lo]).any()  # the padded box's corner is outside the room


def test_the_products_record_the_jobs_grade():
    """glTF's probe node extras and the Unity grid carry the job's grade and share seen vs filled
    (USD's customLayerData: the usdz test above)."""
    from core.export.gltf import read_glb
    from core.export.products import probe_glb
    from core.export.schema import AnswerGrade
    from core.export.unity import unity_probe_grid
    from core.fields import SceneBounds

    meta = {"quality": {"grade": "worse than a constant map", "residual_ratio": 1.3, "seen_share": 0.35,
                        "fallback": {"reason": "the field re-renders the frames worse than the constant map"}}}
    grade = AnswerGrade.of(meta)
    assert grade.seen_share == 0.0 and grade.filled_share == 1.0 and "constant map" in grade.fallback
    assert AnswerGrade.of({}).grade == "unchecked"
    env = lamp_map(16).float()
    doc, _ = read_glb(probe_glb(env, (0.0, 1.0, 0.0), 0.5, 16, 2, "job-1", grade=grade.model_dump()))
    assert doc["nodes"][0]["extras"]["grade"] == grade.model_dump()
    grid = unity_probe_grid(lambda x: (env, {"x": False, "t": False}),
                            SceneBounds.from_points(torch.tensor([[-1.0, 0, -1], [1, 2, 1]])), (1, 1, 1), None,
                            "job-1", grade=grade)
    assert grid.model_dump()["grade"]["grade"] == "worse than a constant map"
