"""End to end through real uvicorn + redis-server + Celery workers + the real engine (draft
preset cut to a few steps via LIGHTFIELD_DISTILL_OVERRIDES): jobs succeed, their light
fields answer in every format, a kill -9'd worker's job resumes, cancel is fast, records
survive an API restart, and concurrent queries all succeed."""
from __future__ import annotations

import asyncio
import base64
import io
import json
import signal
import time

import httpx
import numpy as np
import pytest
import torch

from conftest import TENANTS, running_stack, wait_until
from core.conventions import CONVENTIONS_SUMMARY, tonemap

pytestmark = pytest.mark.slow

TERMINAL = ("succeeded", "failed", "cancelled")


def submit(client, path, params: dict | None = None) -> str:
    resp = client.post("/jobs", files={"file": (path.name, path.read_bytes())},
                       data={"params": json.dumps(params or {})})
    assert resp.status_code == 202, resp.text
    return resp.json()["id"]


def wait_job(client, job: str, states=TERMINAL, timeout_s: float = 120) -> dict:
    def done():
        body = client.get(f"/jobs/{job}").json()
        return body if body["state"] in states else None

    return wait_until(done, timeout_s, interval_s=0.1, what=f"job {job} in {states}")


def inside_point(client, job: str) -> str:
    bounds = client.get(f"/lightfield/{job}").json()["metadata"]["bounds"]
    centre = [(lo + hi) / 2 for lo, hi in zip(bounds["lo"], bounds["hi"])]
    return ",".join(f"{v:.4f}" for v in centre)


def get_map(client, job: str, fmt: str, **query) -> httpx.Response:
    resp = client.get(f"/lightfield/{job}/envmap", params={"format": fmt, **query})
    assert resp.status_code == 200, resp.text
    return resp


@pytest.fixture(scope="module")
def stack(service_stack):
    return service_stack


@pytest.fixture(scope="module")
def image_job(stack, tiny_image):
    with stack.client() as c:
        job = submit(c, tiny_image)
        final = wait_job(c, job)
        assert final["state"] == "succeeded", (final, stack.log("worker0"))
        return job


def test_image_job_succeeds_and_streams_its_progress(stack, tiny_image):
    with stack.client() as c:
        job = submit(c, tiny_image, {"seed": 7})
        events = []
        with c.stream("GET", f"/jobs/{job}/events", timeout=120) as resp:
            assert resp.headers["content-type"].startswith("text/event-stream")
            for line in resp.iter_lines():
                if line.startswith("data: "):
                    events.append(json.loads(line[6:]))
        states = [e["state"] for e in events]
        assert states[-1] == "succeeded"  # the stream ends with the job
        progress = [e["progress"] for e in events]
        assert progress == sorted(progress) and progress[-1] == 1.0
        assert any(e["stage"] == "distill" and e["total"] > 0 for e in events)
        final = c.get(f"/jobs/{job}").json()
        assert final["links"]["envmap"] == f"/lightfield/{job}/envmap" and final["attempts"] == 1
        assert final["finished_at"] >= final["started_at"] >= final["created_at"]


def test_envmap_formats_agree_with_each_other(stack, image_job):
    from core.io.exr import read_exr
    from core.io.hdr import read_hdr
    from core.io.images import read_image

    with stack.client() as c:
        x = inside_point(c, image_job)
        npy_resp = get_map(c, image_job, "npy", x=x, height=16)
        assert npy_resp.headers["x-lightfield-conventions"] == CONVENTIONS_SUMMARY
        assert npy_resp.headers["x-lightfield-extrapolated"] == "none"
        ref = np.load(io.BytesIO(npy_resp.content), allow_pickle=False)
        assert ref.shape == (16, 32, 3) and ref.dtype == np.float32 and np.isfinite(ref).all() and (ref >= 0).all()
        exr = read_exr(get_map(c, image_job, "exr", x=x, height=16).content)
        np.testing.assert_allclose(exr[..., :3], ref, rtol=1e-6, atol=0)
        hdr = read_hdr(get_map(c, image_job, "hdr", x=x, height=16).content)
        np.testing.assert_allclose(hdr, ref, rtol=0.02, atol=1e-6)  # RGBE: 8-bit mantissas
        png_resp = get_map(c, image_job, "png", x=x, height=16, ev=-1)
        assert png_resp.headers["content-type"] == "image/png"
        png = read_image(png_resp.content)
        expected = tonemap(torch.from_numpy(ref), -1.0).numpy()
        np.testing.assert_allclose(png, expected, atol=1.0 / 255 + 1e-6)


