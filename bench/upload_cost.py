"""What one upload costs the service: how many times a job's capture is decoded, and how much
memory the API process needs to accept a small file that declares a long HD video.

Both run the product as a user does, through real processes (redis-server, `lightfield
serve` in API-only mode, a Celery worker) and HTTP:

* decodes: a small MP4 (6 frames, 64x48) and a depth file go through POST /jobs and a
  worker (tiny distillation budget) to `succeeded`. Every process counts its calls of the
  full decoders core.io.read_video / read_image / read_depth (a sitecustomize on the
  children's PYTHONPATH wraps them; header probes are not decodes) and the counts are
  reported per process (API, worker).
* API memory: an MP4 of FRAMES identical 1280x720 frames (H.264 makes it ~100 KB) is
  POSTed to an API with no worker; the API's resident memory before the request (VmRSS)
  and its peak after it (VmHWM, from /proc) are reported.

    python bench/upload_cost.py [--frames 3000] [-o result.json]

The script only uses interfaces the service had before the architecture change as well
(HTTP, service.processes), so the same file measures an older checkout: run it with that
checkout first on PYTHONPATH.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

if __name__ == "__main__" and not os.environ.get("PYTHONPATH"):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DECODERS = ("read_video", "read_image", "read_depth")

# Installed in every child Python process of the decode measurement: wraps the decoders of
# core.io (the package attribute and the defining module's) when core.io is first imported.
SITECUSTOMIZE = '''
import builtins, os, sys

_LOG = os.environ.get("UPLOAD_COST_LOG")
_real_import = builtins.__import__


def _wrap(module, name):
    fn = getattr(module, name, None)
    if fn is None or getattr(fn, "_counted", False):
        return
    def counted(*a, **k):
        with open(_LOG, "a") as f:
            f.write(f"{os.getpid()} {name}\\n")
        return fn(*a, **k)
    counted._counted = True
    setattr(module, name, counted)


def _patch():
    io = sys.modules.get("core.io")
    readers = (("read_video", "core.io.video"), ("read_image", "core.io.images"), ("read_depth", "core.io.depth"))
    for name, sub in readers:
        if io is not None:
            _wrap(io, name)
        if sub in sys.modules:
            _wrap(sys.modules[sub], name)


def _import(name, *args, **kwargs):
    module = _real_import(name, *args, **kwargs)
    if name.startswith("core"):
        _patch()
    return module


if _LOG:
    builtins.__import__ = _import
'''


def _env(**extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env.update({"OMP_NUM_THREADS": "1", **extra})
    return env


def _proc_kb(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def write_long_video(path: Path, frames: int, width: int = 1280, height: int = 720, fps: int = 30) -> Path:
    """An MP4 of `frames` identical frames: H.264 stores the repeats as near-empty P-frames."""
    import av
    import numpy as np

    image = np.zeros((height, width, 3), np.uint8)
    image[..., 0] = np.linspace(0, 255, width, dtype=np.uint8)[None]
    image[..., 1] = np.linspace(0, 255, height, dtype=np.uint8)[:, None]
    with av.open(str(path), mode="w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.options = {"crf": "30", "preset": "ultrafast"}
        frame = av.VideoFrame.from_ndarray(image, format="rgb24")
        for _ in range(frames):
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


class Stack:
    """redis-server + an API-only `lightfield serve` (+ optionally one worker), on loopback."""

    def __init__(self, root: Path, workers: int, env: dict[str, str]):
        from service.processes import free_port, spawn, start_redis, worker_command

        self.root = root
        self.redis = start_redis(root / "redis")
        self.env = {**env, "LIGHTFIELD_BROKER_URL": self.redis.url, "LIGHTFIELD_DATA_DIR": str(root / "data")}
        self.workers = [
            spawn(worker_command(f"w{i}", loglevel="WARNING"), env=self.env, log_path=root / f"worker{i}.log")
            for i in range(workers)
        ]
        self.port = free_port()
        self.api = spawn([sys.executable, "-m", "cli", "serve", "--port", str(self.port), "--log-level", "warning"],
                         env=self.env, log_path=root / "api.log")
        self.url = f"http://127.0.0.1:{self.port}"
        self._wait(lambda: self.get("/healthz").status_code == 200, 120, "the API")
        if workers:
            self._wait(lambda: self.get("/readyz").status_code == 200, 120, "a worker")

    def get(self, path: str):
        import httpx

        return httpx.get(self.url + path, timeout=30)

    def submit(self, files: dict, params: dict):
        import httpx

        return httpx.post(self.url + "/jobs", files=files, data={"params": json.dumps(params)}, timeout=600)

    def _wait(self, ok, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.api.poll() is not None:
                raise RuntimeError(f"the API exited: {(self.root / 'api.log').read_text()[-2000:]}")
            try:
                if ok():
                    return
            except Exception:
                pass
            time.sleep(0.2)
        raise TimeoutError(f"{what} did not become ready within {timeout_s} s")

    def stop(self) -> None:
        from service.processes import stop

        stop(self.api, signal.SIGTERM, grace_s=10)
        for w in self.workers:
            stop(w, signal.SIGQUIT, grace_s=5)
        self.redis.stop()


def measure_decodes(root: Path) -> dict:
    """Decoder calls per process for one small video job with a depth file, API to worker."""
    import numpy as np

    from core.io import write_depth_npz, write_video

    media = root / "media"
    media.mkdir(parents=True)
    frames = np.random.default_rng(0).random((6, 48, 64, 3)).astype(np.float32)
    video = write_video(media / "clip.mp4", frames, fps=6.0)
    depth = write_depth_npz(media / "depth.npz", np.full((48, 64), 2.5, np.float32))
    hook = root / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(SITECUSTOMIZE)
    log = root / "decodes.log"
    log.touch()
    repo = str(Path(__file__).resolve().parents[1])
    pythonpath = os.pathsep.join([str(hook), os.environ.get("PYTHONPATH") or repo])
    env = _env(UPLOAD_COST_LOG=str(log), PYTHONPATH=pythonpath,
               LIGHTFIELD_DISTILL_OVERRIDES='{"iterations": 4, "work_height": 24, "warmup_steps": 1}')
    stack = Stack(root / "stack", workers=1, env=env)
    try:
        with open(video, "rb") as fv, open(depth, "rb") as fd:
            r = stack.submit({"file": ("clip.mp4", fv), "depth": ("depth.npz", fd)}, {"preset": "draft", "fps": 6.0})
        r.raise_for_status()
        job = r.json()["id"]
        state = ""
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline:
            state = stack.get(f"/jobs/{job}").json()["state"]
            if state in ("succeeded", "failed", "cancelled"):
                break
            time.sleep(0.5)
        roles = {stack.api.pid: "api", stack.workers[0].pid: "worker"}
    finally:
        stack.stop()
    calls: dict[str, dict[str, int]] = {}
    for line in log.read_text().split("\n"):
        if line.strip():
            pid, name = line.split()
            role = roles.get(int(pid), f"pid {pid}")
            calls.setdefault(role, {}).setdefault(name, 0)
            calls[role][name] += 1
    video_decodes = sum(c.get("read_video", 0) for c in calls.values())
    return {"job_state": state, "decoder_calls": calls, "video_decodes_per_job": video_decodes,
            "depth_decodes_per_job": sum(c.get("read_depth", 0) for c in calls.values())}


def measure_api_memory(root: Path, frames: int) -> dict:
    """The API's memory around one upload of a small MP4 declaring `frames` 720p frames (no worker)."""
    root.mkdir(parents=True)
    video = write_long_video(root / "long.mp4", frames)
    stack = Stack(root / "stack", workers=0, env=_env())
    try:
        before_kb = _proc_kb(stack.api.pid, "VmRSS")
        t0 = time.perf_counter()
        with open(video, "rb") as f:
            r = stack.submit({"file": ("long.mp4", f)}, {"preset": "draft"})
        seconds = time.perf_counter() - t0
        peak_kb = _proc_kb(stack.api.pid, "VmHWM")
    finally:
        stack.stop()
    return {"upload_bytes": video.stat().st_size, "declared_frames": frames, "frame_size": "1280x720",
            "status": r.status_code, "response_seconds": round(seconds, 2),
            "api_rss_before_mb": round(before_kb / 1024, 1), "api_peak_rss_after_mb": round(peak_kb / 1024, 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=3000, help="declared frames of the long 720p upload")
    parser.add_argument("-o", "--output", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="upload-cost-") as tmp:
        result = {"decodes": measure_decodes(Path(tmp) / "decodes"),
                  "api_memory": measure_api_memory(Path(tmp) / "memory", args.frames)}
    text = json.dumps(result, indent=2)
    print(text)
    if args.output:
        args.output.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
