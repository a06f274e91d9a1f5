"""IMU biases against the base motion: gyroscope vs the measured angular velocity, accelerometer vs
the specific force implied by the measured base acceleration (finite differences of the world-frame
velocity) and gravity, both in the base frame. The re-simulation of the bridge's IMU model is exact here:
the model is f = base_R_world (a - g) + b_a + noise, w = base_R_world omega + b_g + noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .measured import GRAVITY_M_S2, MeasuredData

BLOCK_S = 0.1  # [s] block length for the standard error of the mean (correlated residuals)


@dataclass(frozen=True)
class BiasEstimate:
    """Mean residual (the bias estimate) per axis, its standard error and the residual RMS."""

    mean: np.ndarray
    standard_error: np.ndarray
    rms: float


def imu_residuals(data: MeasuredData, window: slice) -> tuple[np.ndarray, np.ndarray]:
    """(gyro residual [rad/s], accel residual [m/s^2]), each (n, 3), base frame, over the window."""
    assert data.base is not None and data.gyro_rad_s is not None and data.accel_m_s2 is not None
    base_R_world = np.transpose(data.base.world_R_base, (0, 2, 1))
    omega_base = np.einsum("nij,nj->ni", base_R_world, data.base.ang_vel_world_rad_s)
    acc_world = np.gradient(data.base.lin_vel_world_m_s, data.t_s, axis=0)
    gravity = np.array([0.0, 0.0, -GRAVITY_M_S2])
    f_base = np.einsum("nij,nj->ni", base_R_world, acc_world - gravity)
    return (data.gyro_rad_s - omega_base)[window], (data.accel_m_s2 - f_base)[window]


def estimate_bias(residual: np.ndarray, dt_s: float) -> BiasEstimate:
    """Mean of a residual with the standard error from block means (blocks of BLOCK_S)."""
    block = max(1, int(round(BLOCK_S / dt_s)))
    n_blocks = len(residual) // block
    if n_blocks < 3:
        return BiasEstimate(residual.mean(0), np.full(3, np.inf), float(np.sqrt(np.mean(residual**2))))
    means = residual[: n_blocks * block].reshape(n_blocks, block, -1).mean(1)
    se = means.std(0, ddof=1) / math.sqrt(n_blocks)
    return BiasEstimate(residual.mean(0), se, float(np.sqrt(np.mean(residual**2))))
