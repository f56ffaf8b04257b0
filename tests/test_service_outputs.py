"""The hand-off endpoints over real HTTP (uvicorn + redis-server + Celery worker): SH layouts with
the main light's confidence and reason, KTX2 prefiltered cubes, glTF (Khronos validator), USDZ
(usd-core), EXR sequences, EXR metadata, offline /docs and /redoc."""
from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest

from test_service_e2e import inside_point, submit, wait_job

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def stack(service_stack):
    return service_stack


@pytest.fixture(scope="module")
def job(stack, tiny_image):
    with stack.client() as c:
        job = submit(c, tiny_image)
        final = wait_job(c, job)
        assert final["state"] == "succeeded", (final, stack.log("worker0"))
        assert final["message"] == "light field ready"  # not the baking step's "precomputing quality=baked"
        return job


def test_sh_layouts_agree_and_the_light_says_how_sure_it_is(stack, job):
    with stack.client() as c:
        x = inside_point(c, job)
        arcore = c.get(f"/lightfield/{job}/sh", params={"x": x}).json()
        three = c.get(f"/lightfield/{job}/sh", params={"x": x, "layout": "threejs"}).json()
    assert arcore["layout"] == "arcore" and three["layout"] == "threejs"
    with stack.client() as c:  # the job's self-check travels with every answer
        sh = c.get(f"/lightfield/{job}/sh", params={"x": x})
        env = c.get(f"/lightfield/{job}/envmap", params={"x": x, "height": 8})
        info = c.get(f"/lightfield/{job}").json()
    grade = info["metadata"]["quality"]
    assert grade["grade"] in ("explained", "partly explained", "worse than a constant map"), grade
    assert sh.headers["X-Lightfield-Grade"] == env.headers["X-Lightfield-Grade"]
    assert sh.headers["X-Lightfield-Grade"].startswith(f"{grade['grade']}; residual_ratio={grade['residual_ratio']}")
    assert f"seen={grade['seen_share']}" in sh.headers["X-Lightfield-Grade"]
    seen = grade["seen_share"]
    answer = {"grade": grade["grade"], "seen_share": seen, "filled_share": round(1 - seen, 4),
              "residual_ratio": grade["residual_ratio"], "fallback": None}  # every JSON answer carries it
    assert sh.json()["grade"] == info["grade"] == answer, (sh.json()["grade"], info["grade"])
    a = np.reshape(arcore["coefficients"], (9, 3))
    t = np.reshape(three["coefficients"], (9, 3))
    np.testing.assert_allclose(t[[0, 2, 4, 6, 8]], a[[0, 2, 4, 6, 8]], rtol=1e-6)
    np.testing.assert_allclose(t[[1, 3, 5, 7]], -a[[1, 3, 5, 7]], rtol=1e-6)
    assert arcore["arcore_27"] == arcore["coefficients"] == three["arcore_27"]
    light = arcore["dominant_light"]
    assert 0.0 <= light["confidence"] <= 1.0 and light["reason"]
    assert light["found"] == light["reason"].startswith("found")
    assert np.linalg.norm(light["direction"]) == pytest.approx(1.0, abs=1e-5)
    # ambient + light = the whole map: DC of the full SH exceeds the ambient's by the light's share
    full = np.reshape(arcore["coefficients_with_light"], (9, 3))
    assert (full[0] >= a[0] - 1e-6).all()


def test_unity_and_arkit_endpoints_serve_the_clis_models(stack, job):
    """/unity and /arkit answer the same pydantic models the CLI writes (core.export.schema), the
    grid's probes flagged per probe; /cubemap's OpenAPI lists the KTX2 media type it serves."""
    import base64

    from core.export.schema import ArkitProbe, SphericalHarmonics, UnityProbeGrid

    with stack.client() as c:
        x = inside_point(c, job)
        unity = c.get(f"/lightfield/{job}/unity", params={"grid": "2,1,2"})
        outside = c.get(f"/lightfield/{job}/unity", params={"grid": "2,1,1", "lo": "-50,-50,-50", "hi": "50,50,50"})
        arkit = c.get(f"/lightfield/{job}/arkit", params={"x": x, "size": 8})
        sh = c.get(f"/lightfield/{job}/sh", params={"x": x, "layout": "babylon"})
        bad = c.get(f"/lightfield/{job}/unity", params={"grid": "9,9,9"})
        openapi = c.get("/openapi.json").json()
    assert unity.status_code == 200, unity.text
    grid = UnityProbeGrid.model_validate(unity.json())
    assert (
        len(grid.probes) == 4 and grid.extrapolated_probes == 0 and unity.headers["X-Lightfield-Extrapolated"] == "none"
    )
    far = UnityProbeGrid.model_validate(outside.json())
    assert far.extrapolated_probes == 2 and all(p.extrapolated.x for p in far.probes)
    assert outside.headers["X-Lightfield-Extrapolated"] == "x"
    probe = ArkitProbe.model_validate(arkit.json())
    assert probe.bytes_per_row == 64 and [len(base64.b64decode(s)) for s in probe.slices_base64] == [512] * 6
    assert SphericalHarmonics.model_validate(sh.json()).layout == "babylon"
    assert grid.grade == probe.grade and grid.grade.grade != "unchecked" and 0 < grid.grade.seen_share <= 1
    assert bad.status_code == 413 and bad.json()["error"]["code"] == "grid_too_large"
    content = openapi["paths"]["/lightfield/{job_id}/cubemap"]["get"]["responses"]["200"]["content"]
    assert {"application/json", "application/x-npy", "image/ktx2"} <= set(content)


