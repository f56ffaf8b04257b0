"""Batched field evaluation: concurrent queries on one light field become one field call.

A request does not evaluate the field itself. It queues an `EnvmapRequest` on its field's
`FieldBatcher` and awaits the answer. One drain task per field takes everything queued,
groups it by (quality, height) and evaluates each group as ONE call in the threadpool (torch
spreads that call over every core), then encodes the answers in the same thread. So 100
clients asking for 64x128 maps cost one 100-map evaluation instead of 100 one-map
evaluations serialised behind a lock; while it runs, the next batch gathers.

Nothing heavy runs on the event loop, and a burst on one field occupies one threadpool
thread, so health checks and other fields keep answering. The queue is bounded in env map
pixels per field (`max_pending_pixels`): beyond it a request is refused at once with 503
`overloaded` and Retry-After rather than waiting behind minutes of work.
"""
from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from typing import Any, Callable

from fastapi.concurrency import run_in_threadpool

from service.errors import ServiceUnavailable

log = logging.getLogger("lightfield.service")

MAX_CALL_PIXELS = 1 << 21  # env map pixels per field call (a 1024x2048 map): bounds activations
BAKED_COST = 0.05  # a baked (interpolated) pixel costs a few percent of an evaluated one
RETRY_AFTER_BUSY_S = 2


@dataclass(frozen=True)
class EnvmapRequest:
    x: tuple[float, float, float]
    t: float
    height: int
    quality: str  # "exact" | "fast" | "baked" (service.queries)
    finish: Callable[[Any], Any] | None = None  # hdr [H, 2H, 3] numpy -> what the caller wants (encoded bytes, ...)

    @property
    def pixels(self) -> int:
        return 2 * self.height * self.height

    @property
    def cost(self) -> float:
        """Field evaluations it needs (quality=fast evaluates 1/16 of the pixels)."""
        if self.quality == "baked":
            return self.pixels * BAKED_COST
        if self.quality == "fast":
            return self.pixels / 16
        return self.pixels


@dataclass
class EnvmapAnswer:
    value: Any  # finish(hdr), or hdr when no finish was given
    flags: Any  # service.queries.EvalFlags
    quality: str


class FieldBatcher:
    """The queue and drain task of one light field. `evaluate(requests) -> answers` is blocking
    (it runs in the threadpool) and answers a list of requests with one field call per
    (quality, height) group."""

    def __init__(self, evaluate: Callable[[list[EnvmapRequest]], list[EnvmapAnswer]], max_pending_cost: float,
                 on_batch: Callable[[list[EnvmapRequest]], None] | None = None):
        self._evaluate = evaluate
        self.max_pending_cost = max_pending_cost
        self._on_batch = on_batch
        self._queue: list[tuple[EnvmapRequest, asyncio.Future]] = []
        self._pending_cost = 0.0
        self._drain_task: asyncio.Task | None = None
        self.batches = 0  # evaluations run (for tests and metrics)

    async def submit(self, request: EnvmapRequest) -> EnvmapAnswer:
        if self._pending_cost + request.cost > self.max_pending_cost and self._queue:
            raise ServiceUnavailable("this light field has too much queued work; retry shortly", code="overloaded",
                                     retry_after_s=RETRY_AFTER_BUSY_S)
        future = asyncio.get_running_loop().create_future()
        self._queue.append((request, future))
        self._pending_cost += request.cost
        if self._drain_task is None:
            self._drain_task = asyncio.create_task(self._drain())
        return await future

    def _take_batch(self) -> list[tuple[EnvmapRequest, asyncio.Future]]:
        """Everything queued (first come first), up to MAX_CALL_PIXELS per (quality, height) group."""
        batch, rest, group_pixels = [], [], {}
        for item in self._queue:
            request, future = item
            if future.done():  # the client went away while it waited
                self._pending_cost -= request.cost
                continue
            key = (request.quality, request.height)
            used = group_pixels.get(key, 0)
            if used and used + request.pixels > MAX_CALL_PIXELS:
                rest.append(item)
                continue
            group_pixels[key] = used + request.pixels
            batch.append(item)
        self._queue = rest
        return batch

    @staticmethod
    async def _resolve(batch, answers) -> None:
        await _resolve_in_steps(batch, answers)

    async def _drain(self) -> None:
        try:
            while self._queue:
                batch = self._take_batch()
                if not batch:
                    continue
                requests = [r for r, _ in batch]
                try:
                    answers = await run_in_threadpool(self._evaluate, requests)
                    self.batches += 1
                    if self._on_batch is not None:
                        self._on_batch(requests)
                except BaseException as exc:  # every waiter gets the error (validated inputs: a server fault)
                    for _, future in batch:
                        if not future.done():
                            future.set_exception(exc)
                    if not isinstance(exc, Exception):
                        raise
                else:
                    await self._resolve(batch, answers)
                finally:
                    self._pending_cost -= sum(r.cost for r in requests)
        finally:
            self._drain_task = None
            self._pending_cost = max(self._pending_cost, 0.0)


RESOLVE_STEP = 8


async def _resolve_in_steps(batch, answers) -> None:
    """Wake the waiting requests a few at a time, yielding to the event loop in between: 100
    handlers resumed in one loop turn would hold everything else (a /healthz probe, new
    connections) for that whole turn."""
    for k, ((_, future), answer) in enumerate(zip(batch, answers)):
        if not future.done():
            future.set_result(answer)
        if k % RESOLVE_STEP == RESOLVE_STEP - 1:
            await asyncio.sleep(0)


def group_requests(requests: list[EnvmapRequest]) -> dict[tuple[str, int], list[int]]:
    """(quality, height) -> indices of the requests in that group, in order."""
    groups: dict[tuple[str, int], list[int]] = {}
    for i, r in enumerate(requests):
        groups.setdefault((r.quality, r.height), []).append(i)
    return groups
