"""A piecewise-constant velocity command profile in sim time (what ``cmd_vel_script`` plays), and when a
player of stamped commands publishes them."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from tal_core.errors import InputError


@dataclass(frozen=True)
class CommandSegment:
    start_s: float          # [s] sim time the segment starts
    vx_m_s: float           # [m/s] horizontal frame
    vy_m_s: float           # [m/s] horizontal frame
    yaw_rate_rad_s: float   # [rad/s]


def parse_profile(flat: Sequence[float]) -> tuple[CommandSegment, ...]:
    """Segments from a flat list [t0, vx, vy, wz, t1, vx, vy, wz, ...] with increasing start times."""
    values = [float(v) for v in flat]
    if len(values) == 0 or len(values) % 4 != 0:
        raise InputError(f"a command profile needs groups of 4 numbers (t, vx, vy, wz), got {len(values)}")
    if not all(math.isfinite(v) for v in values):
        raise InputError("a command profile has NaN or inf")
    segments = tuple(CommandSegment(*values[i:i + 4]) for i in range(0, len(values), 4))
    starts = [s.start_s for s in segments]
    if any(b <= a for a, b in zip(starts, starts[1:])) or starts[0] < 0.0:
        raise InputError(f"command profile start times must be >= 0 and increasing, got {starts}")
    return segments


def command_at(segments: Sequence[CommandSegment], t_s: float) -> CommandSegment:
    """The segment in force at sim time t_s [s] (zero command before the first one starts)."""
    current = CommandSegment(0.0, 0.0, 0.0, 0.0)
    for segment in segments:
        if segment.start_s <= t_s:
            current = segment
    return current


def stamps_due(segments: Sequence[CommandSegment], period_ns: int, after_ns: int, horizon_ns: int) -> list[int]:
    """Stamps [ns] in (after_ns, horizon_ns] at which a stamped player publishes its command: the points of
    the sim-time grid k * period_ns and every segment start, sorted. The grid is absolute, so what is
    published does not depend on when the player joined the clock."""
    if period_ns <= 0:
        raise InputError(f"the publishing period must be > 0 ns, got {period_ns}")
    if horizon_ns <= after_ns:
        return []
    first = after_ns // period_ns + 1
    stamps = {k * period_ns for k in range(first, horizon_ns // period_ns + 1)}
    stamps.update(round(s.start_s * 1e9) for s in segments if after_ns < round(s.start_s * 1e9) <= horizon_ns)
    return sorted(stamps)
