"""What the chosen model leaves unexplained, and where.

After the identification a subsystem's held-out residual is compared with a noise floor re-estimated with
the updated model (a floor estimated with a model far from the truth is too high: noise perturbations of
the wrong model grow faster). When the residual stays clearly above it, the verdict is "partly
explained" (the named effect explains most of the gap, something else remains) or "not explained by the
library" (the closest candidate explains little, or none fits), never a plain "named".

The remainder is localised by grouping the residual's squared elements, each against the floor's share
of the same elements: per channel, per joint, per leg and per gait phase of the joint's leg (stance,
swing, touchdown). ``ratio`` is cost / floor (1 = at the noise floor); ``share`` is the group's part of
the total excess over the floor (where to look).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .phases import LEG_NAMES, PHASES

REMAINDER_FACTOR = 3.0
"""A held-out residual above this many noise floors (re-estimated with the updated model) is a remainder
the model does not explain. In-library effects fitted right leave 0.5-2 floors (measured, see README)."""
MOSTLY_EXPLAINED = 0.5
"""Fraction of the held-out excess over the floor the named effects must remove for "partly explained";
below it the closest candidate explains little: "not explained by the library"."""


@dataclass
class Group:
    """A part of the residual: its cost, the floor's part of the same elements, ratio and share of the
    total excess over the floor."""

    cost: float
    floor: float
    share: float = 0.0

    @property
    def ratio(self) -> float:
        return self.cost / self.floor if self.floor > 0 else math.inf


@dataclass
class Remainder:
    """The held-out remainder of one subsystem: cost before/after, the re-estimated floor, the verdict and
    the localisation tables (name -> Group)."""

    subsystem: str
    before: float
    after: float
    floor: float
    verdict: str = ""
    flagged: bool = False
    explained_fraction: float = math.nan
    by_channel: dict[str, Group] = field(default_factory=dict)
    by_joint: dict[str, Group] = field(default_factory=dict)
    by_leg: dict[str, Group] = field(default_factory=dict)
    by_phase: dict[str, Group] = field(default_factory=dict)

    @property
    def ratio(self) -> float:
        return self.after / self.floor if self.floor > 0 else math.inf

    def top(self, table: str) -> str:
        """The group with the largest excess in ``table`` ('channel', 'joint', 'leg', 'phase')."""
        groups = getattr(self, f"by_{table}")
        if not groups:
            return ""
        return max(groups, key=lambda k: (groups[k].cost - groups[k].floor, groups[k].ratio))

    def where(self) -> str:
        parts = [f"{t} {self.top(t)}" for t in ("leg", "joint", "phase", "channel") if getattr(self, f"by_{t}")]
        return ", ".join(parts)

    def as_dict(self) -> dict:
        return {
            "ratio": self.ratio,
            "flagged": self.flagged,
            "verdict": self.verdict,
            "explained_fraction": self.explained_fraction,
            "top_leg": self.top("leg"),
            "top_joint": self.top("joint"),
            "top_phase": self.top("phase"),
            "top_channel": self.top("channel"),
        }


def judge(remainder: Remainder, named: tuple[str, ...], at_floor: bool) -> Remainder:
    """Set the verdict: named (explained to the floor), partly explained, not explained by the library,
    or no missing effect."""
    ratio = remainder.ratio
    excess_before = remainder.before - remainder.floor
    if excess_before > 0:
        remainder.explained_fraction = float(np.clip((remainder.before - remainder.after) / excess_before, 0.0, 1.0))
    remainder.flagged = ratio > REMAINDER_FACTOR
    names = ", ".join(named)
    if not remainder.flagged:
        if named:
            remainder.verdict = f"named {names} (held-out residual {ratio:.2g} x the noise floor)"
        elif at_floor:
            remainder.verdict = "no missing effect (at the noise floor)"
        else:
            remainder.verdict = (
                f"no library effect named; held-out residual {ratio:.2g} x the noise floor, below the remainder "
                f"threshold {REMAINDER_FACTOR:g}"
            )
        return remainder
    where = remainder.where()
    if named and remainder.explained_fraction >= MOSTLY_EXPLAINED:
        remainder.verdict = (
            f"partly explained: named {names} (removes {100 * remainder.explained_fraction:.0f}% of the held-out "
            f"excess); remainder {ratio:.3g} x the noise floor, largest at {where}"
        )
    elif named:
        remainder.verdict = (
            f"not explained by the library: the closest candidate {names} removes only "
            f"{100 * remainder.explained_fraction:.0f}% of the held-out excess; remainder {ratio:.3g} x the noise "
            f"floor, largest at {where}"
        )
    else:
        remainder.verdict = (
            f"not explained by the library: no candidate fits; residual {ratio:.3g} x the noise floor, largest at "
            f"{where}"
        )
    return remainder


def localise(
    remainder: Remainder,
    cost: np.ndarray,
    floor: np.ndarray,
    channels: dict[str, np.ndarray],
    joint_names: list[str] | tuple[str, ...],
    joint_of: np.ndarray,
    phase: np.ndarray | None,
) -> Remainder:
    """Fill the localisation tables from per-element squared residuals ``cost`` and the floor's
    per-element part ``floor`` (same shape, last axis the components). ``channels``: channel -> boolean
    mask over the components; ``joint_of``: component -> joint index or -1 (base channels);
    ``phase``: phase index (PHASES) per element of the joint components, shape of ``cost`` (or None)."""

    def group(mask: np.ndarray) -> Group:
        return Group(float(cost[mask].sum()), float(floor[mask].sum()))

    comp_shape = cost.shape
    comp = np.broadcast_to(np.arange(comp_shape[-1]), comp_shape)
    joint = joint_of[comp]
    remainder.by_channel = {name: group(mask[comp]) for name, mask in channels.items()}
    remainder.by_joint = {name: group(joint == j) for j, name in enumerate(joint_names)}
    remainder.by_leg = {leg: group((joint >= 0) & (joint // 3 == i)) for i, leg in enumerate(LEG_NAMES)}
    if phase is not None:
        remainder.by_phase = {p: group((joint >= 0) & (phase == i)) for i, p in enumerate(PHASES)}
    for table in (remainder.by_channel, remainder.by_joint, remainder.by_leg, remainder.by_phase):
        total_excess = sum(max(g.cost - g.floor, 0.0) for g in table.values())
        for g in table.values():
            g.share = max(g.cost - g.floor, 0.0) / total_excess if total_excess > 0 else 0.0
    return remainder
