"""Long exports (EXR sequences, large exact maps, cube/glTF/USD probes) that stop when their
client leaves and never hold up the small queries on the same light field.

* **Their own copy of the field.** An export evaluates a private copy of the loaded field
  (`CachedField.export_artefact`, one export at a time per field), never the copy the
  batcher's small queries use, so a 64-row map asked during a 240-frame sequence waits for
  its own batch, not for the sequence (both share the CPU).
* **Cancelled mid-map.** The field evaluates a map in Python loops over direction blocks and
  probes; `Cancellation.cancel()` raises `ExportCancelled` in the thread running the export
  at its next Python instruction (CPython's PyThreadState_SetAsyncExc), so a 1024-row exact
  map stops within one block (~0.1 s) of its client leaving, not seconds later. The exception
  is only ever armed while the export's own code runs (`running()`), and a pending one is
  withdrawn when it leaves, so it can never land in the threadpool's code.
* **Client gone.** A single map watches `request.is_disconnected()` while it runs; a streamed
  sequence is cancelled by Starlette when the client disconnects, and its generator's
  `finally` cancels the frame in flight.
"""
from __future__ import annotations

import asyncio
import ctypes
import threading
from contextlib import contextmanager
from typing import Any, AsyncIterator, Callable, Iterator

from fastapi.concurrency import run_in_threadpool

DISCONNECT_POLL_S = 0.1


class ExportCancelled(Exception):
    """Raised inside an export's thread when its client has gone."""


def _set_async_exc(thread_id: int, exc: type[BaseException] | None) -> None:
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(thread_id), ctypes.py_object(exc) if exc else None)


class Cancellation:
    """Cancels the export code running inside `running()` blocks, whichever thread runs them."""

    def __init__(self):
        self._lock = threading.Lock()
        self._thread: int | None = None
        self.cancelled = False

    @contextmanager
    def running(self) -> Iterator[None]:
        with self._lock:
            if self.cancelled:
                raise ExportCancelled()
            self._thread = threading.get_ident()
        try:
            yield
        finally:
            with self._lock:
                self._thread = None
                _set_async_exc(threading.get_ident(), None)  # withdraw one armed but not yet raised

    def cancel(self) -> None:
        with self._lock:
            if self.cancelled:
                return
            self.cancelled = True
            if self._thread is not None:  # armed at most once, and only inside running()
                _set_async_exc(self._thread, ExportCancelled)


async def run_export(request, fn: Callable[..., Any], *args, on_cancel: Callable[[], None] | None = None) -> Any:
    """fn(*args) in the threadpool inside a Cancellation, cancelled when the client disconnects
    (then ExportCancelled is raised here; the answer no longer matters)."""
    cancellation = Cancellation()

    def call():
        with cancellation.running():
            return fn(*args)

    task = asyncio.ensure_future(run_in_threadpool(call))
    try:
        while True:
            done, _ = await asyncio.wait({task}, timeout=DISCONNECT_POLL_S)
            if done:
                return task.result()
            if await request.is_disconnected():
                cancellation.cancel()
                task.add_done_callback(_consume)
                if on_cancel is not None:
                    on_cancel()
                raise ExportCancelled()
    except asyncio.CancelledError:
        cancellation.cancel()
        task.add_done_callback(_consume)
        raise


def _consume(task: asyncio.Future) -> None:
    """The abandoned call's outcome (its ExportCancelled) is expected: not an unretrieved error."""
    if not task.cancelled():
        task.exception()


_DONE = object()


def _next(iterator):
    return next(iterator, _DONE)


async def stream_export(chunks: Iterator[bytes], cancellation: Cancellation,
                        on_cancel: Callable[[], None] | None = None) -> AsyncIterator[bytes]:
    """A sync chunk iterator (whose heavy work runs inside `cancellation.running()`) as an async
    stream, one chunk per threadpool call; when the stream is cancelled (Starlette does that when
    the client disconnects) the chunk in flight is cancelled too."""
    finished = False
    try:
        while True:
            # asyncio.wait, not `await task`: a cancelled stream must not wait for the chunk in
            # flight to finish (the thread call is not interruptible from here) but cancel it
            task = asyncio.ensure_future(run_in_threadpool(_next, chunks))
            try:
                await asyncio.wait({task})
            except asyncio.CancelledError:
                task.add_done_callback(_consume)
                raise
            chunk = task.result()
            if chunk is _DONE:
                finished = True
                return
            yield chunk
    finally:
        if not finished:
            cancellation.cancel()
            if on_cancel is not None:
                on_cancel()
