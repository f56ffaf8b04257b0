"""Issue 45 ("round two") against real processes: hostile uploads and storage faults through the
HTTP API (redis-server, Celery workers, `lightfield serve`), each case of the issue reproduced.

* bounded cost before decoding: every hostile upload of the issue answered at once with its 4xx
  (or accepted for what it really holds), the API's resident memory barely moving;
* the same refusal at submission as in the worker, with the field and its range named;
* storage faults: 503 storage_unavailable with Retry-After at submission, a running job given
  back to the queue and resumed from its checkpoint once storage is back, DELETE saying what it
  could not delete and keeping the record;
* fair queries: a long export neither holds up small queries on the same field nor outlives its
  client;
* lifecycle: `kill -9` of `lightfield serve` leaves no child running, and the finished job's
  record shows its last iteration.

Storage faults are injected as an operator meets them: a directory made immutable (chattr +i,
which binds root too) or a full tmpfs; tests that cannot inject them here skip.
"""
from __future__ import annotations

import base64
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import psutil
import pytest

import bench.hostile_inputs as h
from conftest import REPO, SHORT_TIMEOUTS, TENANTS, wait_until

pytestmark = pytest.mark.slow
MB = 1 << 20


@pytest.fixture(scope="module")
def stack(service_stack):
    return service_stack


@pytest.fixture(scope="module")
def alice(stack):
    with stack.client("alice") as c:
        yield c


def _error(resp, status: int, code: str) -> dict:
    assert resp.status_code == status, resp.text
    body = resp.json()
    assert body["error"]["code"] == code, body
    return body["error"]


def rss_mb(pid: int) -> float:
    return psutil.Process(pid).memory_info().rss / MB


@contextmanager
def peak_rss(pid: int):
    """Samples the process's resident memory every 5 ms; yields a dict with before/peak (MB)."""
    out = {"before": rss_mb(pid), "peak": 0.0}
    done = threading.Event()

    def sample():
        while not done.is_set():
            out["peak"] = max(out["peak"], rss_mb(pid))
            time.sleep(0.005)

    t = threading.Thread(target=sample)
    t.start()
    try:
        yield out
    finally:
        done.set()
        t.join()


def _depth_npz(value: float) -> bytes:
    depth = np.full((48, 64), 2.0, np.float32)
    depth[5, 5] = value
    return h.npz(depth)


# name -> (files, expected status, code, text the message names)
HOSTILE = {
    "nested transforms.json (100k deep)": ({"file": h.capture_zip(h.nested_index(100_000))}, 413, "too_large", "deep"),
    "transforms.json of 2M empty lists": ({"file": h.capture_zip(h.container_bomb_index(2_000_000))}, 413,
                                          "too_large", "transforms.json"),
    "100k frames naming one image": ({"file": h.capture_zip(h.many_frames_index(100_000))}, 413, "too_large",
                                     "transforms.json"),
    "zip of 25k entries": ({"file": h.zip_with_entries(25_000)}, 413, "too_large", "entries"),
    "zip lying about its entries": ({"file": h.zip_lying_about_entries(25_000)}, 413, "too_large", "entries"),
    "Fortran npz depth bomb": ({"file": h.png_bytes(), "depth": h.fortran_npz_bomb((40, 500, 500))}, 413,
                               "too_large", "zip bomb"),
    "zip: translation 1e300": ({"file": h.capture_zip(h.capture_index() | {"frames": [
        {"file_path": "images/0.png", "transform_matrix": [[1, 0, 0, 1e300], *h.EYE[1:]]}]})}, 422,
        "invalid_poses", "frames[0].transform_matrix"),
    "zip: fl_x 1e308": ({"file": h.capture_zip(h.capture_index(fl_x=1e308))}, 422, "invalid_intrinsics", "fl_x"),
    "zip: fl_x 1e-300": ({"file": h.capture_zip(h.capture_index(fl_x=1e-300))}, 422, "invalid_intrinsics", "fl_x"),
    "zip: cx 1e308": ({"file": h.capture_zip(h.capture_index(cx=1e308))}, 422, "invalid_intrinsics", "cx"),
    "zip: k1 1e300": ({"file": h.capture_zip(h.capture_index(camera_model="OPENCV", k1=1e300))}, 422,
                      "invalid_intrinsics", "k1"),
    "truncated JPEG": ({"file": h.truncated_jpeg()}, 422, "truncated", "JPEG"),
    "truncated JPEG in a zip": ({"file": h.capture_zip(h.capture_index(), {"images/0.png": h.png_bytes(),
                                                                          "images/1.png": h.truncated_jpeg()})},
                                422, "truncated", "frames[1].file_path"),
    "depth of 3e38 m": ({"file": h.png_bytes(), "depth": _depth_npz(3e38)}, 422, "invalid_depth", "10000"),
    "depth of 1e20 m": ({"file": h.png_bytes(), "depth": _depth_npz(1e20)}, 422, "invalid_depth", "10000"),
    "PNG bomb": ({"file": h.png_bomb()}, 413, "too_many_pixels", "pixels"),
}


