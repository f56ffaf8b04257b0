"""Per-effect cost accounting: wall time and counted work (rays cast) per effect.

Tests compare the counted work (deterministic); the benchmark reports the seconds.
Timing is exclusive: time spent in a nested `track` is charged to the inner effect only.
"""
from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field


@dataclass
class CostReport:
    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    rays: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    _stack: list[list] = field(default_factory=list, repr=False)

    @contextmanager
    def track(self, effect: str):
        start = time.perf_counter()
        frame = [effect, 0.0]  # [name, time charged to children]
        self._stack.append(frame)
        try:
            yield self
        finally:
            self._stack.pop()
            elapsed = time.perf_counter() - start
            self.seconds[effect] += elapsed - frame[1]
            if self._stack:
                self._stack[-1][1] += elapsed

    def count(self, effect: str, rays: int) -> None:
        self.rays[effect] += int(rays)

    @property
    def total_rays(self) -> int:
        return sum(self.rays.values())

    def merge(self, other: "CostReport") -> None:
        for k, v in other.seconds.items():
            self.seconds[k] += v
        for k, v in other.rays.items():
            self.rays[k] += v

    def as_dict(self) -> dict:
        return {
            "seconds": {k: round(v, 6) for k, v in sorted(self.seconds.items())},
            "rays": dict(sorted(self.rays.items())),
        }