def test_envmap_flags_extrapolation_and_batch_matches_single_queries(stack, image_job):
    with stack.client() as c:
        x = inside_point(c, image_job)
        far = get_map(c, image_job, "npy", x="100,100,100", height=8)
        assert far.headers["x-lightfield-extrapolated"] == "x"
        queries = [{"x": [float(v) for v in x.split(",")], "t": 0.0}, {"x": [100, 100, 100], "t": 0.0},
                   {"x": [0.1, -0.2, -1.0], "t": 0.0}]
        batch = c.post(f"/lightfield/{image_job}/envmaps", json={"queries": queries, "height": 8, "format": "npy"})
        assert batch.status_code == 200, batch.text
        items = batch.json()["items"]
        assert [i["extrapolated"]["x"] for i in items[:2]] == [False, True]
        for q, item in zip(queries, items):
            single = np.load(io.BytesIO(
                get_map(c, image_job, "npy", x=",".join(map(str, q["x"])), height=8).content))
            batched = np.load(io.BytesIO(base64.b64decode(item["data_base64"])))
            np.testing.assert_allclose(batched, single, rtol=1e-5, atol=1e-7)
        too_many = c.post(f"/lightfield/{image_job}/envmaps", json={"queries": queries * 100, "height": 8})
        assert too_many.status_code == 413 and too_many.json()["error"]["code"] == "batch_too_large"


def test_fast_quality_uses_the_worker_baked_lattice_and_stays_close_to_exact(stack, image_job):
    assert list((stack.data_dir / "artefacts").glob(f"*/{image_job}/lightfield/baked.safetensors"))
    with stack.client() as c:
        x = inside_point(c, image_job)
        fast = get_map(c, image_job, "npy", x=x, height=16, quality="baked")
        assert fast.headers["x-lightfield-quality"] == "baked"
        exact = get_map(c, image_job, "npy", x=x, height=16, quality="exact")
        assert exact.headers["x-lightfield-quality"] == "exact"
        a = np.load(io.BytesIO(fast.content))
        b = np.load(io.BytesIO(exact.content))
        assert a.shape == b.shape and np.isfinite(a).all()
        # the lattice blends neighbouring nodes: close in energy, not bit-identical
        assert abs(a.mean() - b.mean()) <= 0.25 * b.mean()


def test_sh_and_cubemap_outputs(stack, image_job):
    from core.io.exr import read_exr

    with stack.client() as c:
        sh = c.get(f"/lightfield/{image_job}/sh", params={"x": "0,0,-1"})
        assert sh.status_code == 200, sh.text
        body = sh.json()
        assert len(body["arcore_27"]) == 27 and all(np.isfinite(body["arcore_27"]))
        assert body["arcore_27"][0] > 0  # DC term of a non-negative radiance map
        light = body["dominant_light"]
        if light["found"]:
            assert np.linalg.norm(light["direction"]) == pytest.approx(1.0, abs=1e-4)
            assert min(light["intensity"]) >= 0
        cube = c.get(f"/lightfield/{image_job}/cubemap", params={"x": "0,0,-1", "size": 8})
        assert cube.status_code == 200, cube.text
        faces = cube.json()["faces"]
        assert [f["name"] for f in faces] == ["+X", "-X", "+Y", "-Y", "+Z", "-Z"]
        decoded = np.stack([read_exr(base64.b64decode(f["data_base64"]))[..., :3] for f in faces])
        npy = np.load(io.BytesIO(
            c.get(f"/lightfield/{image_job}/cubemap", params={"x": "0,0,-1", "size": 8, "format": "npy"}).content))
        assert npy.shape == (6, 8, 8, 3)
        np.testing.assert_allclose(decoded, npy, rtol=1e-6)
        # the faces see different parts of the room (not one colour copied six times)
        assert np.ptp(npy.reshape(6, -1).mean(axis=1)) > 0


