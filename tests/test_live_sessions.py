"""Live sessions (issue 63) against the real server, Redis and Celery workers: frames over
HTTP and a real WebSocket client, versions over a real SSE client, bad frames refused while
the session goes on, tenant isolation, limits, idle expiry, and a worker killed mid-session."""
from __future__ import annotations

import base64
import json
import signal
import threading
import time

import numpy as np
import pytest
import torch

from conftest import TENANTS, room_frames, wait_until
from core.engine.warm_start import resample_axis, warm_start


# -- the warm start, alone ---------------------------------------------------------------------
def test_warm_start_copies_equal_shapes_and_stretches_knots():
    old = torch.nn.Module()
    old.a, old.knots, old.odd = (torch.nn.Parameter(torch.randn(3, 4)), torch.nn.Parameter(torch.arange(4.0)[None]),
                                 torch.nn.Parameter(torch.randn(2, 2)))
    new = torch.nn.Module()
    new.a, new.knots, new.odd = (torch.nn.Parameter(torch.zeros(3, 4)), torch.nn.Parameter(torch.zeros(1, 7)),
                                 torch.nn.Parameter(torch.zeros(3, 3)))
    report = warm_start(new, old.state_dict())
    assert torch.equal(new.a, old.a)
    np.testing.assert_allclose(new.knots.detach().numpy()[0], np.linspace(0, 3, 7), atol=1e-6)  # stretched, ends kept
    assert report.copied == ["a"] and report.resampled == ["knots"] and report.fresh == ["odd"]
    assert torch.all(new.odd == 0)  # two axes differ: its fresh initialisation stays
    assert resample_axis(torch.ones(2, 1), 1, 5).shape == (2, 5)


def test_a_warm_started_run_begins_where_the_last_version_ended(tmp_path):
    """run_job's init_state: the next version starts from the last one's weights, on more
    frames, so its first steps already fit the room (lower loss than a fresh start)."""
    from core.engine import run_job
    from core.engine.params import JobParams
    from core.io.images import write_png

    def capture(n: int):
        out = tmp_path / f"capture{n}"
        out.mkdir()
        frames = room_frames(n)
        for i in range(n):
            write_png(out / f"{i}.png", frames[i])
        (out / "capture.json").write_text(json.dumps({"format": "lightfield-capture", "fps": 2.0,
                                                      "frames": [f"{i}.png" for i in range(n)],
                                                      "poses": [_pose(i) for i in range(n)]}))
        return out

    loop = {"distill": {"iterations": 30, "work_height": 24, "warmup_steps": 2, "checkpoint_every": 100}}
    params = JobParams(temporal="off")
    first = run_job(capture(2), None, params, tmp_path / "v1", overrides=loop).artefact
    more = capture(4)
    cold = run_job(more, None, params, tmp_path / "cold", overrides=loop).artefact.meta["training"]
    warm = run_job(more, None, params, tmp_path / "warm", overrides=loop,
                   init_state=first.field.state_dict()).artefact.meta["training"]
    assert cold["warm_start"] is None and warm["warm_start"]["copied"] > 0
    assert np.mean(warm["loss_curve"][:5]) < np.mean(cold["loss_curve"][:5])


def test_a_keyless_server_refuses_a_cross_origin_websocket():
    """The Origin rule of a keyless server (service.origin) holds for a WebSocket handshake too:
    any page could otherwise open one to loopback and send frames."""
    import asyncio

    from service.origin import OriginGuard

    def handshake(origin: bytes) -> tuple[list, list]:
        reached, sent = [], []

        async def app(scope, receive, send):
            reached.append(scope)

        async def receive():
            return {"type": "websocket.connect"}

        async def send(message):
            sent.append(message)

        scope = {"type": "websocket", "scheme": "ws", "headers": [(b"host", b"127.0.0.1:8000"), (b"origin", origin)]}
        asyncio.run(OriginGuard(app, keyless=True)(scope, receive, send))
        return reached, sent

    reached, sent = handshake(b"http://attacker.example")
    assert not reached and sent == [{"type": "websocket.close", "code": 1008, "reason": "origin_not_allowed"}]
    reached, sent = handshake(b"http://127.0.0.1:8000")  # the server's own page
    assert reached and not sent


# -- helpers -----------------------------------------------------------------------------------
def _png(i: int, frames=None) -> bytes:
    from core.io.images import encode_png

    frames = room_frames(8) if frames is None else frames
    return encode_png(frames[i % len(frames)])


