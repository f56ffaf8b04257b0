"""The page's HTTP routes (service.routes.ui) in-process: a real Redis job store, an artefact and
a capture preview written to disk, no worker. Auth, tenancy and error codes as in the API."""
from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest
import torch
from PIL import Image

from core.camera import Intrinsics
from core.fields import FieldConfig, SceneBounds, build_field
from core.fields.kinds.grid import GridSettings
from core.fields.stored.artefact import save_artefact
from jobs.capture_preview import CapturePreview, save_preview
from jobs.storage import JobPaths, new_job_id
from jobs.store import JobRecord
from service.auth import tenant_hash
from service.routes.ui import MAX_INSERTED_PROBES

KEYS = {"alice": "alice-key-0001", "bob": "bob-key-00002"}
W, H, T, FPS = 40, 30, 4, 2.0
WALL = 3.0
BOUNDS = SceneBounds((-3.0, -2.0, -4.0), (3.0, 2.0, 0.5), t0=0.0, t1=(T - 1) / FPS)


def bright_field(uses_time: bool = True):
    """A 2x2x2 grid field that is the same, fairly bright, everywhere (so balls are visible)."""
    cfg = FieldConfig(
        kind="grid", uses_time=uses_time, grid=GridSettings(resolution=(2, 2, 2), env_height=4, time_keyframes=2)
    )
    field = build_field(cfg, BOUNDS)
    with torch.no_grad():
        for p in field.parameters():
            p.fill_(0.0)
    return field


def preview() -> CapturePreview:
    yy = np.linspace(0, 1, H, dtype=np.float32)[None, :, None, None]
    frames = np.broadcast_to(yy * np.array([60, 50, 40], np.float32) + 20, (T, H, W, 3)).round().astype(np.uint8)
    return CapturePreview(
        frames=np.ascontiguousarray(frames + np.arange(T, dtype=np.uint8)[:, None, None, None]),
        depth=np.full((T, H, W), WALL, np.float32),
        poses=np.repeat(np.eye(4)[None], T, 0),
        times=(np.arange(T) / FPS).astype(np.float32),
        intrinsics=Intrinsics.from_hfov(W, H).as_dict(),
        fps=FPS,
        depth_source="test",
        source_frames=T,
    )


@pytest.fixture(scope="module")
def app_env(tmp_path_factory):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.config import ServiceSettings
    from service.processes import start_redis

    root = tmp_path_factory.mktemp("ui-routes")
    redis = start_redis(root / "redis")
    try:
        settings = ServiceSettings(data_dir=root / "data", broker_url=redis.url,
                                   api_keys=",".join(f"{t}:{k}" for t, k in KEYS.items()))
        app = create_app(settings)
        with TestClient(app) as client:
            yield client, app.state.ctx
    finally:
        redis.stop()


def add_job(ctx, state="succeeded", with_preview=True, tenant="alice", uses_time=True, capture_meta=None,
            frame_ev=None, quality=None) -> str:
    job = new_job_id()
    record = JobRecord(id=job, tenant=tenant, tenant_hash=tenant_hash(tenant), input_kind="video")
    ctx.store.create(record, max_in_flight=100)
    paths = JobPaths.for_job(ctx.settings.data_dir, record.tenant_hash, job)
    if state == "succeeded":
        meta = {"capture": {"fps": FPS, **(capture_meta or {})}, **({"quality": quality} if quality else {})}
        save_artefact(paths.artefact_dir, bright_field(uses_time), meta)
        if with_preview:
            stored = preview()
            if frame_ev is not None:
                stored = dataclasses.replace(stored, frame_ev=np.asarray(frame_ev, np.float32))
            save_preview(stored, paths.job_dir)
        relative = str(paths.artefact_dir.relative_to(ctx.settings.data_dir))
        assert ctx.store.update(job, allowed=("queued",), state="succeeded", artefact=relative)
    elif state != "queued":
        assert ctx.store.update(job, allowed=("queued",), state=state)
    return job


def get(client, path, tenant="alice", **params):
    headers = {"Authorization": f"Bearer {KEYS[tenant]}"} if tenant else {}
    return client.get(path, params=params, headers=headers)


