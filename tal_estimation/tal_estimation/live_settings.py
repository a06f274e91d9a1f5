"""Changing one field of a frozen settings dataclass at run time (ROS-free): what a node's live parameter
does before it hands the new settings to its estimator's ``reconfigure``."""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

from tal_core.errors import InputError

Settings = TypeVar("Settings")


def with_field(settings: Settings, name: str, value: Any) -> Settings:
    """A copy of ``settings`` with field ``name`` set to ``value``; a dotted name reaches into nested settings
    (``attitude.k_p``). Raises ValueError with the settings' own reason when the result is invalid."""
    head, _, rest = name.partition(".")
    if rest:
        value = with_field(getattr(settings, head), rest, value)
    try:
        return dataclasses.replace(settings, **{head: value})
    except InputError as exc:
        raise ValueError(str(exc)) from exc
