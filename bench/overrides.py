"""`--set key=value` options of the bench scripts: dotted preset keys, JSON values; and the
tracker run with a config's `tracking` section (`--set tracking.direct.search_step_deg=4`)."""
from __future__ import annotations

import json
from contextlib import AbstractContextManager


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


def tracking_of(config) -> AbstractContextManager:
    """Run the block's jobs with `config.tracking` (an EngineConfig's; None: the defaults): the
    tracker reads its knobs from core.tracking.config's active settings."""
    from core.tracking.config import using_tracking

    return using_tracking(None if config is None else config.tracking)
