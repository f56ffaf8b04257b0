"""Settings a stage reads when it runs, made active for one job without passing them down every
call (the tracker's knobs sit five calls deep): a context variable, so a value set for one job
does not leak into another thread's job. Imports nothing of core."""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Generic, TypeVar

T = TypeVar("T")


class ActiveSettings(Generic[T]):
    def __init__(self, name: str, default: T):
        self._var: ContextVar[T] = ContextVar(name, default=default)

    def get(self) -> T:
        """The settings active now (the default outside any `using`)."""
        return self._var.get()

    @contextmanager
    def using(self, config: T | None) -> Iterator[T]:
        """`config` active inside the block (None: the settings already active)."""
        if config is None:
            yield self._var.get()
            return
        token = self._var.set(config)
        try:
            yield config
        finally:
            self._var.reset(token)