def png(resp) -> np.ndarray:
    assert resp.status_code == 200, resp.text
    assert resp.headers["content-type"] == "image/png"
    return np.asarray(Image.open(io.BytesIO(resp.content)).convert("RGB"))


@pytest.fixture(scope="module")
def job(app_env):
    return add_job(app_env[1])


def test_capture_describes_the_stored_frames(app_env, job):
    client, _ = app_env
    body = get(client, f"/lightfield/{job}/capture").json()
    assert (body["width"], body["height"], body["frames"]) == (W, H, T)
    assert body["times"] == pytest.approx([i / FPS for i in range(T)])
    assert body["uses_time"] is True and body["bounds"]["t1"] == pytest.approx(BOUNDS.t1)


def test_capture_says_where_the_camera_and_its_fov_came_from(app_env):
    """What the page shows next to the frame: FOV source, tracking, notes from the file."""
    client, ctx = app_env
    tracking = {"method": "rotation", "camera_moves": True, "reprojection_error_px": 0.21, "frames_dropped": [3],
                "scale_source": "none: no translation", "cpu_seconds": 1.0}
    job = add_job(ctx, capture_meta={"static_camera": False, "warnings": ["no depth given: ..."], "metadata": {
        "intrinsics_source": "tracking: focal length refined", "tracking": tracking,
        "applied": ["EXIF orientation 6 (rotated 90 cw to view): turned upright"]}})
    body = get(client, f"/lightfield/{job}/capture").json()
    assert body["static_camera"] is False and body["intrinsics_source"] == "tracking: focal length refined"
    assert body["tracking"]["method"] == "rotation" and body["tracking"]["frames_dropped"] == [3]
    assert body["notes"] == ["EXIF orientation 6 (rotated 90 cw to view): turned upright"]
    assert body["warnings"] == ["no depth given: ..."] and body["poses_source"] is None
    plain = get(client, f"/lightfield/{add_job(ctx)}/capture").json()  # an older artefact: nothing recorded
    assert plain["tracking"] is None and plain["notes"] == [] and plain["intrinsics_source"] is None
    assert plain["grade"]["grade"] == "unchecked" and plain["grade"]["seen_share"] is None


def test_capture_carries_the_jobs_grade_and_its_fallback(app_env):
    client, ctx = app_env
    checked = add_job(ctx, quality={"grade": "partly explained", "residual_ratio": 0.8, "seen_share": 0.3,
                                    "fallback": None})
    assert get(client, f"/lightfield/{checked}/capture").json()["grade"] == {
        "grade": "partly explained", "seen_share": 0.3, "filled_share": 0.7, "residual_ratio": 0.8, "fallback": None}
    replaced = add_job(ctx, quality={"grade": "worse than a constant map", "residual_ratio": 1.4, "seen_share": 0.3,
                                     "fallback": {"reason": "worse than the constant map"}})
    grade = get(client, f"/lightfield/{replaced}/capture").json()["grade"]
    assert grade["fallback"] == "worse than the constant map" and grade["filled_share"] == 1.0


def test_frame_is_the_stored_frame_nearest_in_time(app_env, job):
    client, _ = app_env
    stored = preview().frames
    for t, index in ((0.0, 0), (0.74, 1), (0.76, 2), (99.0, T - 1), (-5.0, 0)):
        resp = get(client, f"/lightfield/{job}/frame", t=t)
        np.testing.assert_array_equal(png(resp), stored[index])
        assert resp.headers["x-lightfield-frame-index"] == str(index)


def test_probe_places_a_point_just_in_front_of_the_clicked_surface(app_env, job):
    client, _ = app_env
    body = get(client, f"/lightfield/{job}/probe", u=0.5, v=0.5, t=0.0).json()
    assert body["surface_depth"] == pytest.approx(WALL)
    assert body["depth"] == body["default_depth"] < WALL - body["radius"]
    # identity camera looking along -z: the image centre is straight ahead
    assert body["x"] == pytest.approx([0.0, 0.0, -body["depth"]], abs=1e-5)
    assert body["extrapolated"] == {"x": False, "t": False}
    moved = get(client, f"/lightfield/{job}/probe", u=0.5, v=0.5, t=0.0, depth=1.0).json()
    assert moved["depth"] == 1.0 and moved["x"] == pytest.approx([0.0, 0.0, -1.0], abs=1e-5)
    far = get(client, f"/lightfield/{job}/probe", u=0.5, v=0.5, t=0.0, depth=50.0).json()
    assert far["extrapolated"]["x"] is True