def _pose(i: int) -> list[float]:
    p = np.eye(4)
    p[0, 3] = 0.05 * i
    return p.reshape(-1).tolist()


def _post_frames(client, sid: str, indices, **meta):
    files = [("frame", (f"{i}.png", _png(i), "image/png")) for i in indices]
    body = {"poses": [_pose(i) for i in indices], **meta}
    return client.post(f"/sessions/{sid}/frames", files=files, data={"meta": json.dumps(body)})


def _session(client, sid: str) -> dict:
    return client.get(f"/sessions/{sid}").json()


def _wait_version(client, sid: str, version: int, timeout_s: float = 120) -> dict:
    return wait_until(lambda: (lambda b: b if b["version"] >= version else None)(_session(client, sid)), timeout_s,
                      interval_s=0.2, what=f"session version {version}")


class SSEReader:
    """A real SSE client (httpx streaming) in a thread, collecting (event, data) pairs."""

    def __init__(self, stack, path: str, params: dict, tenant: str = "alice"):
        self.events: list[tuple[str, dict]] = []
        self._client = stack.client(tenant)
        self._thread = threading.Thread(target=self._run, args=(path, params), daemon=True)
        self._thread.start()

    def _run(self, path, params):
        name = None
        with self._client.stream("GET", path, params=params, timeout=120) as resp:
            assert resp.status_code == 200, resp.read()
            for line in resp.iter_lines():
                if line.startswith("event: "):
                    name = line[7:]
                elif line.startswith("data: "):
                    self.events.append((name, json.loads(line[6:])))

    def wait(self, predicate, timeout_s: float = 120):
        return wait_until(lambda: next((d for n, d in list(self.events) if predicate(n, d)), None), timeout_s,
                          interval_s=0.1, what="an SSE event")


# -- HTTP + SSE --------------------------------------------------------------------------------
@pytest.mark.slow
def test_session_over_http_and_sse(service_stack):
    with service_stack.client("alice") as c:
        resp = c.post("/sessions", json={"preset": "draft"})
        assert resp.status_code == 201, resp.text
        sid = resp.json()["id"]
        assert c.get(f"/lightfield/{sid}/sh", params={"x": "0,0,-1"}).json()["error"]["code"] == "not_ready"
        sse = SSEReader(service_stack, f"/sessions/{sid}/events", {"x": ["0,0,-1", "0.5,0,-1"]})

        assert _post_frames(c, sid, [0, 1]).status_code == 202
        first = sse.wait(lambda n, d: n == "version")
        assert first["version"] == 1 and first["frames"] == 2 and len(first["probes"]) == 2
        probe = first["probes"][0]
        assert len(probe["sphericalHarmonicsCoefficients"]) == 27
        assert all(np.isfinite(probe["sphericalHarmonicsCoefficients"]))
        assert probe["primaryLightDirection"]["w"] == 0.0 and probe["primaryLightIntensity"]["w"] == 1.0
        assert abs(np.linalg.norm([probe["primaryLightDirection"][k] for k in "xyz"]) - 1) < 1e-3
        env = c.get(probe["environmentMap"])
        assert env.status_code == 200 and env.headers["content-type"] == "image/x-exr"
        assert env.headers["X-Lightfield-Session-Version"] == "1"
        assert env.headers["X-Lightfield-Session-Frames"] == "2"
        assert c.get(probe["reflectionCubeMap"]).status_code == 200

        # bad frames: a 4xx naming the problem, and the session goes on
        junk = c.post(f"/sessions/{sid}/frames", files=[("frame", ("x.png", b"not an image", "image/png"))])
        assert junk.status_code == 415 and "frame 0" in junk.json()["error"]["message"]
        bent = _post_frames(c, sid, [2], poses=[[2.0] + _pose(2)[1:]])
        assert bent.status_code == 422 and bent.json()["error"]["code"] == "invalid_pose"
        assert "frame 0" in bent.json()["error"]["message"]
        from core.io.images import encode_png

        small = c.post(f"/sessions/{sid}/frames", files=[("frame", ("s.png", encode_png(np.zeros((8, 8, 3))),
                                                                      "image/png"))],
                       data={"meta": json.dumps({"poses": [_pose(0)]})})
        assert small.status_code == 422 and small.json()["error"]["code"] == "frame_size_mismatch"
        no_pose = c.post(f"/sessions/{sid}/frames", files=[("frame", ("p.png", _png(3), "image/png"))])
        assert no_pose.status_code == 422 and no_pose.json()["error"]["code"] == "invalid_pose"
        assert _session(c, sid)["frames"] == 2  # nothing of a refused batch was kept

        assert _post_frames(c, sid, [2, 3, 4]).status_code == 202
        second = sse.wait(lambda n, d: n == "version" and d["version"] >= 2)
        assert second["frames"] == 5
        info = c.get(f"/lightfield/{sid}")
        assert info.json()["metadata"]["training"]["warm_start"]["copied"] > 0  # refined, not restarted

        ended = c.delete(f"/sessions/{sid}")
        assert ended.status_code == 202 and ended.json()["state"] == "ended"
        assert c.post(f"/sessions/{sid}/frames", files=[("frame", ("a.png", _png(0), "image/png"))]).status_code == 409
        sse.wait(lambda n, d: n == "ended")
        job = c.get(f"/jobs/{sid}").json()
        assert job["state"] == "succeeded"  # a normal stored field
        final = c.get(f"/lightfield/{sid}/sh", params={"x": "0,0,-1"})
        assert final.status_code == 200 and "X-Lightfield-Session-Version" not in final.headers


