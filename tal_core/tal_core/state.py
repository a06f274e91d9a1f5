"""Plain state containers shared by the packages."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rotations import quat_xyzw_from_rotation, rotation_from_quat_xyzw, so3_exp


@dataclass(frozen=True)
class BaseState:
    """Floating-base state: position [m], orientation (x, y, z, w), linear [m/s] and angular [rad/s]
    velocity, all in the world frame."""

    position: np.ndarray
    quat_xyzw: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity: np.ndarray

    def predicted(self, dt_s: float) -> BaseState:
        """The state ``dt_s`` [s] later at constant linear and angular velocity (world frame): position moved
        by v dt, orientation turned by w dt; velocities unchanged."""
        rotation = so3_exp(np.asarray(self.angular_velocity, dtype=float) * dt_s) @ rotation_from_quat_xyzw(
            np.asarray(self.quat_xyzw, dtype=float))
        return BaseState(np.asarray(self.position, dtype=float) + np.asarray(self.linear_velocity, dtype=float) * dt_s,
                         quat_xyzw_from_rotation(rotation), self.linear_velocity, self.angular_velocity)
