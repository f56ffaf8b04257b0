"""Wall time, CPU time and peak memory of a block of code, plus the machine a run happened on.

CPU time (time.process_time: all threads of this process) is reported next to wall time
because a shared machine inflates wall time by whatever else runs; with the bench's single
intra-op thread, CPU time is close to what the wall time would be on an idle machine.

Peak memory is the peak RESIDENT SET SIZE increase over the block's starting RSS, sampled
from /proc/self/statm every 5 ms by a background thread. tracemalloc would miss torch's
tensors (they are not allocated through Python's allocator). Caveats: memory freed by an
earlier block and reused by the allocator is not counted again, so numbers are lower
bounds of what a fresh process needs; spikes shorter than the sampling period can be missed.
"""
from __future__ import annotations

import datetime as _dt
import os
import platform
import subprocess
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

MEMORY_METHOD = "peak RSS increase over the block's start, /proc/self/statm sampled every 5 ms"
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def rss_bytes() -> int:
    """Current resident set size of this process (0 where /proc is unavailable)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        return 0


@dataclass
class Measurement:
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    peak_rss_delta_mb: float = 0.0

    def as_dict(self) -> dict:
        return {"seconds": round(self.seconds, 4), "cpu_seconds": round(self.cpu_seconds, 4),
                "peak_rss_delta_mb": round(self.peak_rss_delta_mb, 2)}


class _PeakSampler(threading.Thread):
    def __init__(self, period: float = 0.005):
        super().__init__(daemon=True)
        self.period = period
        self.start_rss = rss_bytes()
        self.peak = self.start_rss
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.is_set():
            self.peak = max(self.peak, rss_bytes())
            self._stop_event.wait(self.period)

    def stop(self) -> float:
        self._stop_event.set()
        self.join()
        self.peak = max(self.peak, rss_bytes())
        return (self.peak - self.start_rss) / 2**20


@contextmanager
def measured():
    """`with measured() as m: ...` fills m.seconds, m.cpu_seconds and m.peak_rss_delta_mb."""
    m = Measurement()
    sampler = _PeakSampler()
    sampler.start()
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        yield m
    finally:
        m.seconds = time.perf_counter() - t0
        m.cpu_seconds = time.process_time() - c0
        m.peak_rss_delta_mb = sampler.stop()


def machine_info(repo: Path | None = None) -> dict:
    """CPU model, cores, load, torch version, date and git commit: what the numbers depend on."""
    import torch

    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    commit, dirty = "unknown", None
    try:
        cwd = repo or Path(__file__).resolve().parents[2]
        commit = (
            subprocess.run(
                ["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=10
            ).stdout.strip()
            or "unknown"
        )
        status = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout
        dirty = bool(status.strip())
    except (OSError, subprocess.SubprocessError):
        pass
    try:
        load = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        load = None
    return {
        "cpu_model": cpu,
        "cores": os.cpu_count(),
        "load_average_1_5_15min": load,
        "torch_version": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "date_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "git_commit": commit,
        "git_tracked_files_modified": dirty,
        "memory_method": MEMORY_METHOD,
    }