@pytest.mark.slow
def test_a_video_chunk_and_depth_maps(service_stack, tiny_video):
    import io

    with service_stack.client("alice") as c:
        sid = c.post("/sessions", json={"fps": 6}).json()["id"]
        resp = c.post(f"/sessions/{sid}/frames", files=[("video", ("chunk.mp4", tiny_video.read_bytes(), "video/mp4"))])
        assert resp.status_code == 202 and resp.json()["frames"] == 6, resp.text
        junk = c.post(f"/sessions/{sid}/frames", files=[("video", ("chunk.mp4", b"\x00" * 4096, "video/mp4"))])
        assert junk.status_code in (415, 422) and _session(c, sid)["frames"] == 6
        assert c.delete(f"/sessions/{sid}").status_code == 202

        sid = c.post("/sessions", json={}).json()["id"]

        def depth(h: int, w: int) -> bytes:
            buf = io.BytesIO()
            np.save(buf, np.full((h, w), 2.5, np.float32), allow_pickle=False)
            return buf.getvalue()

        def post(depths):
            files = [("frame", (f"{i}.png", _png(i), "image/png")) for i in range(len(depths))]
            files += [("depth", (f"{i}.npy", d, "application/octet-stream")) for i, d in enumerate(depths)]
            meta = {"poses": [_pose(i) for i in range(len(depths))]}
            return c.post(f"/sessions/{sid}/frames", files=files, data={"meta": json.dumps(meta)})

        assert post([depth(48, 64), depth(48, 64)]).status_code == 202
        wrong = post([depth(24, 32)])
        assert wrong.status_code == 422 and wrong.json()["error"]["code"] == "invalid_depth"
        assert "frame 0" in wrong.json()["error"]["message"]
        missing = _post_frames(c, sid, [2])  # this session's frames have depth
        assert missing.status_code == 422 and missing.json()["error"]["code"] == "invalid_depth"
        assert _session(c, sid)["frames"] == 2
        assert c.delete(f"/sessions/{sid}").status_code == 202


# -- WebSocket ---------------------------------------------------------------------------------
def _ws(stack, sid: str, tenant: str = "alice"):
    import websocket

    url = stack.base_url.replace("http://", "ws://") + f"/sessions/{sid}/stream"
    return websocket.create_connection(url, header=[f"Authorization: Bearer {TENANTS[tenant]}"], timeout=120)


def _ws_frames(indices) -> str:
    return json.dumps({"type": "frames", "id": "f", "frames": [
        {"image": base64.b64encode(_png(i)).decode(), "pose": _pose(i), "ev": 0.0} for i in indices]})


