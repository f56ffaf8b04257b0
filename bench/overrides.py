"""`--set key=value` options of the bench scripts: dotted preset keys, JSON values; and the
capture stage run with a config's knobs (`--set tracking.direct.search_step_deg=4`)."""
from __future__ import annotations

import json
from contextlib import contextmanager
from typing import Iterator


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


@contextmanager
def knobs_of(config) -> Iterator[None]:
    """Run the block's jobs with `config.tracking` and `config.capture` (an EngineConfig's; None:
    the defaults): the capture stage reads its knobs from the active settings (core.tracking.config,
    core.capture.config), which run_job does not set from its config."""
    from core.capture.config import using_capture
    from core.tracking.config import using_tracking

    with using_tracking(None if config is None else config.tracking), \
            using_capture(None if config is None else config.capture):
        yield