def test_video_job_answers_in_time(stack, tiny_video):
    with stack.client() as c:
        job = submit(c, tiny_video, {"temporal": "on", "fps": 6})
        final = wait_job(c, job)
        assert final["state"] == "succeeded", (final, stack.log("worker0"))
        assert final["input_kind"] == "video"
        meta = c.get(f"/lightfield/{job}").json()["metadata"]
        assert meta["time"]["uses_time"] is True
        x = inside_point(c, job)
        maps = [np.load(io.BytesIO(get_map(c, job, "npy", x=x, t=t, height=8).content))
                for t in (0.0, 5 / 6)]
        assert all(m.shape == (8, 16, 3) and np.isfinite(m).all() for m in maps)
        late = get_map(c, job, "npy", x=x, t=100, height=8)
        assert "t" in late.headers["x-lightfield-extrapolated"].split(",")


def test_capture_app_zip_job_keeps_its_poses_and_probes_stay_put_in_the_room(stack, tmp_path):
    """A nerfstudio zip (a walk with known poses and depth) through POST /jobs: the job uses the
    app's cameras, the page's capture view says where they came from, and a probe placed in
    the first frame is found at its world position in the last one (not at the same pixel)."""
    from capture_fixtures import panorama_clip, walk_poses, write_nerfstudio, zip_dir

    poses = walk_poses(5)
    ldr, depth, intr = panorama_clip(poses, 64, 48, pano_height=128, supersample=1)
    root = write_nerfstudio(tmp_path / "scan", ldr.numpy(), depth.numpy(), intr, [p.numpy() for p in poses])
    (tmp_path / "scan.zip").write_bytes(zip_dir(root))
    with stack.client() as c:
        job = submit(c, tmp_path / "scan.zip", {"fps": 2})
        final = wait_job(c, job)
        assert final["state"] == "succeeded", (final, stack.log("worker0"))
        assert final["input_kind"] == "capture"
        view = c.get(f"/lightfield/{job}/capture").json()
        assert view["poses_source"] == "nerfstudio transforms.json" and view["static_camera"] is False
        assert view["tracking"] is None and view["depth_source"].startswith("file:nerfstudio")
        assert abs(view["intrinsics"]["fx"] / view["width"] - intr.fx / intr.width) < 1e-6  # the app's FOV
        first = c.get(f"/lightfield/{job}/probe", params={"u": 0.5, "v": 0.5, "t": 0.0}).json()
        x = ",".join(f"{v:.6f}" for v in first["x"])
        last = c.get(f"/lightfield/{job}/probe", params={"x": x, "t": view["times"][-1]}).json()
        assert last["frame_index"] == view["frames"] - 1
        assert last["u"] is None or abs(last["u"] - 0.5) > 0.05  # the camera moved: the point moved in the frame


def test_fifty_concurrent_envmap_queries_all_succeed(stack, image_job):
    async def run():
        headers = {"Authorization": f"Bearer {TENANTS['alice']}"}
        async with httpx.AsyncClient(base_url=stack.base_url, headers=headers, timeout=60) as ac:
            points = [f"0,{0.01 * (i % 5)},-1" for i in range(50)]
            return await asyncio.gather(*(ac.get(f"/lightfield/{image_job}/envmap",
                                                 params={"x": p, "height": 16, "format": "npy"}) for p in points))

    responses = asyncio.run(run())
    assert [r.status_code for r in responses] == [200] * 50
    by_point: dict[int, bytes] = {}
    for i, r in enumerate(responses):  # identical queries give identical answers under load
        assert by_point.setdefault(i % 5, r.content) == r.content


def test_deleting_a_finished_job_removes_record_and_artefacts(stack, tiny_image):
    with stack.client() as c:
        job = submit(c, tiny_image)
        assert wait_job(c, job)["state"] == "succeeded"
        job_dirs = list((stack.data_dir / "artefacts").glob(f"*/{job}"))
        assert len(job_dirs) == 1 and any(job_dirs[0].rglob("*.safetensors"))
        assert c.delete(f"/jobs/{job}").status_code == 204
        assert not job_dirs[0].exists()
        assert c.get(f"/jobs/{job}").status_code == 404
        assert c.get(f"/lightfield/{job}/envmap", params={"x": "0,0,0"}).status_code == 404


