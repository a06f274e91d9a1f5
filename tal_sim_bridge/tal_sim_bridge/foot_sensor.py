"""Foot contact sensors, ROS-free: what a quadruped's foot load cells or contact switches report.

A real foot sensor is not the simulator's contact flag: it reads the load with noise, its reading reaches the
bus a sample or more late, and a contact flag comes from a threshold with hysteresis on that reading (so a
light touch is missed and a loaded foot's flag holds through the noise). ``FootForceSensor`` models the four
sensors from the simulator's ground reaction forces: reading = |F| + white noise, delayed by
``delay_samples`` sensor samples; the flag turns on at ``threshold_n`` and off below
``(1 - hysteresis_fraction) * threshold_n``. Seeded, so a lockstep run repeats.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .errors import BridgeConfigError


@dataclass(frozen=True)
class FootSensorSettings:
    delay_samples: int = 1            # [-] sensor samples between the load and its reading
    noise_std_n: float = 2.0          # [N] white noise on the reading (a calibrated load cell)
    threshold_n: float = 15.0         # [N] the contact flag turns on at this reading
    hysteresis_fraction: float = 0.3  # [-] ... and off below (1 - this) * threshold_n
    seed: int = 0

    def __post_init__(self) -> None:
        delay = self.delay_samples
        if isinstance(delay, bool) or int(delay) != delay or delay < 0:
            raise BridgeConfigError(f"foot sensor delay_samples must be an integer >= 0, got {self.delay_samples!r}")
        for name in ("noise_std_n", "threshold_n"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise BridgeConfigError(f"foot sensor {name} must be finite and >= 0, got {value!r}")
        if not 0.0 <= self.hysteresis_fraction < 1.0:
            raise BridgeConfigError(
                f"foot sensor hysteresis_fraction must be in [0, 1), got {self.hysteresis_fraction!r}")


class FootForceSensor:
    """Four feet's force readings [N] and contact flags; ``measure`` once per sensor sample."""

    def __init__(self, settings: FootSensorSettings, feet: int = 4) -> None:
        self.settings = settings
        self._rng = np.random.default_rng(settings.seed)
        self._line: deque[np.ndarray] = deque(maxlen=settings.delay_samples + 1)
        self._flags = np.zeros(feet, dtype=bool)
        self.feet = feet

    def measure(self, forces_n: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The ground reaction force vectors [N] acting on the feet now -> (readings [N], contact flags) as the
        sensors report them now (the reading of ``delay_samples`` samples ago; before that, the first)."""
        load = np.linalg.norm(np.asarray(forces_n, dtype=float).reshape(self.feet, 3), axis=1)
        s = self.settings
        reading = load + (self._rng.normal(0.0, s.noise_std_n, self.feet) if s.noise_std_n > 0.0 else 0.0)
        self._line.append(reading)
        out = self._line[0]
        release = (1.0 - s.hysteresis_fraction) * s.threshold_n
        self._flags = np.where(self._flags, out >= release, out >= s.threshold_n)
        return out.copy(), self._flags.copy()
