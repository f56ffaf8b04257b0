"""Weight-loading priors are built once per worker process and reused by every job it runs (a
diffusion prior's weights take seconds to load and gigabytes to hold); the engine builds the
others per job, since they hold per-capture state."""
from __future__ import annotations

import json
import threading

_lock = threading.Lock()
_cache: dict[tuple[str, str, str], object] = {}


def cached_prior(name: str, settings: dict, device=None):
    """`core.priors.registry.build_prior`, keeping priors whose settings name weights."""
    from core.priors.registry import build_prior  # noqa: PLC0415 — core.priors.registry pulls in pydantic, torch: imported when used

    if not settings.get("weights"):
        return build_prior(name, settings, device)
    key = (name, json.dumps(settings, sort_keys=True, default=str), str(device))
    with _lock:
        if key not in _cache:
            _cache[key] = build_prior(name, settings, device)
        return _cache[key]
