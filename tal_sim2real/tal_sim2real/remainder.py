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

The dynamics' held-out residual comes from open-loop segments re-simulated from measured states, and a
segment through a contact transition is chaotic: a touchdown resolved one step earlier turns a joint's
velocity by rad/s. The noise floor (a mean over a few noise draws) prices that on average, but the excess of
a correct model is heavy-tailed over segments: on a benchmark dataset with its effect named right, 2 of 20
held-out segments (a touchdown of one leg each) carried 78 % of the excess, the total was 4.0 floors and the
median segment 0.83. So the verdict of a segmented subsystem is taken without its worst
``ISOLATED_SEGMENTS`` share of segments (``set_aside``); they are listed as isolated events (when, how
large, which joint), and a remainder is systematic when what is left is still above ``REMAINDER_FACTOR``
floors (the benchmark's out-of-library effects keep 14-20 floors without them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .phases import LEG_NAMES, PHASES

REMAINDER_FACTOR = 3.0
"""A held-out residual above this many noise floors (re-estimated with the updated model) is a remainder
the model does not explain. In-library effects fitted right leave 0.5-2 floors (measured, see README)."""
ISOLATED_SEGMENTS = 0.1
"""Share of a segmented subsystem's held-out segments (those with the largest excess over their floor; none
below ten segments) set aside as isolated events before the remainder verdict."""
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
class IsolatedSegment:
    """A held-out segment set aside before the verdict: its start [s], cost / floor, share of the total excess
    over the floor and the joint with the largest excess in it."""

    start_s: float
    ratio: float
    share: float
    joint: str


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
    isolated: list[IsolatedSegment] = field(default_factory=list)
    kept_after: float = math.nan  # held-out cost / floor of the segments left after ``set_aside``
    kept_floor: float = math.nan

    @property
    def ratio(self) -> float:
        return self.after / self.floor if self.floor > 0 else math.inf

    @property
    def systematic_ratio(self) -> float:
        """cost / floor the verdict is taken on: without the isolated segments when some were set aside."""
        if not self.isolated:
            return self.ratio
        return self.kept_after / self.kept_floor if self.kept_floor > 0 else math.inf

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
            "systematic_ratio": self.systematic_ratio,
            "isolated_segments": len(self.isolated),
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
    or no missing effect. Judged on ``systematic_ratio`` (see ``set_aside``)."""
    ratio = remainder.systematic_ratio
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


def set_aside(
    remainder: Remainder,
    cost: np.ndarray,
    floor: np.ndarray,
    starts_s: np.ndarray,
    joint_names: list[str] | tuple[str, ...],
    joint_of: np.ndarray,
    fraction: float = ISOLATED_SEGMENTS,
) -> np.ndarray:
    """Set aside the ``int(fraction * segments)`` held-out segments with the largest excess over their floor
    as isolated events (``cost``/``floor``: per element, first axis the segments, last the components;
    ``starts_s``: each segment's start). Fills ``remainder.isolated``, ``kept_after`` and ``kept_floor``;
    returns the mask of the segments kept (the localisation's)."""
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"isolated segment fraction must be in [0, 1), got {fraction}")
    n = cost.shape[0]
    if len(starts_s) != n:
        raise ValueError(f"{len(starts_s)} segment starts for {n} segments")
    axes = tuple(range(1, cost.ndim))
    seg_cost, seg_floor = cost.sum(axis=axes), floor.sum(axis=axes)
    excess = seg_cost - seg_floor
    keep = np.ones(n, dtype=bool)
    aside = [i for i in np.argsort(-excess, kind="stable")[: int(fraction * n)] if excess[i] > 0]
    total_excess = float(np.clip(excess, 0.0, None).sum())
    comp_excess = (cost - floor).reshape(n, -1, cost.shape[-1]).sum(axis=1)
    on_joint = joint_of >= 0
    remainder.isolated = []
    for i in sorted(aside, key=lambda i: starts_s[i]):
        keep[i] = False
        joint_excess = np.bincount(joint_of[on_joint], comp_excess[i][on_joint], minlength=len(joint_names))
        remainder.isolated.append(
            IsolatedSegment(
                float(starts_s[i]),
                float(seg_cost[i] / seg_floor[i]) if seg_floor[i] > 0 else math.inf,
                float(excess[i] / total_excess) if total_excess > 0 else 0.0,
                joint_names[int(np.argmax(joint_excess))] if joint_names else "",
            )
        )
    remainder.kept_after = float(seg_cost[keep].sum())
    remainder.kept_floor = float(seg_floor[keep].sum())
    return keep


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
