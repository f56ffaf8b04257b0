"""Replaying a capture as a live session over HTTP: what `lightfield stream` and
bench/live_sessions.py share.

The capture (a video with params, a nerfstudio zip or directory, a simulator capture) is read
here as the engine reads it (core.capture.load, without tracking) and sent frame by frame, at
its frame rate, as a phone would: each frame a PNG in the engine's convention with its pose
(when the capture has poses), its stated exposure and its depth (when the capture has a
depth file). Versions are followed on the session's SSE stream in a thread of their own.
"""
from __future__ import annotations

import io
import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import httpx


@dataclass(frozen=True)
class ReplayFrame:
    png: bytes
    pose: list[float] | None
    ev: float | None
    depth: bytes | None  # float32 [H, W] .npy


@dataclass
class ReplayCapture:
    frames: list[ReplayFrame]
    fps: float
    params: dict  # what the session is opened with: the capture's intrinsics and fps


def read_capture(path: Path, depth: Path | None = None, params: dict | None = None) -> ReplayCapture:
    import numpy as np  # noqa: PLC0415 — numpy is heavy: imported when used

    from core.capture.load import load_capture  # noqa: PLC0415 — core.capture pulls in torch, av, cv2: imported when used
    from core.capture.params import CaptureParams  # noqa: PLC0415 — core.capture pulls in torch: imported when used
    from core.io.images import encode_png  # noqa: PLC0415 — core.io pulls in PIL: imported when used

    params = dict(params or {})
    capture_keys = set(CaptureParams.model_fields)
    capture = load_capture(path, depth, CaptureParams(**{k: v for k, v in params.items() if k in capture_keys}))
    has_poses = bool(capture.metadata.get("poses_source"))
    has_depth = str(capture.depth_source).startswith("file")
    frames = []
    for i in range(capture.num_frames):
        depth_npy = None
        if has_depth:
            buf = io.BytesIO()
            np.save(buf, capture.depth[i].numpy().astype(np.float32), allow_pickle=False)
            depth_npy = buf.getvalue()
        frames.append(ReplayFrame(
            png=encode_png(capture.frames[i].numpy()),  # tagged as the engine's curve: read back as it was
            pose=[float(v) for v in capture.poses[i].reshape(-1).tolist()] if has_poses else None,
            ev=None if capture.stated_ev is None else float(capture.stated_ev[i]),
            depth=depth_npy))
    session_params = {k: v for k, v in params.items() if k not in ("poses", "frame_ev", "max_frames")}
    k = capture.intrinsics
    session_params["intrinsics"] = {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy}
    session_params["fps"] = capture.fps
    return ReplayCapture(frames, capture.fps, session_params)


@dataclass
class SessionClient:
    base_url: str
    key: str | None = None
    timeout_s: float = 60.0
    events: list[tuple[float, str, dict]] = field(default_factory=list)  # (arrival, event, data)
    _http: httpx.Client | None = None

    def __post_init__(self):
        headers = {"Authorization": f"Bearer {self.key}"} if self.key else {}
        self._http = httpx.Client(base_url=self.base_url, timeout=self.timeout_s, headers=headers)

    def close(self) -> None:
        self._http.close()

    def open(self, params: dict) -> str:
        resp = self._http.post("/sessions", json=params)
        _check(resp, "POST /sessions")
        return resp.json()["id"]

    def send(self, sid: str, frames: list[ReplayFrame]) -> dict:
        files = [("frame", (f"{i}.png", f.png, "image/png")) for i, f in enumerate(frames)]
        files += [("depth", (f"{i}.npy", f.depth, "application/octet-stream")) for i, f in enumerate(frames) if f.depth]
        meta = {}
        if frames[0].pose is not None:
            meta["poses"] = [f.pose for f in frames]
        if frames[0].ev is not None:
            meta["ev"] = [f.ev for f in frames]
        for _attempt in range(20):  # 429: the session's rate limit; wait the second out
            resp = self._http.post(f"/sessions/{sid}/frames", files=files, data={"meta": json.dumps(meta)})
            if resp.status_code != 429:
                break
            time.sleep(float(resp.headers.get("Retry-After", "1")))
        _check(resp, "POST frames")
        return resp.json()

    def end(self, sid: str) -> dict:
        resp = self._http.delete(f"/sessions/{sid}")
        _check(resp, "DELETE session")
        return resp.json()

    def get(self, path: str, **params) -> httpx.Response:
        return self._http.get(path, params=params)

    def follow(self, sid: str, probes: list[str], on_event: Callable[[str, dict], None] | None = None
               ) -> threading.Thread:
        """The session's SSE stream in a daemon thread, events kept in `self.events`; it ends
        with the session (event `ended`)."""
        def run():
            name = None
            with httpx.Client(base_url=self.base_url, headers=self._http.headers, timeout=None) as http:
                with http.stream("GET", f"/sessions/{sid}/events", params={"x": probes}) as resp:
                    for line in resp.iter_lines():
                        if line.startswith("event: "):
                            name = line[7:]
                        elif line.startswith("data: "):
                            data = json.loads(line[6:])
                            self.events.append((time.monotonic(), name, data))
                            if on_event is not None:
                                on_event(name, data)
                            if name in ("ended", "deleted"):
                                return

        thread = threading.Thread(target=run, name=f"sse-{sid[:8]}", daemon=True)
        thread.start()
        return thread


def _check(resp: httpx.Response, what: str) -> None:
    if resp.status_code >= 400:
        raise RuntimeError(f"{what}: {resp.status_code} {resp.text[:500]}")


def replay(client: SessionClient, sid: str, capture: ReplayCapture, *, batch: int = 1, speed: float = 1.0,
           on_sent: Callable[[int, float], None] | None = None) -> list[float]:
    """Send the capture's frames `batch` at a time, paced at its frame rate x `speed`
    (0: as fast as accepted). Returns each batch's send time (time.monotonic())."""
    start, sent_at = time.monotonic(), []
    for first in range(0, len(capture.frames), batch):
        due = start + first / (capture.fps * speed) if speed > 0 else 0.0
        time.sleep(max(0.0, due - time.monotonic()))
        chunk = capture.frames[first:first + batch]
        client.send(sid, chunk)
        sent_at.append(time.monotonic())
        if on_sent is not None:
            on_sent(first + len(chunk), sent_at[-1])
    return sent_at
