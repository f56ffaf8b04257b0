"""The service under load, as users meet it (issue 14's targets): one finished draft job in
the embedded service (`lightfield serve`: its own Redis, a Celery worker, the API), then

* load: C concurrent clients (keep-alive HTTP/1.1, a minimal asyncio client so the load
  generator costs the shared CPU as little as possible) asking GET /lightfield/{id}/envmap
  for 64x128 maps at random positions and times inside the scene, with every other
  parameter at its default (format exr, quality fast), for D seconds after a warm-up;
  meanwhile one client polls /healthz every 50 ms. Answers/s, latency percentiles, non-200s;
* single requests: a 1024x2048 EXR and a 128-px cube map (JSON, one EXR per face), default
  quality and quality=exact;
* accuracy of the cheaper qualities against exact evaluation at random (x, t), at 64 and 256
  rows: `fast` (the default: the field at a quarter of the rows, upsampled) and `baked` (the
  worker's lattice, interpolated); relative RMSE per map and relative error of its mean;
* API memory: resident set of the API process sampled every 50 ms, around the upload of a
  small MP4 that declares 3000 1280x720 frames (first, on the fresh API; cancelled at once)
  and through all the queries.

The job: the simulator's `spatial` suite (a room with two strong near lamps, as `make demo`),
uploaded with its depth, intrinsics and poses, distilled with the draft preset.

    python bench/service_load.py [--clients 100] [--duration 20] [--iterations N] [-o bench/results]

Writes service_load.json and service_load.md to the output directory. Numbers depend on the
machine and on what else runs: the load average is recorded at start and end.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import platform
import random
import sys
import tempfile
import threading
import time
from pathlib import Path

if __name__ == "__main__" and not os.environ.get("PYTHONPATH"):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

TARGETS = {"answers_per_s": 300, "p99_s": 1.0, "healthz_p99_s": 0.1, "exr1024_s": 2.0, "cube128_s": 0.2,
           "api_rss_mb": 1024}


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, math.ceil(q * len(ordered)) - 1))]


def summary(values: list[float]) -> dict:
    return {"n": len(values), "p50": round(pct(values, 0.5), 4), "p90": round(pct(values, 0.9), 4),
            "p99": round(pct(values, 0.99), 4), "max": round(max(values), 4) if values else None}


# -- a minimal keep-alive HTTP/1.1 client ---------------------------------------------------------------
class Connection:
    def __init__(self, port: int):
        self.port = port
        self.reader = self.writer = None

    async def request(self, path: str) -> tuple[int, bytes]:
        for attempt in (0, 1):
            if self.writer is None:
                self.reader, self.writer = await asyncio.open_connection("127.0.0.1", self.port)
            try:
                self.writer.write(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{self.port}\r\n\r\n".encode())
                head = await self.reader.readuntil(b"\r\n\r\n")
                break
            except (ConnectionError, asyncio.IncompleteReadError):
                self.close()
                if attempt:
                    raise
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split()[1])
        headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:] if line)}
        body = await self.reader.readexactly(int(headers.get("content-length", "0")))
        if headers.get("connection", "").lower() == "close":
            self.close()
        return status, body

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.reader = self.writer = None


async def run_clients(port: int, paths, clients: int, measure_from: float, stop_at: float) -> dict:
    """`clients` keep-alive connections asking paths(rng) back to back; latencies of the
    answers that start after `measure_from` and end before `stop_at` (time.time())."""
    latencies: list[float] = []
    statuses: dict[int, int] = {}

    async def client(k: int) -> None:
        conn = Connection(port)
        rng = random.Random(k)
        while time.time() < stop_at:
            path = paths(rng)
            t0 = time.time()
            try:
                status, _ = await conn.request(path)
            except (ConnectionError, asyncio.IncompleteReadError):
                status = 0
            t1 = time.time()
            if t0 >= measure_from and t1 <= stop_at:
                latencies.append(t1 - t0)
                statuses[status] = statuses.get(status, 0) + 1
        conn.close()

    await asyncio.gather(*(client(k) for k in range(clients)))
    return {"latencies": latencies, "statuses": statuses}


def _clients_process(port, paths, clients, measure_from, stop_at, nice, out) -> None:
    """The load generator, in its own process at a lower priority: real clients would run on
    other machines, here they share the server's 2 cores and should not starve it."""
    os.nice(nice)
    out.put(asyncio.run(run_clients(port, paths, clients, measure_from, stop_at)))


async def probe_health(port: int, measure_from: float, stop_at: float, every_s: float = 0.05) -> dict:
    conn, latencies, statuses = Connection(port), [], {}
    while time.time() < stop_at:
        t0 = time.time()
        status, _ = await conn.request("/healthz")
        if t0 >= measure_from:
            latencies.append(time.time() - t0)
            statuses[status] = statuses.get(status, 0) + 1
        await asyncio.sleep(every_s)
    conn.close()
    return {"latencies": latencies, "statuses": statuses}