def test_probe_by_world_point_reports_where_it_appears(app_env, job):
    client, _ = app_env
    body = get(client, f"/lightfield/{job}/probe", x="0,0,-2", t=1.0).json()
    assert body["visible"] is True and (body["u"], body["v"]) == pytest.approx((0.5, 0.5))
    assert body["depth"] == pytest.approx(2.0) and body["frame_index"] == 2
    behind = get(client, f"/lightfield/{job}/probe", x="0,0,2", t=1.0).json()
    assert behind["visible"] is False and behind["u"] is None


def test_insertion_draws_balls_at_the_probe_and_leaves_the_rest_of_the_frame(app_env, job):
    client, _ = app_env
    frame = png(get(client, f"/lightfield/{job}/frame", t=0.5))
    out = png(get(client, f"/lightfield/{job}/insertion", t=0.5, points=f"0.3,0.5,{WALL - 0.5}"))
    assert out.shape == frame.shape
    diff = np.abs(out.astype(int) - frame.astype(int)).max(-1)
    ball_px = (int(0.5 * H), int(0.3 * W))
    assert diff[ball_px] > 20, "no ball at the probe"
    assert diff[:, -8:].max() <= 1 and diff[:4].max() <= 1, "pixels far from the balls changed"
    two = png(get(client, f"/lightfield/{job}/insertion", t=0.5, points="0.3,0.5,2.5;0.8,0.2,2.5"))
    assert np.abs(two.astype(int) - frame.astype(int)).max(-1)[int(0.2 * H), int(0.8 * W)] > 20


def test_a_field_without_time_is_queried_without_t(app_env):
    client, ctx = app_env
    job = add_job(ctx, uses_time=False)
    assert get(client, f"/lightfield/{job}/capture").json()["uses_time"] is False
    probe = get(client, f"/lightfield/{job}/probe", u=0.5, v=0.5, t=1.0).json()
    assert probe["extrapolated"] == {"x": False, "t": False}
    out = png(get(client, f"/lightfield/{job}/insertion", t=1.0, points="0.5,0.5,2.0"))
    frame = png(get(client, f"/lightfield/{job}/frame", t=1.0))
    assert np.abs(out.astype(int) - frame.astype(int)).max() > 20


def test_insertion_renders_each_frame_at_its_own_exposure(app_env):
    """A capture that stated its exposures: the field is in scene units, so the same ball is
    composited 2 stops darker into the frame taken 2 stops darker."""
    from core.conventions import inverse_tonemap

    client, ctx = app_env
    job = add_job(ctx, uses_time=False, frame_ev=[0.0, -2.0, 0.0, 0.0],
                  capture_meta={"metadata": {"exposure_source": "params"}})
    view = get(client, f"/lightfield/{job}/capture").json()
    assert view["exposure_source"] == "params" and view["frame_ev"] == [0.0, -2.0, 0.0, 0.0]
    balls = {}
    for t in (0.0, 0.5):  # frames 0 (ev 0) and 1 (ev -2)
        out = png(get(client, f"/lightfield/{job}/insertion", t=t, points=f"0.3,0.5,{WALL - 0.5}"))
        centre = out[int(0.5 * H) - 1: int(0.5 * H) + 2, int(0.3 * W) - 1: int(0.3 * W) + 2] / 255.0
        balls[t] = float(inverse_tonemap(torch.from_numpy(centre).float()).mean())
    assert balls[0.5] / balls[0.0] == pytest.approx(0.25, rel=0.15)
    plain = add_job(ctx, uses_time=False)
    view = get(client, f"/lightfield/{plain}/capture").json()
    assert view["exposure_source"] is None and view["frame_ev"] is None
    out = png(get(client, f"/lightfield/{plain}/insertion", t=0.5, points=f"0.3,0.5,{WALL - 0.5}"))
    centre = out[int(0.5 * H) - 1: int(0.5 * H) + 2, int(0.3 * W) - 1: int(0.3 * W) + 2] / 255.0
    assert float(inverse_tonemap(torch.from_numpy(centre).float()).mean()) == pytest.approx(balls[0.0], rel=0.05)


