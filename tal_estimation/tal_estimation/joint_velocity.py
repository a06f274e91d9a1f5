"""Joint velocities from joint positions, for robots whose joint states carry no velocities (ROS-free).

Causal: a backward finite difference between consecutive samples, then a first-order low-pass with cut-off
``cutoff_hz``, discretised exactly for each sample's own interval (alpha = 1 - exp(-2 pi f_c dt)), so stamps
with jitter need no resampling. The first sample, and the first after a gap longer than ``max_gap_s`` or a
stamp that does not advance, reads zero velocity and restarts the difference.
"""

from __future__ import annotations

import math

import numpy as np

from tal_core.errors import InputError


class JointVelocityFilter:
    """Finite difference + first-order low-pass per joint; see the module docstring."""

    def __init__(self, cutoff_hz: float, max_gap_s: float = math.inf) -> None:
        if not (math.isfinite(cutoff_hz) and cutoff_hz > 0.0) or not max_gap_s > 0.0:
            raise InputError(f"JointVelocityFilter needs cutoff_hz > 0 and max_gap_s > 0, got {cutoff_hz!r}, "
                             f"{max_gap_s!r}")
        self.cutoff_hz = float(cutoff_hz)
        self.max_gap_s = float(max_gap_s)
        self._t: float | None = None
        self._q: np.ndarray | None = None
        self._velocity: np.ndarray | None = None

    def reset(self) -> None:
        self._t = None
        self._q = None
        self._velocity = None

    def update(self, t_s: float, positions: np.ndarray) -> np.ndarray:
        """The filtered velocities [rad/s] at ``t_s`` [s] given the positions [rad] of that sample."""
        q = np.asarray(positions, dtype=float)
        if self._t is None or self._q is None or self._velocity is None or self._q.shape != q.shape \
                or not (0.0 < t_s - self._t <= self.max_gap_s):
            self._t, self._q, self._velocity = float(t_s), q.copy(), np.zeros_like(q)
            return self._velocity.copy()
        dt = float(t_s) - self._t
        raw = (q - self._q) / dt
        alpha = 1.0 - math.exp(-2.0 * math.pi * self.cutoff_hz * dt)
        self._velocity = self._velocity + alpha * (raw - self._velocity)
        self._t, self._q = float(t_s), q.copy()
        return self._velocity.copy()
