"""Priors by name: `@register_prior("name")` on a Prior subclass with its `Config`; the engine
builds the prior a job names with `build_prior(name, settings)`, and the job schema and the
CLI offer `job_prior_names()`. A new prior is one module plus its registration.

Registration happens when the defining module is imported. Priors whose module pulls in heavy
optional dependencies are listed in LAZY_PRIORS and imported on first use; they are the ones
a user asks for by name, so they are job choices before their module is loaded.
"""
from __future__ import annotations

import importlib
from pathlib import Path
from typing import Callable, Mapping, TypeVar

from pydantic import BaseModel, ValidationError

from core.priors.base import Prior, PriorError

PRIORS: dict[str, type[Prior]] = {}  # name -> class, in registration order
LAZY_PRIORS: dict[str, str] = {"diffusion": "core.priors.diffusion.prior"}  # name -> defining module
P = TypeVar("P", bound=type[Prior])


def register_prior(name: str, *, for_jobs: bool = False) -> Callable[[P], P]:
    """Class decorator: the prior `name` with settings `cls.Config`. `for_jobs`: users may pick
    it for a job (JobParams.prior, `lightfield estimate --prior`); test fixtures and oracles
    that need Python objects (a radiance function, a simulated scene) are not."""

    def register(cls: P) -> P:
        if not issubclass(cls, Prior):
            raise TypeError(f"prior {name!r}: {cls.__name__} must subclass core.priors.base.Prior")
        if PRIORS.get(name, cls) is not cls:
            raise ValueError(f"prior {name!r} is already registered by {PRIORS[name].__name__}")
        cls.name, cls.for_jobs = name, for_jobs
        PRIORS[name] = cls
        return cls

    return register


def prior_class(name: str) -> type[Prior]:
    if name not in PRIORS and name in LAZY_PRIORS:
        try:
            importlib.import_module(LAZY_PRIORS[name])
        except ImportError as exc:
            raise PriorError(
                f"the {name} prior is unavailable ({LAZY_PRIORS[name]} could not be imported: {exc})"
            ) from exc
    if name not in PRIORS:
        raise PriorError(f"unknown prior {name!r}; choose one of {', '.join(prior_names())}")
    return PRIORS[name]


def prior_names() -> tuple[str, ...]:
    return tuple(PRIORS) + tuple(n for n in LAZY_PRIORS if n not in PRIORS)


def job_prior_names() -> tuple[str, ...]:
    """Priors a user may pick for a job: those registered `for_jobs`, and the lazy ones."""
    return tuple(n for n, cls in PRIORS.items() if cls.for_jobs) + tuple(n for n in LAZY_PRIORS if n not in PRIORS)


def prior_settings(name: str, settings: BaseModel | Mapping | None = None) -> BaseModel:
    """`settings` validated as prior `name`'s Config (PriorError naming the bad key)."""
    config_cls = prior_class(name).Config
    if isinstance(settings, config_cls):
        return settings
    try:
        return config_cls.model_validate(dict(settings or {}))
    except ValidationError as exc:
        detail = "; ".join(f"{'.'.join(map(str, e['loc'])) or name}: {e['msg']}" for e in exc.errors())
        raise PriorError(f"prior {name!r}: {detail}") from None


WEIGHTS_WHERE = "a local model directory, --prior-weights DIR"


def require_weights(name: str, settings: BaseModel | Mapping | None, where: str = WEIGHTS_WHERE) -> None:
    """The rule of priors that load weights (their Config has `weights`): the settings name an
    existing directory. PriorError saying what is wrong (`where` tells the user where weights
    go); priors without weights pass. The engine (build_prior) and the service's submission
    check both apply it."""
    if "weights" not in prior_class(name).Config.model_fields:
        return
    weights = settings.get("weights") if isinstance(settings, Mapping) else getattr(settings, "weights", None)
    if not weights:
        raise PriorError(f"the {name!r} prior needs model weights ({where}); none was given")
    if not Path(weights).is_dir():
        raise PriorError(f"{str(weights)!r} is not a directory")


def build_prior(name: str, settings: BaseModel | Mapping | None = None, device=None) -> Prior:
    """The prior `name` built from its settings (a dict or its Config); `device`: see Prior.from_config."""
    config = prior_settings(name, settings)
    require_weights(name, config)
    return prior_class(name).from_config(config, device)
