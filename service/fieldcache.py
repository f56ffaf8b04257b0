"""Loaded light fields, cached per API process (bounded LRU).

Loading an artefact costs a file read, a checksum and a module build; keeping the last few
in memory makes repeated queries on the same job pay only the evaluation. Each cached field
carries its batcher (service.evaluator: concurrent queries become one field call) and a
lock: torch evaluation already uses every core, so running two calls on one field at once
only adds memory, and it keeps modules that cache buffers safe.
"""
from __future__ import annotations

import copy
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable


@dataclass
class CachedField:
    artefact: Any  # core.fields.stored.artefact.LightFieldArtefact
    lock: threading.Lock = field(default_factory=threading.Lock)
    baked: Any = None  # core.fields.stored.bake.BakedField, loaded (or baked) on the first fast query
    batcher: Any = None  # service.evaluator.FieldBatcher, created on the first query
    # long exports (service.exports) evaluate a copy of their own, one at a time, so they never
    # hold `lock` (the batcher's small queries) for seconds
    export_lock: threading.Lock = field(default_factory=threading.Lock)
    _export_copy: Any = None

    def export_artefact(self):
        """The exports' copy of the artefact (made on first use). Call with export_lock held."""
        if self._export_copy is None:
            self._export_copy = copy.deepcopy(self.artefact)
        return self._export_copy


class FieldCache:
    def __init__(self, capacity: int, loader: Callable[[Path], Any] | None = None):
        self.capacity = capacity
        self._loader = loader or _load_artefact
        self._items: "OrderedDict[str, CachedField]" = OrderedDict()
        self._lock = threading.Lock()
        self._loading: dict[str, threading.Lock] = {}

    def get(self, key: str, directory: Path) -> CachedField:
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
            load_lock = self._loading.setdefault(key, threading.Lock())
        with load_lock:  # one load per key even when many requests miss at once
            with self._lock:
                if key in self._items:
                    return self._items[key]
            item = CachedField(self._loader(directory))
            with self._lock:
                self._items[key] = item
                self._loading.pop(key, None)
                while len(self._items) > self.capacity:
                    self._items.popitem(last=False)
            return item

    def peek(self, key: str) -> CachedField | None:
        """The loaded field or None, never loading (safe on the event loop)."""
        with self._lock:
            item = self._items.get(key)
            if item is not None:
                self._items.move_to_end(key)
            return item

    def evict(self, key: str) -> None:
        with self._lock:
            self._items.pop(key, None)

    def __len__(self) -> int:
        return len(self._items)


def _load_artefact(directory: Path):
    from core.fields.stored.artefact import LightFieldArtefact  # noqa: PLC0415 — core.fields.stored.artefact pulls in safetensors: imported when used

    return LightFieldArtefact.load(directory)