@pytest.mark.parametrize("name", list(HOSTILE))
def test_hostile_uploads_are_refused_at_once_at_little_cost(stack, alice, name):
    files, status, code, named = HOSTILE[name]
    with peak_rss(stack.api.pid) as rss:
        t0 = time.monotonic()
        resp = alice.post("/jobs", files={k: (k, v) for k, v in files.items()})
        took = time.monotonic() - t0
    err = _error(resp, status, code)
    assert named in err["message"], err
    # issue: up to +1.5 GB and 33 s; loose guards here (bench/upload_cost.py measures)
    assert rss["peak"] - rss["before"] < 150, (name, rss)
    assert took < 10, (name, took)
    assert alice.get("/healthz").status_code == 200


def test_a_png_bomb_gets_the_same_code_in_a_zip(alice):
    index = h.capture_index(frames=1)
    del index["w"], index["h"]
    err = _error(alice.post("/jobs", files={"file": ("c.zip", h.capture_zip(index, {"images/0.png": h.png_bomb()}))}),
                 413, "too_many_pixels")
    assert "frames[0].file_path" in err["message"]


def test_an_mp4_declaring_1e8_samples_is_taken_for_what_it_holds(stack, alice, tmp_path):
    """Issue: 202 while the API grew 517 -> 1276 MB (np.arange over the declared count)."""
    bomb = h.mp4_declaring(tmp_path / "bomb.mp4", 10**8)
    with peak_rss(stack.api.pid) as rss:
        resp = alice.post("/jobs", files={"file": ("bomb.mp4", bomb.read_bytes())})
    assert resp.status_code == 202, resp.text
    alice.delete(f"/jobs/{resp.json()['id']}")
    assert rss["peak"] - rss["before"] < 100, rss