@pytest.mark.slow
def test_session_over_websocket(service_stack):
    with service_stack.client("alice") as c:
        sid = c.post("/sessions", json={}).json()["id"]
    ws = _ws(service_stack, sid)
    try:
        ws.send(json.dumps({"type": "subscribe", "id": "s", "probes": [[0, 0, -1]]}))
        replies = [json.loads(ws.recv())]
        time.sleep(2.5)  # past the request-header deadline (2 s here): a WebSocket is not a slow request
        ws.send(_ws_frames([0, 1, 2]))
        ws.send(json.dumps({"type": "frames", "id": "bad", "frames": [{"image": "%%%", "pose": _pose(3)}]}))
        ws.send(json.dumps({"type": "frames", "id": "nan", "frames": [
            {"image": base64.b64encode(_png(3)).decode(), "pose": _pose(3), "ev": "dark"}]}))
        ws.send("not json")
        version = None
        deadline = time.monotonic() + 120
        while version is None and time.monotonic() < deadline:
            message = json.loads(ws.recv())
            replies.append(message)
            if message["type"] == "version":
                version = message
        by_id = {m.get("id"): m for m in replies if m.get("id")}
        assert by_id["s"]["type"] == "subscribed"
        assert by_id["f"]["type"] == "accepted" and by_id["f"]["accepted"] == 3
        assert by_id["bad"]["type"] == "error" and by_id["bad"]["status"] == 422
        assert "base64" in by_id["bad"]["message"]
        assert by_id["nan"]["status"] == 422 and by_id["nan"]["code"] == "invalid_ev"
        assert any(m["type"] == "error" and m["code"] == "invalid_message" for m in replies)
        assert version is not None and version["frames"] == 3, replies
        assert len(version["probes"][0]["sphericalHarmonicsCoefficients"]) == 27
        ws.send(_ws_frames([3]))  # the session went on after the bad messages
        while True:
            message = json.loads(ws.recv())
            if message.get("id") == "f":
                assert message["type"] == "accepted" and message["frames"] == 4
                break
        ws.send(json.dumps({"type": "end", "id": "e"}))
        after_end = []
        while not after_end or after_end[-1]["type"] != "ended":  # the server closes after `ended`
            after_end.append(json.loads(ws.recv()))
        reply = next(m for m in after_end if m.get("id") == "e")
        assert reply["type"] == "session" and reply["session"]["state"] == "ended", after_end
    finally:
        ws.close()


@pytest.mark.slow
def test_tenants_are_isolated(service_stack):
    with service_stack.client("alice") as alice, service_stack.client("bob") as bob:
        sid = alice.post("/sessions", json={}).json()["id"]
        assert bob.get(f"/sessions/{sid}").status_code == 404
        assert _post_frames(bob, sid, [0]).status_code == 404
        assert bob.delete(f"/sessions/{sid}").status_code == 404
        assert bob.get(f"/sessions/{sid}/events", params={"x": "0,0,0"}).status_code == 404
        assert bob.get(f"/lightfield/{sid}/sh", params={"x": "0,0,0"}).status_code == 404
        ws = _ws(service_stack, sid, "bob")
        try:
            assert json.loads(ws.recv())["status"] == 404
        finally:
            ws.close()
        assert alice.get(f"/sessions/{sid}").status_code == 200
        assert alice.post("/sessions", json={"poses": [_pose(0)]}).status_code == 422  # frames carry poses
        assert alice.delete(f"/sessions/{sid}").status_code == 202


# -- limits, expiry, a worker killed mid-session -------------------------------------------------
@pytest.mark.slow
def test_limits_and_idle_expiry(make_stack):
    stack = make_stack(LIGHTFIELD_SESSION_IDLE_S="3", LIGHTFIELD_MAX_SESSION_FRAMES="8",
                       LIGHTFIELD_MAX_SESSION_FPS="6", LIGHTFIELD_MAX_LIVE_SESSIONS="2")
    stack.wait_ready()
    with stack.client("alice") as c:
        sid = c.post("/sessions", json={}).json()["id"]
        assert c.post("/sessions", json={}).status_code == 201
        assert c.post("/sessions", json={}).status_code == 429  # the tenant's live sessions
        rate = _post_frames(c, sid, range(7))
        assert rate.status_code == 429 and "per second" in rate.json()["error"]["message"]
        assert _post_frames(c, sid, range(6)).status_code == 202
        time.sleep(1.1)
        full = _post_frames(c, sid, [6, 7, 8])
        assert full.status_code == 413 and full.json()["error"]["code"] == "too_many_frames"
        assert _session(c, sid)["frames"] == 6

        # nothing sent for LIGHTFIELD_SESSION_IDLE_S: expired, and its last version stored as a field
        ended = wait_until(lambda: (lambda b: b if b["state"] == "expired" else None)(_session(c, sid)), 30,
                           interval_s=0.5, what="idle expiry")
        assert ended["frames"] == 6
        assert _post_frames(c, sid, [6]).json()["error"]["code"] == "session_ended"
        wait_until(lambda: c.get(f"/jobs/{sid}").json().get("state") == "succeeded", 120, what="the final field")
        assert c.get(f"/lightfield/{sid}/sh", params={"x": "0,0,-1"}).status_code == 200
        assert c.post("/sessions", json={}).status_code == 201  # the expired ones no longer count


