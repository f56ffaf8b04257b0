"""Priors are built once per worker process and reused by every job it runs (a diffusion
prior's weights take seconds to load and gigabytes to hold)."""
from __future__ import annotations

import threading

_lock = threading.Lock()
_cache: dict[tuple[str, str | None], object] = {}


def get_prior(name: str, weights: str | None = None):
    key = (name, weights)
    with _lock:
        if key not in _cache:
            from core.priors.registry import build_prior

            _cache[key] = build_prior(name, weights=weights)
        return _cache[key]
