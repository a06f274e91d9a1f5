"""The sim-time tick grid every periodic node and offline replay share (no rclpy here)."""

from __future__ import annotations

NS_PER_S = 1_000_000_000
TICK_TOLERANCE_NS = 100_000  # [ns] stamps are exact multiples of the physics step; absorb rounding
CLOCK_RESET_NS = 500_000_000  # [ns] a stamp this far behind the last one is a restarted clock, not reordering


def reaches_tick(stamp_ns: int, next_tick_ns: int, tolerance_ns: int = TICK_TOLERANCE_NS) -> bool:
    """True when a sample stamped ``stamp_ns`` is at (or past) the control tick ``next_tick_ns``; a sample
    up to ``tolerance_ns`` early counts (rounding; the jitter of a real robot's stamps)."""
    return stamp_ns >= next_tick_ns - tolerance_ns


def tick_after(stamp_ns: int, period_ns: int, tolerance_ns: int = TICK_TOLERANCE_NS) -> int:
    """The next control tick [ns] after the one at ``stamp_ns``, on the sim-time grid k * period_ns (a stamp
    up to ``tolerance_ns`` before a grid point belongs to it)."""
    return ((stamp_ns + tolerance_ns) // period_ns + 1) * period_ns



class StampedInbox:
    """Inputs stamped with the tick they were computed for (a heightmap, a foothold), held until the consumer's
    first tick at least ``lag_ns`` after their stamp and then handed over in stamp order. A consumer that
    used an input stamped with its own tick would depend on whether it arrived before or after the tick's
    other inputs (other topics, no order between them); one period later it has arrived in lockstep.
    At most ``keep`` inputs are held (the oldest are dropped, counted); inputs from before a restarted clock
    (stamped more than ``CLOCK_RESET_NS`` after the tick asking) are forgotten."""

    def __init__(self, lag_ns: int, keep: int = 64) -> None:
        if lag_ns < 0 or keep < 1:
            raise ValueError(f"StampedInbox needs lag_ns >= 0 and keep >= 1, got {lag_ns} and {keep}")
        self.lag_ns = int(lag_ns)
        self.keep = int(keep)
        self.dropped = 0
        self._items: list[tuple[int, int, object]] = []  # (stamp, arrival, item)
        self._arrivals = 0

    def __len__(self) -> int:
        return len(self._items)

    def add(self, stamp_ns: int, item: object) -> None:
        self._arrivals += 1
        self._items.append((int(stamp_ns), self._arrivals, item))
        if len(self._items) > self.keep:
            self._items.sort(key=lambda entry: entry[:2])
            del self._items[0]
            self.dropped += 1

    def due(self, tick_ns: int) -> list[tuple[int, object]]:
        """(stamp, item) of the held inputs stamped at least ``lag_ns`` before ``tick_ns``, oldest first."""
        cutoff = tick_ns - self.lag_ns + TICK_TOLERANCE_NS
        self._items = [entry for entry in self._items if entry[0] <= tick_ns + CLOCK_RESET_NS]
        due = sorted((entry for entry in self._items if entry[0] <= cutoff), key=lambda entry: entry[:2])
        if due:
            self._items = [entry for entry in self._items if entry[0] > cutoff]
        return [(stamp, item) for stamp, _, item in due]