@pytest.mark.slow
def test_a_killed_worker_resumes_from_the_last_version(make_stack):
    stack = make_stack(LIGHTFIELD_DISTILL_OVERRIDES=json.dumps({"iterations": 400, "work_height": 24,
                                                               "warmup_steps": 2}),
                       LIGHTFIELD_SESSION_STEPS="400")
    stack.wait_ready()
    with stack.client("alice") as c:
        sid = c.post("/sessions", json={}).json()["id"]
        assert _post_frames(c, sid, [0, 1]).status_code == 202
        _wait_version(c, sid, 1, timeout_s=240)
        # version 2 is being computed: kill its worker; a new one starts over from version 1
        assert _post_frames(c, sid, [2, 3]).status_code == 202
        wait_until(lambda: stack.log("worker0").count("received") >= 2, 30, what="the second update to start")
        time.sleep(1.0)
        assert _session(c, sid)["version"] == 1
        stack.workers[0].send_signal(signal.SIGKILL)
        stack.workers[0].wait(10)
        stack.start_worker()
        body = _wait_version(c, sid, 2, timeout_s=300)
        assert body["version_frames"] == 4
        info = c.get(f"/lightfield/{sid}").json()["metadata"]
        assert info["training"]["warm_start"]["copied"] > 0  # from version 1, not from scratch


# -- the command-line client -------------------------------------------------------------------
@pytest.mark.slow
def test_lightfield_stream_replays_a_capture(service_stack, tmp_path, monkeypatch, capsys):
    from cli.main import main
    from core.io.images import write_png

    frames = room_frames(4)
    names = [f"{i}.png" for i in range(len(frames))]
    for name, frame in zip(names, frames):
        write_png(tmp_path / name, frame)
    (tmp_path / "capture.json").write_text(json.dumps({
        "format": "lightfield-capture", "frames": names, "fps": 4.0, "poses": [_pose(i) for i in range(4)]}))
    monkeypatch.setenv("LIGHTFIELD_API_KEY", TENANTS["alice"])
    code = main(["stream", str(tmp_path), "--url", service_stack.base_url, "--speed", "0", "--batch", "2",
                 "--probe", "0,0,-1"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "4 frames at 4 fps" in out and " version " in out and "ended: stored field /lightfield/" in out
    sid = out.split()[1].rstrip(":")
    with service_stack.client("alice") as c:
        assert c.get(f"/jobs/{sid}").json()["state"] == "succeeded"


# -- hosts sharing only Redis and an S3 store ----------------------------------------------------
@pytest.mark.slow
def test_a_session_through_the_object_store(tmp_path, s3_server):
    from test_storage_s3 import MultiHostStack

    prefix = f"sessions{time.monotonic_ns()}"
    stack = MultiHostStack(tmp_path / "stack", extra_env={
        **s3_server.env, "LIGHTFIELD_STORAGE_URL": f"s3://{s3_server.bucket}/{prefix}"})
    try:
        stack.start(workers=2)
        stack.wait_ready()
        with stack.client("alice") as c:
            sid = c.post("/sessions", json={}).json()["id"]
            assert _post_frames(c, sid, [0, 1]).status_code == 202
            assert not list(stack.host_dir("api").glob(f"uploads/*/{sid}/frames/*"))  # the API keeps no frame
            assert len([k for k in s3_server.keys(prefix) if f"{sid}/frames/" in k]) == 2
            _wait_version(c, sid, 1)
            assert any(k.endswith(f"{sid}/versions/1/lightfield.json") for k in s3_server.keys(prefix))
            resp = c.get(f"/lightfield/{sid}/sh", params={"x": "0,0,-1"})
            assert resp.status_code == 200 and resp.headers["X-Lightfield-Session-Version"] == "1"
            assert _post_frames(c, sid, [2, 3]).status_code == 202
            assert _wait_version(c, sid, 2)["version_frames"] == 4
            assert c.delete(f"/sessions/{sid}").status_code == 202
            wait_until(lambda: _session(c, sid)["final"], 120, what="the final field, the rest deleted")
            assert c.get(f"/jobs/{sid}").json()["state"] == "succeeded"
            keys = [k for k in s3_server.keys(prefix) if sid in k]
            assert any(k.endswith(f"{sid}/lightfield/lightfield.json") for k in keys)
            assert not [k for k in keys if "/frames/" in k or "/versions/" in k]  # nothing else is kept
            assert c.get(f"/lightfield/{sid}/sh", params={"x": "0,0,-1"}).status_code == 200
    finally:
        stack.stop()