# -- resilience: a stack per test, with longer jobs ------------------------------------------
# Long enough that an idle machine is still mid-run after the 5 s lease check (160 steps
# finished within it); short enough that a loaded CI machine finishes the resumed job.
LONG_ITERATIONS = 800
LONG_DISTILL = json.dumps({"iterations": LONG_ITERATIONS, "checkpoint_every": 4, "work_height": 24, "warmup_steps": 2})


@pytest.fixture(scope="module")
def long_stack(tmp_path_factory):
    """A stack whose jobs run long enough to be cancelled or killed mid-run."""
    with running_stack(tmp_path_factory.mktemp("long"), {"LIGHTFIELD_DISTILL_OVERRIDES": LONG_DISTILL}) as stack:
        yield stack


def test_cancel_stops_a_running_job_within_seconds(long_stack, tiny_image):
    stack = long_stack
    with stack.client() as c:
        running = submit(c, tiny_image)
        queued = submit(c, tiny_image)
        wait_until(lambda: c.get(f"/jobs/{running}").json()["iteration"] >= 2, 90, what="distillation steps")
        not_yet = c.get(f"/lightfield/{running}/envmap", params={"x": "0,0,-1"})
        assert not_yet.status_code == 409 and not_yet.json()["error"]["code"] == "not_ready"
        # the second job waits behind the first (one job per worker): cancelling it is immediate
        gone = c.delete(f"/jobs/{queued}")
        assert gone.status_code == 202 and gone.json()["state"] == "cancelled"
        t0 = time.monotonic()
        resp = c.delete(f"/jobs/{running}")
        assert resp.status_code == 202 and resp.json()["cancel_requested"] is True
        final = wait_job(c, running, timeout_s=10)
        assert final["state"] == "cancelled" and time.monotonic() - t0 < 3.0
        assert not list((stack.data_dir / "artefacts").glob(f"*/{running}/lightfield"))
        assert c.delete(f"/jobs/{running}").status_code == 204  # a second DELETE removes the record
        assert c.get(f"/jobs/{running}").status_code == 404
        stack.wait_ready()  # the worker is free again


def test_kill_9_worker_mid_job_resumes_from_checkpoint(long_stack, tiny_image):
    stack = long_stack  # runs after the cancel test: this one kills the stack's first worker
    with stack.client() as c:
        job = submit(c, tiny_image)
        ckpt = wait_until(lambda: next(iter((stack.data_dir / "artefacts").glob(f"*/{job}/checkpoint/*.json")), None),
                          90, what="a checkpoint")
        stack.start_worker()  # a spare worker: re-deliveries while the first is alive must not run
        before = c.get(f"/jobs/{job}").json()
        assert before["state"] == "running" and ckpt.exists()
        time.sleep(5)  # > visibility timeout: the broker re-delivers to the spare, the lease holds it off
        mid = c.get(f"/jobs/{job}").json()
        assert mid["state"] == "running" and mid["attempts"] == 1, mid
        assert mid["iteration"] < mid["total"] - 8, "job too fast to kill mid-run; raise its iterations"
        stack.workers[0].send_signal(signal.SIGKILL)
        stack.workers[0].wait(timeout=10)
        final = wait_job(c, job, timeout_s=400)
        assert final["state"] == "succeeded", (final, stack.log("worker1"))
        assert final["attempts"] == 2 and final["resumed"] is True
        training = c.get(f"/lightfield/{job}").json()["metadata"]["training"]
        assert training["resumed_from"] >= 4  # continued from the checkpoint, not from step 0
        assert training["iterations"] == LONG_ITERATIONS


def test_job_records_survive_an_api_restart(stack, image_job):
    with stack.client() as c:
        before = c.get(f"/jobs/{image_job}").json()
    stack.stop_api()
    stack.start_api()
    with stack.client() as c:
        after = c.get(f"/jobs/{image_job}").json()
        assert after["state"] == before["state"] == "succeeded" and after["created_at"] == before["created_at"]
        assert get_map(c, image_job, "npy", x="0,0,-1", height=8).status_code == 200