def test_prefiltered_cubemap_is_a_binary_ktx2(stack, job):
    from core.export.ktx2 import decode_ktx2_cubemap

    with stack.client() as c:
        x = inside_point(c, job)
        resp = c.get(f"/lightfield/{job}/cubemap", params={"x": x, "size": 16, "format": "ktx2"})
        assert resp.status_code == 200 and resp.headers["content-type"] == "image/ktx2"
        levels = decode_ktx2_cubemap(resp.content)
        npy = np.load(
            io.BytesIO(c.get(f"/lightfield/{job}/cubemap", params={"x": x, "size": 16, "format": "npy"}).content)
        )
        assert [lv.shape[1] for lv in levels] == [16, 8, 4]
        np.testing.assert_allclose(levels[0][..., :3], npy, rtol=2e-3, atol=1e-4)
        bad = c.get(f"/lightfield/{job}/cubemap", params={"x": x, "size": 12, "format": "ktx2"})
        assert bad.status_code == 422 and "power of two" in bad.json()["error"]["message"]


def test_gltf_endpoint_passes_the_khronos_validator(stack, job, tmp_path, node_consumers):
    from node_consumers import run_consumer
    from test_export_node import assert_valid_glb

    with stack.client() as c:
        resp = c.get(f"/lightfield/{job}/gltf", params={"x": inside_point(c, job), "size": 16})
    assert resp.status_code == 200 and resp.headers["content-type"] == "model/gltf-binary"
    (tmp_path / "probe.glb").write_bytes(resp.content)
    assert_valid_glb(run_consumer("gltf", tmp_path / "probe.glb"))


def test_usdz_endpoint_opens_in_usd_core(stack, job, tmp_path):
    pytest.importorskip("pxr", reason="usd-core is a dev dependency")
    from pxr import Usd, UsdLux

    with stack.client() as c:
        resp = c.get(f"/lightfield/{job}/usdz", params={"x": inside_point(c, job), "height": 16})
    assert resp.status_code == 200
    (tmp_path / "probe.usdz").write_bytes(resp.content)
    stage = Usd.Stage.Open(str(tmp_path / "probe.usdz"))
    assert UsdLux.DomeLight(stage.GetPrimAtPath("/Probe/EnvLight")).GetTextureFormatAttr().Get() == "latlong"
    assert stage.GetRootLayer().customLayerData["lightfield:grade"] == resp.headers["X-Lightfield-Grade"].split(";")[0]


def test_sequence_streams_a_zip_of_exrs_with_metadata(stack, job):
    from core.io.exr import read_exr_header

    with stack.client() as c:
        x = inside_point(c, job)
        with c.stream("GET", f"/lightfield/{job}/sequence",
                      params={"x": x, "t0": 0, "t1": 0, "frames": 3, "height": 8}) as resp:
            assert resp.status_code == 200 and resp.headers["content-type"] == "application/zip"
            body = b"".join(resp.iter_bytes())
        too_many = c.get(f"/lightfield/{job}/sequence", params={"x": x, "t0": 0, "t1": 1, "frames": 100000})
        backwards = c.get(f"/lightfield/{job}/sequence", params={"x": x, "t0": 1, "t1": 0, "frames": 2})
    assert too_many.status_code == 413 and too_many.json()["error"]["code"] == "frames_too_large"
    assert backwards.status_code == 422
    with zipfile.ZipFile(io.BytesIO(body)) as z:
        index = json.loads(z.read("sequence.json"))
        assert len(index["frames"]) == 3
        header = read_exr_header(z.read(index["frames"][0]["file"]))
    assert header["lightfield:artefactId"] == job


def test_envmap_exr_says_where_when_and_what(stack, job):
    from core.io.exr import read_exr_header

    with stack.client() as c:
        x = inside_point(c, job)
        resp = c.get(f"/lightfield/{job}/envmap", params={"x": x, "t": 0, "height": 8, "format": "exr"})
    header = read_exr_header(resp.content)
    np.testing.assert_allclose(header["lightfield:probePosition"], [float(v) for v in x.split(",")], rtol=1e-5)
    assert header["lightfield:artefactId"] == job and header["lightfield:time"] == 0.0
    assert len(header["chromaticities"]) == 8


def test_docs_and_redoc_are_served_without_a_cdn(stack):
    import httpx

    for page, assets in (("/docs", ("swagger-ui-bundle.js", "swagger-ui.css")), ("/redoc", ("redoc.standalone.js",))):
        html = httpx.get(stack.base_url + page, timeout=10)
        assert html.status_code == 200
        assert "cdn.jsdelivr" not in html.text and "unpkg.com" not in html.text and "fonts.googleapis" not in html.text
        for name in assets:
            assert f"/docs-assets/{name}" in html.text
            asset = httpx.get(f"{stack.base_url}/docs-assets/{name}", timeout=10)
            assert asset.status_code == 200 and len(asset.content) > 10_000
