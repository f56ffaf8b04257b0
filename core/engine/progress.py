"""Progress reporting and cancellation for long jobs (CLI progress bar, Celery task state)."""
from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from typing import Callable, Iterator


class Cancelled(RuntimeError):
    """Raised inside the engine when `should_cancel()` returns True."""


@dataclass(frozen=True)
class Progress:
    stage: str  # "loading" | "point_cloud" | "temporal" | "distill" | "saving" | "done"
    iteration: int
    total: int
    loss: float | None
    fraction: float  # overall job fraction in [0, 1]
    eta_s: float | None
    message: str = ""

    def as_dict(self) -> dict:
        return asdict(self)


ProgressCallback = Callable[[Progress], None]
CancelCheck = Callable[[], bool]


class StageTimer:
    """Wall time per named stage (loading, point cloud, prior, field rendering, optimisation),
    reported in the artefact so a user sees what the job simulated and what it cost."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - t0
            self.calls[name] += 1

    def as_dict(self) -> dict:
        return {k: {"seconds": round(v, 4), "calls": self.calls[k]} for k, v in self.seconds.items()}


class Reporter:
    """Turns loop positions into `Progress` events and checks for cancellation.

    The distillation stage is assumed to dominate the job: it covers the fraction range
    [distill_start, 0.98]; ETA extrapolates the mean step time of this run (resumed steps
    excluded, so a resumed job does not claim to be faster than it is).
    """

    def __init__(self, callback: ProgressCallback | None, should_cancel: CancelCheck | None,
                 distill_start: float = 0.1):
        self._cb = callback
        self._cancel = should_cancel
        self._distill_start = distill_start
        self._t0: float | None = None
        self._first_iter = 0

    def check_cancel(self) -> None:
        if self._cancel is not None and self._cancel():
            raise Cancelled("job cancelled")

    def stage(self, stage: str, fraction: float, message: str = "") -> None:
        self.check_cancel()
        if self._cb is not None:
            self._cb(Progress(stage, 0, 0, None, float(fraction), None, message))

    def begin(self, start_iteration: int) -> None:
        """Mark the start of the optimisation (after a possible resume at `start_iteration`)."""
        self._t0, self._first_iter = time.perf_counter(), start_iteration

    def step(self, iteration: int, total: int, loss: float | None) -> None:
        """Called after finishing step `iteration` (1-based count of completed steps)."""
        if self._t0 is None:
            self.begin(iteration - 1)
        done = iteration - self._first_iter
        eta = (time.perf_counter() - self._t0) / done * max(total - iteration, 0) if done > 0 else None
        frac = self._distill_start + (0.98 - self._distill_start) * (iteration / max(total, 1))
        if self._cb is not None:
            self._cb(Progress("distill", iteration, total, loss, frac, eta))
        self.check_cancel()
