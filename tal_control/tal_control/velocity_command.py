"""The velocity command in force at each control tick, from stamped and unstamped sources (no rclpy).

Stamped commands (the sim time from which they apply) are queued and come into force at the first tick at
or after their stamp, whatever their arrival order: a lockstep run with a scripted command then does not
depend on when the script's process got the CPU. One that arrives after its tick has run applies at once
and is counted as late when it changes the command.

Unstamped commands (a teleop's Twist) apply from the next tick after their arrival, unless stamped
commands are in use (the newest stamp is at most ``stamped_priority_s`` older than the last tick): a
player that publishes both (cmd_vel_script echoes its command as a Twist, for recorders) is then followed
by its stamps only.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence

import numpy as np

from tal_core.errors import InputError
from tal_core.ticks import TICK_TOLERANCE_NS


class VelocityCommandInput:
    """vx, vy [m/s] (horizontal frame), yaw rate [rad/s], clamped to the given limits."""

    def __init__(self, max_linear_m_s: float, max_yaw_rate_rad_s: float, stamped_priority_s: float = 1.0) -> None:
        self.max_linear_m_s = float(max_linear_m_s)
        self.max_yaw_rate_rad_s = float(max_yaw_rate_rad_s)
        self.stamped_priority_ns = round(stamped_priority_s * 1e9)
        self.command = np.zeros(3)
        self.late = 0                 # stamped commands that arrived after their tick and changed the command
        self.unstamped_ignored = 0    # unstamped commands not applied because stamped ones were in use
        self.reset()

    def reset(self) -> None:
        """Forget the queue and the ticks (restarted clock); the command in force stays."""
        self._queue: list[tuple[int, np.ndarray]] = []   # stamped commands not yet in force, by stamp
        self._in_force_ns: int | None = None             # stamp of the stamped command in force
        self._newest_ns: int | None = None               # newest stamp received
        self._last_tick_ns: int | None = None

    def set_limits(self, max_linear_m_s: float, max_yaw_rate_rad_s: float) -> None:
        """New clamps [m/s], [rad/s] (a live parameter change): the command in force and the queued ones are
        clamped to them at once; what a lower limit cut off is not restored by raising it again."""
        for name, value in (("max_linear_m_s", max_linear_m_s), ("max_yaw_rate_rad_s", max_yaw_rate_rad_s)):
            if not (np.isfinite(value) and value >= 0.0):
                raise InputError(f"velocity command limit {name} must be finite and >= 0, got {value!r}")
        self.max_linear_m_s = float(max_linear_m_s)
        self.max_yaw_rate_rad_s = float(max_yaw_rate_rad_s)
        self.command = self._clamped(self.command)
        self._queue = [(stamp, self._clamped(command)) for stamp, command in self._queue]

    def _clamped(self, values: Sequence[float]) -> np.ndarray:
        v = np.asarray(values, dtype=float).reshape(-1)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise InputError(f"velocity command must be 3 finite values (vx, vy, yaw rate), got {list(values)!r}")
        lin, yaw = self.max_linear_m_s, self.max_yaw_rate_rad_s
        return np.array([np.clip(v[0], -lin, lin), np.clip(v[1], -lin, lin), np.clip(v[2], -yaw, yaw)])

    def stamped_in_use(self) -> bool:
        if self._newest_ns is None:
            return False
        return self._last_tick_ns is None or self._newest_ns >= self._last_tick_ns - self.stamped_priority_ns

    def unstamped(self, values: Sequence[float]) -> bool:
        """A command without stamp; returns whether it was applied. InputError for NaN or wrong size."""
        command = self._clamped(values)
        if self.stamped_in_use():
            self.unstamped_ignored += 1
            return False
        self.command = command
        return True

    def stamped(self, stamp_ns: int, values: Sequence[float]) -> bool:
        """A command applying from ``stamp_ns`` [ns]; returns True when it came late (after its tick) and
        changed the command. InputError for NaN or wrong size."""
        command = self._clamped(values)
        self._newest_ns = stamp_ns if self._newest_ns is None else max(self._newest_ns, stamp_ns)
        if self._in_force_ns is not None and stamp_ns <= self._in_force_ns:
            return False  # not newer than the command in force (sent again)
        if self._last_tick_ns is not None and stamp_ns <= self._last_tick_ns:
            late = not np.array_equal(command, self.command)
            self.late += int(late)
            self._queue = [(s, c) for s, c in self._queue if s > stamp_ns]
            self.command, self._in_force_ns = command, stamp_ns
            return late
        stamps = [s for s, _ in self._queue]
        index = bisect.bisect_left(stamps, stamp_ns)
        if index < len(stamps) and stamps[index] == stamp_ns:
            self._queue[index] = (stamp_ns, command)
        else:
            self._queue.insert(index, (stamp_ns, command))
        return False

    def at_tick(self, stamp_ns: int) -> np.ndarray:
        """The command for the tick at ``stamp_ns`` [ns]: the stamped commands due come into force."""
        while self._queue and self._queue[0][0] <= stamp_ns + TICK_TOLERANCE_NS:
            self._in_force_ns, self.command = self._queue.pop(0)
        self._last_tick_ns = stamp_ns
        return self.command
