"""Leg naming and ordering conventions shared by every package.

Legs are always ordered LF, RF, LH, RH (left-front, right-front, left-hind, right-hind) and each leg has
the joints HAA, HFE, KFE in that order. Code names legs (``Leg.LF``) instead of indexing them bare.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from enum import IntEnum
from typing import Generic, TypeVar

T = TypeVar("T")


class Leg(IntEnum):
    """Leg identifiers; the integer value is the index in every per-leg fixed array."""

    LF = 0
    RF = 1
    LH = 2
    RH = 3


LEGS: tuple[Leg, ...] = (Leg.LF, Leg.RF, Leg.LH, Leg.RH)
LEG_NAMES: tuple[str, ...] = tuple(leg.name for leg in LEGS)
JOINT_KINDS: tuple[str, ...] = ("HAA", "HFE", "KFE")
# Each leg's y-mirror (left <-> right at the same end): a robot symmetric about its base's x-z plane does on a
# y-mirrored terrain with the mirrored leg what it does on the terrain with the leg.
MIRROR_LEG: dict[Leg, Leg] = {Leg.LF: Leg.RF, Leg.RF: Leg.LF, Leg.LH: Leg.RH, Leg.RH: Leg.LH}
MIRROR_LEG_INDEX: tuple[int, ...] = tuple(int(MIRROR_LEG[leg]) for leg in LEGS)  # by leg index (per-leg arrays)
RIGHT_LEGS: tuple[Leg, ...] = (Leg.RF, Leg.RH)
NUM_LEGS = len(LEGS)
JOINTS_PER_LEG = len(JOINT_KINDS)


@dataclass(frozen=True)
class PerLeg(Generic[T]):
    """An immutable value per leg, indexable by ``Leg`` and iterable in LF, RF, LH, RH order."""

    LF: T
    RF: T
    LH: T
    RH: T

    def __getitem__(self, leg: Leg | int) -> T:
        return getattr(self, Leg(leg).name)

    def __iter__(self) -> Iterator[T]:
        return iter((self.LF, self.RF, self.LH, self.RH))

    def __len__(self) -> int:
        return NUM_LEGS

    @classmethod
    def from_sequence(cls, values: list[T] | tuple[T, ...]) -> PerLeg[T]:
        """Build from a sequence in LF, RF, LH, RH order; raises ValueError on a wrong length."""
        if len(values) != NUM_LEGS:
            raise ValueError(f"expected {NUM_LEGS} per-leg values (LF, RF, LH, RH), got {len(values)}")
        return cls(*values)


def leg_from_name(name: str) -> Leg:
    """Return the Leg for 'LF', 'RF', 'LH' or 'RH' (case-insensitive); raises ValueError otherwise."""
    try:
        return Leg[name.upper()]
    except KeyError:
        raise ValueError(f"unknown leg name {name!r}; expected one of {', '.join(LEG_NAMES)}") from None
