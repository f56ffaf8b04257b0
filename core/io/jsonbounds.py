"""JSON from untrusted files, parsed within a budget: size, nesting depth and container count
are checked on the raw bytes before `json.loads` builds anything.

`json.loads` recurses once per nesting level (100 000 nested lists: RecursionError) and builds
a Python object per list or dict (8 M empty lists in 16 MB: about 500 MB), so neither can be
left to it. Strings are blanked with one regular expression (brackets inside strings are text,
not structure), then the brackets are counted and their running depth taken with numpy: a
few tens of milliseconds for megabytes, with memory a small multiple of the input.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass

import numpy as np

from core.io.limits import MediaError

_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"')
_OPEN = np.zeros(256, np.int8)
_OPEN[[ord("["), ord("{")]] = 1
_CLOSE = np.zeros(256, np.int8)
_CLOSE[[ord("]"), ord("}")]] = 1


@dataclass(frozen=True)
class JsonBudget:
    max_bytes: int = 8 * 1024 * 1024
    max_depth: int = 32
    max_containers: int = 200_000


def structure(raw: bytes) -> tuple[int, int]:
    """(deepest nesting, number of arrays and objects) of JSON text, strings ignored."""
    blanked = np.frombuffer(_STRING.sub(b'""', raw), np.uint8)
    if blanked.size == 0:
        return 0, 0
    opens = _OPEN[blanked]
    steps = opens - _CLOSE[blanked]  # int8 per byte: +1 opens, -1 closes
    return int(np.cumsum(steps, dtype=np.int32).max()), int(np.count_nonzero(opens))


def load_json(raw: bytes, what: str, budget: JsonBudget = JsonBudget(), error=None):
    """The parsed document, or `error(code, message)` (default: MediaError) when `raw` passes its
    budget ('too_large', checked before anything is parsed) or is not UTF-8 JSON ('truncated')."""
    error = error or MediaError
    if len(raw) > budget.max_bytes:
        raise error("too_large", f"{what} is {len(raw)} bytes, more than the limit of {budget.max_bytes}")
    depth, containers = structure(raw)
    if depth > budget.max_depth:
        raise error("too_large", f"{what} nests arrays/objects {depth} deep, more than the limit of {budget.max_depth}")
    if containers > budget.max_containers:
        raise error("too_large", f"{what} holds {containers} arrays/objects, more than the limit of "
                                 f"{budget.max_containers}")
    try:
        return json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise error("truncated", f"{what} is not valid UTF-8 JSON ({exc})") from None