def load_phase(port: int, paths, clients: int, warmup_s: float, duration_s: float, nice: int = 10) -> dict:
    """Clients in a niced child process, /healthz probed from this one at normal priority."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    start = time.time() + 2.0  # the child's interpreter start-up
    measure_from, stop_at = start + warmup_s, start + warmup_s + duration_s
    child = ctx.Process(target=_clients_process, args=(port, paths, clients, measure_from, stop_at, nice, out))
    child.start()
    health = asyncio.run(probe_health(port, measure_from, stop_at))
    load = out.get(timeout=duration_s + warmup_s + 120)
    child.join(timeout=30)
    latencies = load["latencies"]
    return {"clients": clients, "duration_s": duration_s, "load_generator_nice": nice, "answers": len(latencies),
            "answers_per_s": round(len(latencies) / duration_s, 1), "latency_s": summary(latencies),
            "statuses": {str(k): v for k, v in sorted(load["statuses"].items())},
            "healthz_s": summary(health["latencies"]),
            "healthz_statuses": {str(k): v for k, v in health["statuses"].items()}}


# -- memory sampling ---------------------------------------------------------------------------------
class RssSampler:
    def __init__(self, pid: int, interval_s: float = 0.05):
        import psutil

        self.proc = psutil.Process(pid)
        self.interval_s = interval_s
        self.peak = 0
        self.samples: list[tuple[str, int]] = []
        self._label = "start"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def mark(self, label: str) -> int:
        rss = self.proc.memory_info().rss
        self._label = label
        return rss

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                rss = self.proc.memory_info().rss
            except Exception:
                return
            self.peak = max(self.peak, rss)
            self.samples.append((self._label, rss))

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(timeout=2)

    def peak_of(self, label: str) -> int:
        return max((r for lab, r in self.samples if lab == label), default=0)


# -- the job ------------------------------------------------------------------------------------------
def simulated_upload(root: Path) -> tuple[Path, Path, dict]:
    from core.sim.capture import write_capture
    from core.sim.suites import suite

    scene = suite("spatial")
    doc = write_capture(scene, root / "capture", envmap_height=16, video=scene.frames > 1)
    k = doc["intrinsics"]
    params = {"intrinsics": {n: k[n] for n in ("fx", "fy", "cx", "cy")}, "poses": doc["poses"], "fps": doc["fps"],
              "preset": "draft"}
    media = doc["video"] if scene.frames > 1 else doc["frames"][0]
    return root / "capture" / media, root / "capture" / doc["depth"], params


class EnvmapPaths:
    """GET /lightfield/{job}/envmap at a random point and time inside the scene box, every
    other parameter at its default (picklable: the load generator is another process)."""

    def __init__(self, job: str, bounds: dict, height: int, extra: str = ""):
        self.job, self.bounds, self.height, self.extra = job, bounds, height, extra

    def __call__(self, rng) -> str:
        b = self.bounds
        x = ",".join(f"{rng.uniform(lo, hi):.4f}" for lo, hi in zip(b["lo"], b["hi"]))
        t = rng.uniform(b["t0"], b["t1"])
        return f"/lightfield/{self.job}/envmap?x={x}&t={t:.4f}&height={self.height}{self.extra}"


def timed_get(client, path: str, params: dict, reps: int) -> dict:
    times, size = [], 0
    for _ in range(reps):
        t0 = time.perf_counter()
        resp = client.get(path, params=params)
        times.append(time.perf_counter() - t0)
        if resp.status_code != 200:
            raise RuntimeError(f"GET {path} {params}: {resp.status_code} {resp.text[:300]}")
        size = len(resp.content)
    return {"reps": reps, "s": summary(times), "bytes": size, "quality": resp.headers.get("x-lightfield-quality")}


def accuracy(client, job: str, points: list[tuple[str, float]], height: int, quality: str) -> dict:
    import io

    import numpy as np

    rel_rmse, rel_mean = [], []
    for x, t in points:
        maps = {}
        for q in (quality, "exact"):
            resp = client.get(f"/lightfield/{job}/envmap",
                              params={"x": x, "t": t, "height": height, "format": "npy", "quality": q})
            resp.raise_for_status()
            maps[q] = np.load(io.BytesIO(resp.content)).astype(np.float64)
        approx, exact = maps[quality], maps["exact"]
        rel_rmse.append(float(np.sqrt(((approx - exact) ** 2).mean()) / np.sqrt((exact ** 2).mean())))
        rel_mean.append(float(abs(approx.mean() - exact.mean()) / exact.mean()))
    return {"quality": quality, "height": height, "points": len(points), "relative_rmse": summary(rel_rmse),
            "relative_mean_error": summary(rel_mean)}


def upload_memory(svc, sampler: RssSampler, root: Path, frames: int) -> dict:
    from bench.upload_cost import write_long_video

    video = write_long_video(root / "long.mp4", frames)
    before = sampler.mark("upload")
    t0 = time.perf_counter()
    resp = svc.client.post("/jobs", files={"file": ("long.mp4", video.read_bytes())}, data={"params": "{}"})
    elapsed = time.perf_counter() - t0
    time.sleep(0.5)
    peak = max(sampler.peak_of("upload"), sampler.mark("after-upload"))
    if resp.status_code == 202:  # cancel it, and let the worker stop before the load test
        job = resp.json()["id"]
        svc.client.delete(f"/jobs/{job}")
        deadline = time.time() + 120
        while time.time() < deadline and svc.client.get(f"/jobs/{job}").json()["state"] in ("queued", "running"):
            time.sleep(0.5)
    return {"file_bytes": video.stat().st_size, "declared_frames": frames, "status": resp.status_code,
            "response_s": round(elapsed, 3), "api_rss_before_mb": round(before / 2**20),
            "api_rss_peak_mb": round(peak / 2**20)}


def markdown(r: dict) -> str:
    load, t = r["load"], TARGETS
    ok = lambda good: "met" if good else "**missed**"  # noqa: E731
    lines = [
        "# Service under load (`bench/service_load.py`)", "",
        f"Generated {r['when']} on {r['machine']} ({r['cpu_count']} CPUs), commit {r['commit']}; "
        f"load average at start {r['load_average_start']}, at end {r['load_average_end']} "
        "(other processes share this machine; the load generator runs on it too, at nice +10 "
        "so that it does not take the server's CPU as clients on other machines would not).", "",
        f"Job: the simulator's `spatial` room, draft preset ({r['job']['iterations']} iterations, "
        f"field `{r['job']['field']}`), distilled by the embedded worker in {r['job']['wall_s']} s.", "",
        "| target | measured | |", "|---|---|---|",
        f"| >= {t['answers_per_s']} answers/s, {load['clients']} clients, 64x128 EXR, default quality "
        f"| {load['answers_per_s']} answers/s | {ok(load['answers_per_s'] >= t['answers_per_s'])} |",
        f"| p99 <= {t['p99_s']} s | p50 {load['latency_s']['p50']} s, p99 {load['latency_s']['p99']} s "
        f"| {ok(load['latency_s']['p99'] <= t['p99_s'])} |",
        f"| no non-200 | statuses {load['statuses']} | {ok(set(load['statuses']) == {'200'})} |",
        f"| (same load, `quality=baked`) | {r['load_baked']['answers_per_s']} answers/s, p99 "
        f"{r['load_baked']['latency_s']['p99']} s, /healthz p99 {r['load_baked']['healthz_s']['p99']} s, "
        f"statuses {r['load_baked']['statuses']} | at the accuracy cost below |",
        f"| /healthz p99 <= {t['healthz_p99_s']} s during the load | p50 {load['healthz_s']['p50']} s, "
        f"p99 {load['healthz_s']['p99']} s, max {load['healthz_s']['max']} s "
        f"| {ok(load['healthz_s']['p99'] <= t['healthz_p99_s'])} |",
        f"| 1024x2048 EXR <= {t['exr1024_s']} s | {r['exr1024']['fast']['s']['p50']} s (p50 of "
        f"{r['exr1024']['fast']['reps']}; exact: {r['exr1024']['exact']['s']['p50']} s) "
        f"| {ok(r['exr1024']['fast']['s']['p50'] <= t['exr1024_s'])} |",
        f"| 128-px cube map <= {t['cube128_s']} s | {r['cube128']['fast']['s']['p50']} s (p50 of "
        f"{r['cube128']['fast']['reps']}; exact: {r['cube128']['exact']['s']['p50']} s) "
        f"| {ok(r['cube128']['fast']['s']['p50'] <= t['cube128_s'])} |",
        f"| API memory <= {t['api_rss_mb']} MB for any accepted upload | {r['upload']['api_rss_before_mb']} -> "
        f"{r['upload']['api_rss_peak_mb']} MB around a {r['upload']['file_bytes'] // 1024} KB MP4 declaring "
        f"{r['upload']['declared_frames']} 720p frames (HTTP {r['upload']['status']} in "
        f"{r['upload']['response_s']} s); peak over all the queries that followed: {r['api_rss_peak_mb']} MB "
        f"| {ok(r['upload']['api_rss_peak_mb'] <= t['api_rss_mb'])} |", "",
        "Accuracy against `quality=exact` at random points and times inside the scene: `fast` (the default: "
        "the field at (x, t) at a quarter of the rows, at least 16, upsampled) and `baked` (the worker's "
        "5x5x5 lattice, interpolated in x and t):", "",
        "| quality | rows | points | relative RMSE p50 / p90 / max | relative error of the mean p50 / p90 / max |",
        "|---|---|---|---|---|",
    ]
    for a in r["accuracy"]:
        lines.append(f"| {a['quality']} | {a['height']} | {a['points']} | {a['relative_rmse']['p50']} / "
                     f"{a['relative_rmse']['p90']} / "
                     f"{a['relative_rmse']['max']} | {a['relative_mean_error']['p50']} / "
                     f"{a['relative_mean_error']['p90']} / {a['relative_mean_error']['max']} |")
    lines += ["", f"Load phase detail: {json.dumps(load)}", "", f"Baked load phase: {json.dumps(r['load_baked'])}", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", type=int, default=100)
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--warmup", type=float, default=3.0)
    ap.add_argument("--iterations", type=int, default=None, help="distillation steps (default: the draft preset's)")
    ap.add_argument("--upload-frames", type=int, default=3000)
    ap.add_argument("-o", "--out", type=Path, default=Path("bench/results"))
    args = ap.parse_args(argv)

    import subprocess

    from service.local import EmbeddedService

    root = Path(tempfile.mkdtemp(prefix="lf-load-"))
    env = {"PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    if args.iterations:
        env["LIGHTFIELD_DISTILL_OVERRIDES"] = json.dumps({"iterations": args.iterations})
    result: dict = {"when": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": platform.processor() or platform.machine(),
                    "cpu_count": os.cpu_count(), "load_average_start": [round(v, 2) for v in os.getloadavg()],
                    "commit": subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], capture_output=True,
                                             text=True).stdout.strip(), "targets": TARGETS}
    svc = EmbeddedService(root / "data", env=env).start()
    try:
        with RssSampler(svc.proc.pid) as sampler:
            file, depth, params = simulated_upload(root)
            t0 = time.perf_counter()
            job = svc.submit(file, params, depth)
            svc.wait(job, timeout_s=3600)
            meta = svc.client.get(f"/lightfield/{job}").json()["metadata"]
            result["job"] = {"wall_s": round(time.perf_counter() - t0, 1), "iterations": meta["training"]["iterations"],
                             "field": meta["field"]["kind"]}
            b = meta["bounds"]
            print(f"job {job} done in {result['job']['wall_s']} s", file=sys.stderr)

            def random_point(rng) -> tuple[str, float]:
                x = ",".join(f"{rng.uniform(lo, hi):.4f}" for lo, hi in zip(b["lo"], b["hi"]))
                return x, round(rng.uniform(b["t0"], b["t1"]), 4)

            result["upload"] = upload_memory(svc, sampler, root, args.upload_frames)
            sampler.mark("load")
            paths = EnvmapPaths(job, b, height=64)
            result["load"] = load_phase(svc.port, paths, args.clients, args.warmup, args.duration)
            print(json.dumps(result["load"]), file=sys.stderr)
            result["load_baked"] = load_phase(svc.port, EnvmapPaths(job, b, height=64, extra="&quality=baked"),
                                              args.clients, args.warmup, args.duration)
            print(json.dumps(result["load"]), file=sys.stderr)
            sampler.mark("single")
            x, t = random_point(random.Random(0))
            envmap, cubemap = f"/lightfield/{job}/envmap", f"/lightfield/{job}/cubemap"
            result["exr1024"] = {"fast": timed_get(svc.client, envmap, {"x": x, "t": t, "height": 1024}, 5),
                                 "exact": timed_get(svc.client, envmap, {"x": x, "t": t, "height": 1024,
                                                                         "quality": "exact"}, 1)}
            result["cube128"] = {"fast": timed_get(svc.client, cubemap, {"x": x, "t": t, "size": 128}, 10),
                                 "exact": timed_get(svc.client, cubemap, {"x": x, "t": t, "size": 128,
                                                                          "quality": "exact"}, 3)}
            rng = random.Random(1)
            points = [random_point(rng) for _ in range(16)]
            result["accuracy"] = [accuracy(svc.client, job, points, h, q) for q in ("fast", "baked") for h in (64, 256)]
        result["api_rss_peak_mb"] = round(sampler.peak / 2**20)
    finally:
        svc.stop()
    result["load_average_end"] = [round(v, 2) for v in os.getloadavg()]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "service_load.json").write_text(json.dumps(result, indent=2) + "\n")
    (args.out / "service_load.md").write_text(markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