def test_insertion_of_a_large_frame_is_rendered_at_the_capped_height(app_env, job, monkeypatch):
    import service.routes.ui as routes_ui

    client, _ = app_env
    monkeypatch.setattr(routes_ui, "INSERTION_MAX_HEIGHT", H // 2)
    out = png(get(client, f"/lightfield/{job}/insertion", t=0.0, points="0.5,0.5,2.5"))
    assert out.shape == (H // 2, W // 2, 3)
    frame = png(get(client, f"/lightfield/{job}/frame", t=0.0)).astype(float)
    half = frame.reshape(H // 2, 2, W // 2, 2, 3).mean(axis=(1, 3))  # area average, as the engine resizes
    assert np.abs(out[:3].astype(float) - half[:3]).max() <= 1.5  # untouched rows keep the picture
    assert np.abs(out.astype(float) - half).max(-1)[H // 4, W // 4] > 20  # the ball at the probe


@pytest.mark.parametrize("path, params, status, code", [
    ("probe", {"u": 1.5, "v": 0.5}, 422, "invalid_probe"),
    ("probe", {"u": 0.5, "v": 0.5, "depth": -1}, 422, "invalid_probe"),
    ("probe", {"u": 0.5, "v": 0.5, "t": "nan"}, 422, "invalid_t"),
    ("probe", {"u": 0.5}, 422, "invalid_probe"),
    ("probe", {"u": 0.5, "v": 0.5, "x": "0,0,-1"}, 422, "invalid_probe"),
    ("probe", {"x": "0,0"}, 422, "invalid_x"),
    ("frame", {"t": "inf"}, 422, "invalid_t"),
    ("insertion", {"points": "0.5,0.5,abc"}, 422, "invalid_points"),
    ("insertion", {"points": "2,0.5,1"}, 422, "invalid_points"),
    ("insertion", {"points": ";".join(["0.5,0.5,2"] * (MAX_INSERTED_PROBES + 1))}, 422, "invalid_points"),
    ("insertion", {"points": "0.5,0.5,2", "env_height": 100000}, 422, "invalid_request"),
])
def test_bad_requests_get_a_specific_4xx(app_env, job, path, params, status, code):
    client, _ = app_env
    resp = get(client, f"/lightfield/{job}/{path}", **params)
    assert resp.status_code == status, resp.text
    assert resp.json()["error"]["code"] == code


def test_auth_tenancy_and_job_state_rules(app_env, job):
    client, ctx = app_env
    assert get(client, f"/lightfield/{job}/frame", tenant=None).status_code == 401
    resp = get(client, f"/lightfield/{job}/frame", tenant="bob")
    assert resp.status_code == 404 and resp.json()["error"]["code"] == "job_not_found"
    running = add_job(ctx, state="running")
    resp = get(client, f"/lightfield/{running}/capture")
    assert resp.status_code == 409 and resp.json()["error"]["code"] == "not_ready"
    bare = add_job(ctx, with_preview=False)
    resp = get(client, f"/lightfield/{bare}/probe", u=0.5, v=0.5)
    assert resp.status_code == 404 and resp.json()["error"]["code"] == "frames_unavailable"


def test_the_sample_room_scan_is_a_video_the_upload_accepts(app_env, tmp_path):
    """The page's 'Try a sample room scan' downloads this and uploads it as a user's video: an
    MP4 of the 46-frame scan, the same bytes on every call, with no key needed (not tenant data)."""
    from core.io.video import read_video

    client = app_env[0]
    first, second = client.get("/samples/room_scan.mp4"), get(client, "/samples/room_scan.mp4")
    assert first.status_code == 200 and first.headers["content-type"] == "video/mp4"
    assert first.content == second.content
    path = tmp_path / "scan.mp4"
    path.write_bytes(first.content)
    frames = read_video(path).frames
    assert frames.shape[:3] == (46, 144, 192)