def test_a_hostile_upload_does_not_hold_up_another_tenants_upload(stack, alice, tiny_image):
    """Issue: a PNG upload of another tenant waited 22 s behind a 100k-frame index (one upload
    check at a time per process)."""
    hostile = h.capture_zip(h.many_frames_index(100_000))
    answers: dict[str, tuple[int, float]] = {}

    def send(tenant: str, files) -> None:
        with stack.client(tenant) as c:
            t0 = time.monotonic()
            resp = c.post("/jobs", files=files)
            answers[tenant] = (resp.status_code, time.monotonic() - t0)
            if resp.status_code == 202:
                c.delete(f"/jobs/{resp.json()['id']}")

    threads = [threading.Thread(target=send, args=("alice", {"file": ("c.zip", hostile)})),
               threading.Thread(target=send, args=("bob", {"file": ("room.png", tiny_image.read_bytes())}))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert answers["alice"][0] == 413 and answers["bob"][0] == 202, answers
    assert answers["bob"][1] < 5 and answers["alice"][1] < 5, answers


# -- messages a person understands ------------------------------------------------------------------------
def test_nan_queries_and_malformed_bodies_get_plain_messages(alice, finished_job):
    job = finished_job
    err = _error(alice.get(f"/lightfield/{job}/envmap", params={"x": "nan,0,0"}), 422, "invalid_x")
    assert err["message"] == "x: must be three finite numbers 'X,Y,Z' in metres, each within +-1e6, got 'nan,0,0'"
    err = _error(alice.get(f"/lightfield/{job}/envmap", params={"x": "0,0,-1", "t": "nan"}), 422, "invalid_t")
    assert err["message"] == "t: must be a finite number of seconds within +-1e9, got 'nan'"
    nested = b'{"queries": ' + b"[" * 50_000 + b"]" * 50_000 + b"}"
    err = _error(alice.post(f"/lightfield/{job}/envmaps", content=nested, headers={"content-type": "application/json"}),
                 400, "malformed_body")
    assert "nested too deeply" in err["message"]
    err = _error(alice.post(f"/lightfield/{job}/envmaps", content=b'{"queries": [',
                            headers={"content-type": "application/json"}), 400, "malformed_body")
    assert "not valid JSON" in err["message"] and "character 13" in err["message"]


# -- fair queries -----------------------------------------------------------------------------------------
def _counter(text: str, name: str) -> float:
    return sum(
        float(line.split()[-1]) for line in text.splitlines() if line.startswith(name) and not line.startswith("#")
    )


def _open_request(stack, path: str) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", stack.port), timeout=30)
    s.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {TENANTS['alice']}\r\n\r\n".encode())
    return s


def test_a_long_sequence_neither_blocks_small_queries_nor_outlives_its_client(stack, alice, finished_job):
    """Issue: a 240-frame 1024-row exact sequence kept a field busy (a 64-row map waited 31 s) and
    went on computing ~10 s after its client left."""
    job = finished_job
    s = _open_request(stack, f"/lightfield/{job}/sequence?x=0,0,-1&t0=0&t1=0&frames=240&height=512&quality=exact")
    try:
        assert s.recv(4096).startswith(b"HTTP/1.1 200")  # streaming: the first frame is out
        wait_until(lambda: _counter(alice.get("/metrics").text, "lightfield_export_maps_total") >= 1, 60,
                   what="the sequence to compute frames")
        waits = []
        for i in range(5):
            t0 = time.monotonic()
            resp = alice.get(
                f"/lightfield/{job}/envmap", params={"x": f"0,{0.01 * i},-1", "height": 64, "format": "npy"}
            )
            assert resp.status_code == 200
            waits.append(time.monotonic() - t0)
        assert max(waits) < 2.0, waits  # one 512-row exact frame alone takes longer than that here
    finally:
        s.close()
    metrics = lambda: alice.get("/metrics").text  # noqa: E731
    wait_until(lambda: _counter(metrics(), "lightfield_exports_cancelled_total") >= 1, 10, what="the export cancelled")
    done = _counter(metrics(), "lightfield_export_maps_total")
    time.sleep(2.0)
    assert _counter(metrics(), "lightfield_export_maps_total") == done  # nothing computed after its client left
    assert done < 240
    assert "Task exception was never retrieved" not in stack.log("api")


def test_a_large_exact_map_is_cancelled_when_its_client_leaves(stack, alice, finished_job):
    before = _counter(alice.get("/metrics").text, "lightfield_exports_cancelled_total")
    s = _open_request(stack, f"/lightfield/{finished_job}/envmap?x=0,0,-1&height=1024&quality=exact&format=npy")
    time.sleep(0.3)
    s.close()
    wait_until(lambda: _counter(alice.get("/metrics").text, "lightfield_exports_cancelled_total") > before, 15,
               what="the large map cancelled")
    time.sleep(0.5)
    assert "Task exception was never retrieved" not in stack.log("api")  # the cancelled call ends quietly
    # the export copy answers exactly what the shared field does (the batch route uses the latter)
    resp = alice.get(f"/lightfield/{finished_job}/envmap", params={"x": "0,0,-1", "height": 400, "quality": "exact",
                                                                   "format": "npy"})
    assert resp.status_code == 200 and resp.headers["x-lightfield-quality"] == "exact"
    batch = alice.post(f"/lightfield/{finished_job}/envmaps", json={"queries": [{"x": [0, 0, -1]}], "height": 400,
                                                                    "quality": "exact", "format": "npy"})
    assert batch.status_code == 200, batch.text
    shared = np.load(io.BytesIO(base64.b64decode(batch.json()["items"][0]["data_base64"])))
    np.testing.assert_array_equal(shared, np.load(io.BytesIO(resp.content)))


def test_healthz_is_answered_by_the_front_door(stack):
    """Plain GET /healthz never reaches the event loop: the front door's thread answers it, on
    keep-alive connections too, while other requests on new connections are handed over."""
    s = socket.create_connection(("127.0.0.1", stack.port), timeout=10)
    for _ in range(3):
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        reply = s.recv(65536)
        assert reply.startswith(b"HTTP/1.1 200") and reply.endswith(b"}"), reply
    s.sendall(b"GET /readyz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")  # not health: handed to the loop, answered
    reply = b""
    while b"\r\n\r\n" not in reply:
        reply += s.recv(65536)
    assert reply.split(b" ")[1] in (b"200", b"503")
    s.close()


# -- storage faults -------------------------------------------------------------------------------------
@contextmanager
def immutable(path: Path):
    """`path` (a directory) refuses new and removed entries, even to root (chattr +i); skips
    the test where that cannot be done."""
    path.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        path.chmod(0o555)
        undo = lambda: path.chmod(0o755)  # noqa: E731
    elif shutil.which("chattr") and subprocess.run(["chattr", "+i", str(path)], capture_output=True).returncode == 0:
        undo = lambda: subprocess.run(["chattr", "-i", str(path)], check=True)  # noqa: E731
    else:
        pytest.skip("cannot make a directory unwritable here (no chattr)")
    try:
        probe = path / ".probe"
        try:
            probe.write_bytes(b"x")
        except OSError:
            pass
        else:
            probe.unlink()
            pytest.skip("the directory stays writable here")
        yield
    finally:
        undo()


@pytest.fixture(scope="module")
def storage_stack(tmp_path_factory):
    """Its own stack: a slower job (so a fault lands mid-run) and quick storage retries."""
    from conftest import running_stack

    env = {"LIGHTFIELD_DISTILL_OVERRIDES": json.dumps({"iterations": 80, "checkpoint_every": 4, "work_height": 24,
                                                       "warmup_steps": 2}),
           "LIGHTFIELD_STORAGE_RETRY_S": "1", "LIGHTFIELD_STORAGE_RETRIES": "30"}
    with running_stack(tmp_path_factory.mktemp("storage"), env) as s:
        yield s


def _tenant_dir(stack, area: str, tenant: str = "alice") -> Path:
    from service.auth import tenant_hash

    return stack.data_dir / area / tenant_hash(tenant)


def _upload_dirs(stack) -> set:
    return {p for p in (stack.data_dir / "uploads").glob("*/*")}


def test_unwritable_upload_storage_is_503_with_retry_after(storage_stack, tiny_image):
    """Issue: 500 (PermissionError) where the docs promise 503 storage_unavailable."""
    stack = storage_stack
    with stack.client("alice") as c:
        before = _upload_dirs(stack)
        with immutable(_tenant_dir(stack, "uploads")):
            resp = c.post("/jobs", files={"file": ("room.png", tiny_image.read_bytes())})
            err = _error(resp, 503, "storage_unavailable")
            assert int(resp.headers["retry-after"]) > 0 and "not writable" in err["message"]
            assert str(stack.data_dir) not in err["message"]
        assert _upload_dirs(stack) == before
        resp = c.post("/jobs", files={"file": ("room.png", tiny_image.read_bytes())})  # storage back: accepted
        assert resp.status_code == 202, resp.text
        c.delete(f"/jobs/{resp.json()['id']}")


def test_full_upload_storage_is_503_storage_full(storage_stack, tiny_image):
    stack = storage_stack
    target = _tenant_dir(stack, "uploads")
    target.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(target)],
                                           capture_output=True).returncode != 0:
        pytest.skip("cannot mount a small tmpfs here")
    try:
        with stack.client("alice") as c:
            resp = c.post("/jobs", files={"file": ("big.png", h.png_bytes(1024, 768) + bytes(2 * MB))})
            err = _error(resp, 503, "storage_unavailable")
            assert "full" in err["message"] and int(resp.headers["retry-after"]) > 0
            assert not any(target.iterdir())
    finally:
        subprocess.run(["umount", "-l", str(target)], check=False)


