"""Tracking statistics of a locomotion run (for the wbc node's end-of-run summary)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .locomotion import BaseState, TickOutput


@dataclass
class TrackingStats:
    """Mean absolute tracking errors after ``settle_s`` [s] of sim time.

    Height: base z reference vs measured [m]. Velocity: rate-limited commanded horizontal velocity vs
    measured base velocity, world frame [m/s]. Yaw rate [rad/s].
    """

    settle_s: float = 2.0
    ticks: int = 0
    fallbacks: int = 0
    safe_mode_ticks: int = 0
    _height: list[float] = field(default_factory=list)
    _velocity: list[float] = field(default_factory=list)
    _yaw_rate: list[float] = field(default_factory=list)
    _slack_max: float = 0.0
    _start_xy: np.ndarray | None = None
    _last_xy: np.ndarray | None = None

    def add(self, t_s: float, base: BaseState, out: TickOutput) -> None:
        self.ticks += 1
        self.fallbacks += int(out.solution.fallback)
        xy = base.position[:2].copy()
        if self._start_xy is None:
            self._start_xy = xy
        self._last_xy = xy
        if t_s < self.settle_s:
            return
        trunk = out.targets.trunk
        self._height.append(abs(float(trunk.base_position[2] - base.position[2])))
        self._velocity.append(float(np.linalg.norm(trunk.command_velocity_world[:2] - base.linear_velocity[:2])))
        self._yaw_rate.append(abs(float(trunk.command_yaw_rate - base.angular_velocity[2])))
        self._slack_max = max(self._slack_max, out.solution.slack_norm)

    def summary(self) -> dict[str, float | int | None]:
        def mean(values: list[float]) -> float | None:
            return round(float(np.mean(values)), 5) if values else None

        distance = (float(np.linalg.norm(self._last_xy - self._start_xy))
                    if self._start_xy is not None and self._last_xy is not None else 0.0)
        return {
            "ticks": self.ticks, "qp_fallbacks": self.fallbacks, "safe_mode_ticks": self.safe_mode_ticks,
            "height_error_mean_abs_m": mean(self._height), "velocity_error_mean_abs_m_s": mean(self._velocity),
            "yaw_rate_error_mean_abs_rad_s": mean(self._yaw_rate),
            "max_slack_norm": round(self._slack_max, 4) if math.isfinite(self._slack_max) else None,
            "distance_m": round(distance, 4),
        }
