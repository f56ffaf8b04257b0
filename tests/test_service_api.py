"""The HTTP API against a real stack (redis-server + Celery worker + uvicorn subprocesses):
auth, tenant isolation, every bad input of issue 5 answered with its 4xx, and the schema.
No job here needs to finish; see test_service_e2e.py for full runs."""
from __future__ import annotations

import io
import json
import struct
import zlib

import numpy as np
import pytest


def _error(resp, status: int, code: str | None = None) -> dict:
    assert resp.status_code == status, resp.text
    body = resp.json()
    assert set(body) == {"error"} and set(body["error"]) == {"code", "message"}, body
    if code is not None:
        assert body["error"]["code"] == code, body
    assert body["error"]["message"]
    return body["error"]


def _png_bomb(width: int = 40000, height: int = 40000) -> bytes:
    """A valid, tiny PNG that declares width x height pixels (a decompression bomb)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    idat = zlib.compress(b"\x00" * 1024)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def _npz(depth: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, depth=depth)
    return buf.getvalue()


@pytest.fixture(scope="module")
def stack(service_stack):
    return service_stack


@pytest.fixture
def alice(stack):
    with stack.client("alice") as c:
        yield c


def test_health_ready_metrics_and_schema(stack, alice):
    assert alice.get("/healthz").json() == {"status": "ok", "dependencies": {}}  # distributed: none supervised
    ready = alice.get("/readyz")
    assert ready.status_code == 200 and ready.json()["workers"] >= 1
    metrics = alice.get("/metrics").text
    assert "lightfield_http_requests_total" in metrics and 'lightfield_jobs{state="queued"}' in metrics
    assert 'route="/healthz"' in metrics  # templated routes, not raw paths
    schema = alice.get("/openapi.json").json()
    for path in ("/jobs", "/jobs/{job_id}", "/jobs/{job_id}/events", "/lightfield/{job_id}",
                 "/lightfield/{job_id}/envmap", "/lightfield/{job_id}/envmaps", "/lightfield/{job_id}/sh",
                 "/lightfield/{job_id}/cubemap", "/healthz", "/readyz", "/metrics"):
        assert path in schema["paths"], path
    assert "multipart/form-data" in schema["paths"]["/jobs"]["post"]["requestBody"]["content"]
    assert "JobView" in schema["components"]["schemas"]


def test_requests_without_a_valid_key_are_401(stack):
    import httpx

    with httpx.Client(base_url=stack.base_url) as anon:
        _error(anon.get("/jobs"), 401, "unauthorized")
        _error(anon.get("/jobs", headers={"Authorization": "Bearer not-a-key"}), 401, "unauthorized")
        assert anon.get("/healthz").status_code == 200  # probes need no key


def _post(client, files: dict, params: dict | str | None = None):
    data = {}
    if params is not None:
        data["params"] = params if isinstance(params, str) else json.dumps(params)
    return client.post("/jobs", files=files, data=data)


BAD_INPUTS = [
    ("empty file", {"file": ("a.png", b"")}, None, 422, "empty"),
    ("text file", {"file": ("a.png", b"hello, I am not an image at all")}, None, 415, "not_media"),
    ("truncated png", "truncated_png", None, 422, "truncated"),
    ("truncated video", "truncated_video", None, 422, None),
    ("decompression bomb", {"file": ("bomb.png", _png_bomb())}, None, 413, "too_many_pixels"),
    ("heif image", {"file": ("a.heic", b"\x00\x00\x00\x18ftypheic" + b"\x00" * 64)}, None, 415, "unsupported_format"),
    ("unknown preset", "image", {"preset": "fastest"}, 422, "invalid_params"),
    ("unknown params field", "image", {"bogus": 1}, 422, "invalid_params"),
    ("params not json", "image", "{not json", 422, "invalid_params"),
    ("half intrinsics", "image", {"intrinsics": {"fx": 100}}, 422, "invalid_params"),
    ("pose count mismatch", "image", {"poses": [np.eye(4).ravel().tolist()] * 2}, 422, "invalid_poses"),
    ("pose not 16 numbers", "image", {"poses": [[1, 0, 0]]}, 422, "invalid_params"),
    ("exposure count mismatch", "image", {"frame_ev": [0.0, -1.0]}, 422, "invalid_frame_ev"),
    ("exposure not finite", "image", {"frame_ev": ["NaN"]}, 422, "invalid_params"),
    ("exposure neither numbers nor 'estimate'", "image", {"frame_ev": "guess"}, 422, "invalid_params"),
    ("weights outside model dirs", "image", {"prior": "diffusion", "prior_weights": "/etc"}, 422, "invalid_params"),
    ("depth size mismatch", "image+depth_small", None, 422, "invalid_depth"),
    ("depth all nan", "image+depth_nan", None, 422, "invalid_depth"),
    ("depth not a depth file", "image+depth_text", None, 415, "not_depth"),
    ("unknown form field", "image+extra", None, 422, "unknown_field"),
]


@pytest.fixture(scope="module")
def media(tiny_image, tiny_video):
    png = tiny_image.read_bytes()
    video = tiny_video.read_bytes()
    return {
        "image": {"file": ("room.png", png)},
        "truncated_png": {"file": ("room.png", png[: len(png) // 3])},
        "truncated_video": {"file": ("room.mp4", video[: len(video) // 4])},
        "image+depth_small": {"file": ("room.png", png), "depth": ("d.npz", _npz(np.ones((10, 10), np.float32)))},
        "image+depth_nan": {"file": ("room.png", png), "depth": ("d.npz", _npz(np.full((48, 64), np.nan, np.float32)))},
        "image+depth_text": {"file": ("room.png", png), "depth": ("d.npz", b"depth? no.")},
        "image+extra": {"file": ("room.png", png), "secret": ("x", b"1")},
    }


@pytest.mark.parametrize("label,files,params,status,code", BAD_INPUTS, ids=[b[0] for b in BAD_INPUTS])
def test_bad_input_gets_its_4xx_and_the_server_keeps_serving(stack, alice, media, label, files, params, status, code):
    files = media[files] if isinstance(files, str) else files
    err = _error(_post(alice, files, params), status, code)
    if code == "invalid_params" and isinstance(params, dict):
        assert next(iter(params)) in err["message"]  # the message names the offending field
    assert alice.get("/healthz").status_code == 200
    # nothing half-created: no job in the list, no files left behind
    assert all(j["state"] != "queued" or j["input_kind"] for j in alice.get("/jobs").json()["jobs"])
    assert not any(p.is_file() for p in (stack.data_dir / "uploads").rglob("*")) or _has_live_job(alice)


def _ns_zip(tmp, edit=None, extra_members=()) -> bytes:
    """A small nerfstudio capture zip (3 frames 16 x 12), its transforms.json edited by `edit`."""
    import zipfile

    from capture_fixtures import write_nerfstudio
    from core.camera import Intrinsics

    rng = np.random.default_rng(0)
    frames = rng.uniform(0, 1, (3, 12, 16, 3)).astype(np.float32)
    root = write_nerfstudio(tmp, frames, np.ones((3, 12, 16), np.float32), Intrinsics.from_hfov(16, 12, 60.0),
                            [np.eye(4)] * 3)
    meta = json.loads((root / "transforms.json").read_text())
    if edit:
        edit(meta)
    (root / "transforms.json").write_text(json.dumps(meta))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for p in sorted(root.rglob("*")):
            if p.is_file():
                z.write(p, p.relative_to(root).as_posix())
        for name, data in extra_members:
            z.writestr(name, data)
    return buf.getvalue()


ZIP_INPUTS = [
    ("scaled pose", lambda m: m["frames"][1].update(transform_matrix=(2 * np.eye(4)).tolist()), (), 422,
     "shape_mismatch", "frames[1].transform_matrix"),
    ("path traversal", lambda m: m["frames"][2].update(file_path="../../../etc/passwd"), (), 422, "not_found",
     "frames[2].file_path"),
    ("missing image", lambda m: m["frames"][0].update(file_path="images/nope.png"), (), 422, "not_found",
     "frames[0].file_path"),
    ("360 camera", lambda m: m.update(camera_model="EQUIRECTANGULAR"), (), 415, "unsupported_codec", "camera_model"),
    ("empty transforms.json", lambda m: m.clear(), (), 422, "shape_mismatch", "frames"),
    ("zip bomb member", None, (("images/zeros.bin", b"\0" * (8 << 20)),), 413, "too_large", "zip bomb"),
]


@pytest.mark.parametrize("label,edit,extra,status,code,names", ZIP_INPUTS, ids=[z[0] for z in ZIP_INPUTS])
def test_bad_capture_zips_get_a_4xx_naming_the_field(stack, alice, tmp_path, label, edit, extra, status, code, names):
    err = _error(_post(alice, {"file": ("scan.zip", _ns_zip(tmp_path, edit, extra))}), status, code)
    assert names in err["message"], err["message"]
    assert alice.get("/healthz").status_code == 200


def test_a_good_capture_zip_is_accepted(stack, alice, tmp_path):
    created = _post(alice, {"file": ("scan.zip", _ns_zip(tmp_path))}, {"fps": 2})
    assert created.status_code == 202, created.text
    assert created.json()["input_kind"] == "capture"
    alice.delete(f"/jobs/{created.json()['id']}")


def _has_live_job(client) -> bool:
    return any(j["state"] in ("queued", "running") for j in client.get("/jobs").json()["jobs"])


def test_body_that_is_not_multipart_is_415(alice):
    _error(alice.post("/jobs", json={"file": "x"}), 415, "not_multipart")


def test_byte_and_in_flight_limits(make_stack, tiny_image):
    # no worker: accepted jobs stay queued, so the in-flight limit is reached deterministically
    stack = make_stack(workers=0, LIGHTFIELD_MAX_UPLOAD_BYTES="100000", LIGHTFIELD_MAX_JOBS_IN_FLIGHT="1")
    with stack.client("alice") as alice, stack.client("bob") as bob:
        _error(alice.post("/jobs", files={"file": ("big.png", b"\x89PNG\r\n\x1a\n" + b"\0" * 200_000)}),
               413, "too_large")
        assert not any(p.is_file() for p in (stack.data_dir / "uploads").rglob("*"))
        first = _post(alice, {"file": ("room.png", tiny_image.read_bytes())})
        assert first.status_code == 202 and first.json()["state"] == "queued"
        refused = _post(alice, {"file": ("room.png", tiny_image.read_bytes())})
        _error(refused, 429, "too_many_jobs")
        assert int(refused.headers["retry-after"]) > 0  # issue 14: a 429 says when to retry
        assert _post(bob, {"file": ("room.png", tiny_image.read_bytes())}).status_code == 202  # per tenant
        # cancelling the queued job frees the slot at once (nobody holds its lease)
        assert alice.delete(f"/jobs/{first.json()['id']}").json()["state"] == "cancelled"
        assert _post(alice, {"file": ("room.png", tiny_image.read_bytes())}).status_code == 202
        _error(stack.client("alice").get("/readyz"), 503, "not_ready")  # no worker answers
        # issue 14: losing Redis (distributed mode: nothing restarts it) was a 500 internal_error
        stack.redis.stop()
        for resp in (alice.get("/jobs"), alice.get(f"/jobs/{first.json()['id']}"),
                     alice.get(f"/lightfield/{first.json()['id']}/envmap", params={"x": "0,0,0"}),
                     _post(bob, {"file": ("room.png", tiny_image.read_bytes())})):
            _error(resp, 503, "broker_unavailable")
            assert int(resp.headers["retry-after"]) > 0
        assert alice.get("/healthz").status_code == 200  # the API process itself is alive
        _error(alice.get("/readyz"), 503, "not_ready")
    assert "Traceback" not in stack.log("api")


def test_unknown_and_malformed_ids_are_404(alice):
    for path in ("/jobs/6f1c7c1e-3d0b-4c55-9a2f-0d8f2b7c1a11", "/jobs/../../etc/passwd", "/jobs/not-a-uuid",
                 "/lightfield/6f1c7c1e-3d0b-4c55-9a2f-0d8f2b7c1a11",
                 "/lightfield/6f1c7c1e-3d0b-4c55-9a2f-0d8f2b7c1a11/envmap?x=0,0,0"):
        _error(alice.get(path), 404)
    _error(alice.delete("/jobs/6f1c7c1e-3d0b-4c55-9a2f-0d8f2b7c1a11"), 404, "job_not_found")


def test_query_parameters_are_validated_before_any_work(alice):
    job = "6f1c7c1e-3d0b-4c55-9a2f-0d8f2b7c1a11"
    _error(alice.get(f"/lightfield/{job}/envmap?x=1,2"), 422, "invalid_x")
    _error(alice.get(f"/lightfield/{job}/envmap?x=nan,0,0"), 422, "invalid_x")
    _error(alice.get(f"/lightfield/{job}/envmap?x=0,0,0&t=inf"), 422, "invalid_t")
    _error(alice.get(f"/lightfield/{job}/envmap?x=0,0,0&height=100000"), 413, "height_too_large")
    _error(alice.get(f"/lightfield/{job}/envmap?x=0,0,0&format=jpg"), 422, "invalid_request")
    _error(alice.get(f"/lightfield/{job}/cubemap?x=0,0,0&size=100000"), 413, "size_too_large")
    _error(alice.get("/jobs?limit=100000"), 422, "invalid_limit")


def test_tenants_never_see_each_others_jobs(stack, media):
    with stack.client("alice") as alice, stack.client("bob") as bob:
        created = _post(alice, media["image"])
        assert created.status_code == 202, created.text
        job = created.json()["id"]
        assert created.headers["location"] == f"/jobs/{job}"
        assert alice.get(f"/jobs/{job}").status_code == 200
        for call in (bob.get(f"/jobs/{job}"), bob.get(f"/jobs/{job}/events"), bob.get(f"/lightfield/{job}"),
                     bob.get(f"/lightfield/{job}/envmap?x=0,0,0"), bob.delete(f"/jobs/{job}")):
            _error(call, 404, "job_not_found")
        assert job not in [j["id"] for j in bob.get("/jobs").json()["jobs"]]
        assert job in [j["id"] for j in alice.get("/jobs").json()["jobs"]]
        assert alice.get(f"/jobs/{job}").json()["state"] != "cancelled"  # bob's DELETE did nothing
        alice.delete(f"/jobs/{job}")
