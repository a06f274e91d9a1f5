"""Drift and velocity error of an estimate against a reference, in constant memory.

Shared by the ``state_estimator`` node (against ground truth, for its summary) and the offline replay
(against ground truth and against the live estimate in a bag): a node can run for hours, so the
statistics are running sums, never a list of samples.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class DriftStatistics:
    """Running drift [m] and velocity error [m/s] per world axis.

    align_start: the first position error is taken as the offset between the two frames (the estimate
    starts where the reference is, up to its initialisation) and subtracted from every later one.
    """

    align_start: bool = True
    n: int = 0
    offset: np.ndarray | None = None
    first_t_s: float | None = None
    last_t_s: float | None = None
    sq_position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sq_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    last_position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    max_abs_position: float = 0.0
    max_abs_velocity: float = 0.0

    def add(self, t_s: float, position_error: np.ndarray, velocity_error: np.ndarray) -> None:
        """One comparison at time ``t_s`` [s]: estimate minus reference, position [m] and velocity [m/s]."""
        if self.align_start and self.offset is None:
            self.offset = np.array(position_error, dtype=float)
        dp = position_error - self.offset if self.align_start else np.asarray(position_error, dtype=float)
        self.n += 1
        self.first_t_s = t_s if self.first_t_s is None else self.first_t_s
        self.last_t_s = t_s
        self.sq_position += dp**2
        self.sq_velocity += velocity_error**2
        self.last_position = dp
        self.max_abs_position = max(self.max_abs_position, float(np.max(np.abs(dp))))
        self.max_abs_velocity = max(self.max_abs_velocity, float(np.max(np.abs(velocity_error))))

    def summary(self, decimals: int = 5) -> dict[str, object]:
        """Final and RMS drift, velocity RMSE, maxima, sample count and compared span; {} before any sample."""
        if self.n == 0:
            return {}
        return {"samples": self.n, "final_drift_m": np.round(self.last_position, decimals).tolist(),
                "rms_drift_m": np.round(np.sqrt(self.sq_position / self.n), decimals).tolist(),
                "velocity_rmse_m_s": np.round(np.sqrt(self.sq_velocity / self.n), decimals).tolist(),
                "max_abs_position_m": self.max_abs_position, "max_abs_velocity_m_s": self.max_abs_velocity,
                "compared_s": round(float(self.last_t_s - self.first_t_s), 3)}


class StampMatcher:
    """Pairs estimates with references of exactly the same stamp, whichever arrives first, in bounded memory
    (the ``keep`` newest unmatched of each side). An estimator on its own tick grid and ground truth on
    another (333 and 250 Hz: every 12 ms) are compared at their common stamps only, so the statistics do not
    depend on arrival order."""

    def __init__(self, keep: int = 64) -> None:
        if keep < 1:
            raise ValueError(f"StampMatcher: keep must be >= 1, got {keep}")
        self.keep = int(keep)
        self._estimates: dict[int, object] = {}
        self._references: dict[int, object] = {}

    def add_estimate(self, stamp_ns: int, estimate: object) -> tuple[object, object] | None:
        """(estimate, reference) when the reference of ``stamp_ns`` is already here, else None (held)."""
        return self._add(int(stamp_ns), estimate, self._estimates, self._references, estimate_first=True)

    def add_reference(self, stamp_ns: int, reference: object) -> tuple[object, object] | None:
        """(estimate, reference) when the estimate of ``stamp_ns`` is already here, else None (held)."""
        return self._add(int(stamp_ns), reference, self._references, self._estimates, estimate_first=False)

    def _add(self, stamp: int, item: object, mine: dict[int, object], theirs: dict[int, object],
             estimate_first: bool) -> tuple[object, object] | None:
        other = theirs.pop(stamp, None)
        if other is not None:
            return (item, other) if estimate_first else (other, item)
        mine[stamp] = item
        while len(mine) > self.keep:
            del mine[min(mine)]
        return None
