"""The sim-time tick grid every periodic node and offline replay share (no rclpy here)."""

from __future__ import annotations

NS_PER_S = 1_000_000_000
TICK_TOLERANCE_NS = 100_000  # [ns] stamps are exact multiples of the physics step; absorb rounding
CLOCK_RESET_NS = 500_000_000  # [ns] a stamp this far behind the last one is a restarted clock, not reordering


def reaches_tick(stamp_ns: int, next_tick_ns: int) -> bool:
    """True when a sample stamped ``stamp_ns`` is at (or past) the control tick ``next_tick_ns``."""
    return stamp_ns >= next_tick_ns - TICK_TOLERANCE_NS


def tick_after(stamp_ns: int, period_ns: int) -> int:
    """The next control tick [ns] after the one at ``stamp_ns``, on the sim-time grid k * period_ns."""
    return ((stamp_ns + TICK_TOLERANCE_NS) // period_ns + 1) * period_ns

