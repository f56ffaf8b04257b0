"""argparse choices that come from the project's registries (presets, priors, field kinds,
temporal modes, the diffusion prior's inference profiles, import layouts and ControlNet
conditionings), read when first needed (a value to check, a subcommand's --help), so the
names are never written out again and `lightfield --help` imports no torch. Give such an
argument a `metavar` and "%(choices)s" in its help: argparse formats both lazily."""
from __future__ import annotations

from typing import Callable, Iterable, Iterator


class RegistryChoices:
    def __init__(self, names: Callable[[], Iterable[str]]):
        self._names = names
        self._loaded: tuple[str, ...] | None = None

    def _all(self) -> tuple[str, ...]:
        if self._loaded is None:
            self._loaded = tuple(self._names())
        return self._loaded

    def __contains__(self, value: object) -> bool:
        return value in self._all()

    def __iter__(self) -> Iterator[str]:
        return iter(self._all())


def _presets() -> Iterable[str]:
    from core.engine.presets import preset_names

    return preset_names()


def _priors() -> Iterable[str]:
    from core.priors.registry import job_prior_names

    return job_prior_names()


def _fields() -> Iterable[str]:
    from core.fields import field_kinds

    return field_kinds()


def _prior_profiles() -> Iterable[str]:
    from core.priors.diffusion.profiles import PROFILES

    return PROFILES


def _import_layouts() -> Iterable[str]:
    from core.priors.diffusion.importing import LAYOUTS

    return ("auto", *LAYOUTS)


def _control_conditionings() -> Iterable[str]:
    from typing import get_args

    from core.priors.diffusion.card import Conditioning

    return get_args(Conditioning)


def _temporal_modes() -> Iterable[str]:
    from core.capture.temporal import TEMPORAL_MODES

    return TEMPORAL_MODES


PRESETS = RegistryChoices(_presets)
PRIORS = RegistryChoices(_priors)
FIELDS = RegistryChoices(_fields)
PRIOR_PROFILES = RegistryChoices(_prior_profiles)
IMPORT_LAYOUTS = RegistryChoices(_import_layouts)
CONTROL_CONDITIONINGS = RegistryChoices(_control_conditionings)
TEMPORAL_MODES = RegistryChoices(_temporal_modes)
