"""`--set key=value` options of the bench scripts: dotted preset keys, JSON values."""
from __future__ import annotations

import json


def parse_set(items: list[str]) -> dict:
    """["distill.iterations=400", "distill.supervision=balls"] -> {"distill.iterations": 400, ...}
    (a value that is not JSON stays a string)."""
    overrides = {}
    for item in items:
        key, value = item.split("=", 1)
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
    return overrides
