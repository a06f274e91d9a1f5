"""Plain state containers shared by the packages."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BaseState:
    """Floating-base state: position [m], orientation (x, y, z, w), linear [m/s] and angular [rad/s]
    velocity, all in the world frame."""

    position: np.ndarray
    quat_xyzw: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity: np.ndarray
