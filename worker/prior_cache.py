"""Priors are built once per worker process and reused by every job it runs (a diffusion
prior's weights take seconds to load and gigabytes to hold)."""
from __future__ import annotations

import threading

_lock = threading.Lock()
_cache: dict[tuple[str, str | None, str | None], object] = {}


def get_prior(name: str, weights: str | None = None, profile: str | None = None):
    """One prior per (name, weights, inference profile); the profile changes what it computes."""
    key = (name, weights, profile)
    with _lock:
        if key not in _cache:
            from core.priors.registry import build_prior

            _cache[key] = build_prior(name, weights=weights, **({"profile": profile} if profile else {}))
        return _cache[key]