def test_a_storage_fault_mid_job_is_waited_out_and_the_job_resumes(storage_stack, tiny_image):
    """Issue: the artefact directory becoming unwritable mid-job failed it as engine_error
    (SafetensorError), never retried once storage was back."""
    stack = storage_stack
    with stack.client("alice") as c:
        resp = c.post("/jobs", files={"file": ("room.png", tiny_image.read_bytes())})
        assert resp.status_code == 202, resp.text
        job = resp.json()["id"]
        checkpoint = _tenant_dir(stack, "artefacts") / job / "checkpoint"
        wait_until(lambda: (checkpoint / "checkpoint.json").is_file(), 120, interval_s=0.02, what="a checkpoint")
        with immutable(checkpoint):
            waiting = wait_until(lambda: (lambda b: b if b["stage"] == "waiting_for_storage" else None)(
                c.get(f"/jobs/{job}").json()), 120, interval_s=0.1, what="the job to wait for storage")
            assert waiting["state"] == "queued" and waiting["storage_retries"] >= 1 and waiting["error"] is None
            assert "resuming from the last checkpoint" in waiting["message"]
            time.sleep(2.5)  # a retry or two meets the same fault
        final = wait_until(lambda: (lambda b: b if b["state"] in ("succeeded", "failed", "cancelled") else None)(
            c.get(f"/jobs/{job}").json()), 240, interval_s=0.25, what="the job to end")
        assert final["state"] == "succeeded", (final, stack.log("worker0"))
        assert final["resumed"] is True and final["attempts"] >= 2 and final["storage_retries"] >= 1
        assert final["iteration"] == final["total"] == 80
        assert c.delete(f"/jobs/{job}").status_code == 204


