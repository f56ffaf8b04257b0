"""The base of every settings section of core.fields (a kind's `Config`, an encoding's
settings, FieldConfig itself)."""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class FieldSettings(BaseModel):
    """Base of every kind's settings section (strict: a misspelt key is an error)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
