"""Where upload checks run: a small thread pool of their own, with a time budget per check.

The check (service.validation.check_capture) reads headers, one video frame and one depth
map, with every size a file declares checked before anything is allocated (core.io), so one
check costs at most ~100 MB and typically milliseconds. It runs outside the event loop and
outside the threadpool that answers queries, `workers` at a time, so an upload that is slow
to check delays neither the queries nor other tenants' uploads beyond its own slot; a check
that overruns its budget is answered 413 at once (its thread finishes the bounded work on
its own and is reused).
"""
from __future__ import annotations

import asyncio
import functools
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

from service.errors import PayloadTooLarge


class UploadChecks:
    def __init__(self, workers: int, budget_s: float):
        self.workers, self.budget_s = workers, budget_s
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="upload-check")

    async def run(self, check: Callable[..., Any], *args) -> Any:
        """check(*args) in the pool; its 4xx ApiErrors propagate; past the budget: 413 too_large."""
        future = asyncio.get_running_loop().run_in_executor(self._pool, functools.partial(check, *args))
        try:
            return await asyncio.wait_for(asyncio.shield(future), self.budget_s)
        except asyncio.TimeoutError:
            raise PayloadTooLarge(f"the upload could not be checked within the budget of {self.budget_s:g} s per "
                                  "upload (LIGHTFIELD_UPLOAD_CHECK_S): it is too large or too complex",
                                  code="too_large") from None

    def shutdown(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
