"""Command latency without ROS: wall time from a joint state leaving the bridge to the command computed on it.

The bridge notes the wall time (``time.monotonic()``) at which it published the ``joint_states`` of each stamp
(a bounded table of the most recent ones) and, when a ``joint_command`` stamped with one of them arrives, the
difference is that command's latency: the controller's whole path (transport, estimator and wbc ticks,
transport back). Each stamp is timed once (a second command for the same stamp is not). The initial state
(stamp 0) is not timed: the bridge re-sends it until a controller has joined, so its latency is DDS
discovery. Median and p99 are over the last ``window`` timed commands, the count and the maximum over all.
"""

from __future__ import annotations

import numpy as np

DEFAULT_PENDING = 256
"""Stamps remembered: 256 ms of 1 kHz joint states (a command later than that is not timed)."""
DEFAULT_WINDOW = 1 << 17
"""Latencies kept for median / p99: ~8.7 min of 250 Hz commands (1 MB)."""


class CommandLatency:
    """Joint-state publication times by stamp [ns] and the latencies [s] of the commands stamped with them."""

    def __init__(self, pending: int = DEFAULT_PENDING, window: int = DEFAULT_WINDOW) -> None:
        if pending < 1 or window < 1:
            raise ValueError(f"CommandLatency needs pending >= 1 and window >= 1, got {pending}, {window}")
        self._pending = int(pending)
        self._published: dict[int, float] = {}   # stamp [ns] -> wall time [s], oldest first
        self._samples = np.empty(int(window))
        self.count = 0          # commands timed
        self.untimed = 0        # commands whose stamp was not (or no longer) in the table
        self.max_s = 0.0

    def published(self, stamp_ns: int, wall_s: float) -> None:
        """The joint state stamped ``stamp_ns`` left the bridge at ``wall_s`` (monotonic) [s]."""
        if stamp_ns <= 0:
            return
        table = self._published
        table[stamp_ns] = wall_s
        if len(table) > self._pending:
            del table[next(iter(table))]

    def command(self, stamp_ns: int, wall_s: float) -> float | None:
        """A command stamped ``stamp_ns`` arrived at ``wall_s`` [s]; returns its latency [s] (None: untimed)."""
        sent = self._published.pop(stamp_ns, None)
        if sent is None:
            self.untimed += 1
            return None
        latency = wall_s - sent
        self._samples[self.count % self._samples.size] = latency
        self.count += 1
        if latency > self.max_s:
            self.max_s = latency
        return latency

    def summary(self) -> dict[str, object]:
        """``command_latency_ms`` of the bridge's end-of-run summary."""
        n = min(self.count, self._samples.size)
        if n == 0:
            return {"count": 0, "untimed": self.untimed, "median_ms": None, "p99_ms": None, "max_ms": None}
        median, p99 = np.percentile(self._samples[:n], [50.0, 99.0]) * 1e3
        return {"count": self.count, "untimed": self.untimed, "median_ms": round(float(median), 3),
                "p99_ms": round(float(p99), 3), "max_ms": round(self.max_s * 1e3, 3)}