def test_delete_says_what_it_could_not_delete_and_keeps_the_record(storage_stack, tiny_image):
    """Issue: DELETE answered 204 but left 6.4 MB of artefacts and the upload with no record."""
    stack = storage_stack
    with stack.client("alice") as c:
        resp = c.post("/jobs", files={"file": ("room.png", tiny_image.read_bytes())})
        job = resp.json()["id"]
        c.delete(f"/jobs/{job}")  # cancelled, so it is finished quickly
        wait_until(lambda: c.get(f"/jobs/{job}").json()["state"] == "cancelled", 60, what="cancelled")
        area = _tenant_dir(stack, "artefacts") / job
        (area / "keep").mkdir(parents=True, exist_ok=True)  # something the job owns on disk
        (area / "keep" / "f").write_bytes(b"x")
        with immutable(area):
            resp = c.delete(f"/jobs/{job}")
            err = _error(resp, 503, "storage_unavailable")
            assert "artefacts" in err["message"] and int(resp.headers["retry-after"]) > 0
            assert c.get(f"/jobs/{job}").status_code == 200  # the record that owns them is kept
        assert c.delete(f"/jobs/{job}").status_code == 204
        assert not area.exists() and c.get(f"/jobs/{job}").status_code == 404


# -- lifecycle ---------------------------------------------------------------------------------------------
def test_kill_9_of_serve_stops_its_children_and_the_job_record_ends_complete(tmp_path, tiny_image):
    """Issue: `kill -9` of `lightfield serve` left its worker running ~30 s without Redis; after a
    restart the job was succeeded but its record still said iteration 177/600."""
    from service.local import EmbeddedService

    distill = json.dumps({"iterations": 60, "checkpoint_every": 2, "work_height": 24, "warmup_steps": 2})
    env = {"LIGHTFIELD_DISTILL_OVERRIDES": distill, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", **SHORT_TIMEOUTS}
    svc = EmbeddedService(tmp_path / "data", env=env).start()
    try:
        job = svc.submit(tiny_image)
        wait_until(lambda: list(svc.data_dir.glob(f"artefacts/*/{job}/checkpoint/*.json")), 120, interval_s=0.05,
                   what="a checkpoint")
        children = psutil.Process(svc.proc.pid).children(recursive=True)
        assert any("celery" in " ".join(p.cmdline()) for p in children)
        svc.proc.send_signal(signal.SIGKILL)
        svc.proc.wait(timeout=10)
        _, alive = psutil.wait_procs(children, timeout=3)
        assert not alive, [" ".join(p.cmdline())[:80] for p in alive]
        svc.start()
        final = svc.wait(job, timeout_s=240)
        assert final["state"] == "succeeded", final
        assert final["iteration"] == final["total"] == 60 and final["resumed"] is True
    finally:
        svc.stop()
