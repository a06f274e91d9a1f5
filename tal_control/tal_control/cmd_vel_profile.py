"""A piecewise-constant velocity command profile in sim time (what ``cmd_vel_script`` plays)."""

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
