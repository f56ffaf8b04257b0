"""Field kinds by name: `@register_field("name")` on a LightField subclass with a `Config`
(its settings section in FieldConfig); FieldConfig, build_field (core.fields.kinds.base) and the
CLI's and the job schema's choices read this table, so a new kind is one module plus its
registration. It imports nothing of core.fields (config and base import it), so no import,
not even a type-checking one, closes a loop through it."""
from __future__ import annotations

from typing import Callable, TypeVar

from pydantic import BaseModel

FIELDS: dict[str, type] = {}  # kind -> its LightField subclass, in registration order
F = TypeVar("F", bound=type)


def register_field(kind: str) -> Callable[[F], F]:
    """Class decorator: the field kind `kind`, whose settings section is `cls.Config`."""

    def register(cls: F) -> F:
        config = getattr(cls, "Config", None)
        if not (isinstance(config, type) and issubclass(config, BaseModel)):
            raise TypeError(f"field {kind!r}: {cls.__name__}.Config must be a pydantic model (its settings)")
        if FIELDS.get(kind, cls) is not cls:
            raise ValueError(f"field kind {kind!r} is already registered by {FIELDS[kind].__name__}")
        cls.kind = kind
        FIELDS[kind] = cls
        return cls

    return register


def field_kinds() -> tuple[str, ...]:
    return tuple(FIELDS)


def field_class(kind: str) -> type:
    """The LightField subclass registered as `kind`."""
    if kind not in FIELDS:
        raise ValueError(f"unknown field kind {kind!r}; choose one of {', '.join(FIELDS)}")
    return FIELDS[kind]

