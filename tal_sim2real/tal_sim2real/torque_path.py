"""The actuator torque path, re-simulated on measured data: commanded torque -> delivered torque.

The bridge's ActuatorModel (tal_sim_bridge.effects) runs step by step; here the same model runs
vectorised over a whole recording (one call per candidate parameter set), so that fitting actuator
delay, lag, torque gain and torque limit against the measured joint torques (joint_states.effort) costs
milliseconds. ``test_parts`` checks it against ActuatorModel sample by sample.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import lfilter

from tal_core.robot_description import RobotDescription

from .measured import MeasuredData, white_noise_std


def torque_limits(description: RobotDescription, q_rad: np.ndarray, every: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Nominal (N, 12) lower and upper torque limits [N m] at the measured joint positions [rad]
    (evaluated every ``every`` samples and held in between)."""
    low = np.empty_like(q_rad)
    high = np.empty_like(q_rad)
    for start in range(0, len(q_rad), every):
        lo, hi = description.torque_limits(q_rad[start])
        low[start : start + every] = lo
        high[start : start + every] = hi
    return low, high


def delivered_torque(
    command_nm: np.ndarray,
    dt_s: float,
    low_nm: np.ndarray,
    high_nm: np.ndarray,
    *,
    delay_s: float | np.ndarray = 0.0,
    lag_s: float = 0.0,
    gain: float | np.ndarray = 1.0,
    limit_scale: float = 1.0,
) -> np.ndarray:
    """(N, J) torque [N m] the actuators deliver for the (N, J) command in force at each physics step,
    starting from rest (zero history): delay (rounded to steps) -> first-order lag -> gain -> clip.
    ``delay_s`` and ``gain`` may be (J,) arrays: one value per joint (per-leg variants)."""
    steps = np.broadcast_to(np.round(np.asarray(delay_s, dtype=float) / dt_s).astype(int), command_nm.shape[1:])
    delayed = np.zeros_like(command_nm)
    for s in np.unique(steps):
        cols = steps == s
        if s < len(command_nm):
            delayed[s:, cols] = command_nm[: len(command_nm) - s, cols]
    if lag_s > 0.0:
        alpha = 1.0 - math.exp(-dt_s / lag_s)
        delayed = lfilter([alpha], [1.0, alpha - 1.0], delayed, axis=0)
    return np.clip(gain * delayed, limit_scale * low_nm, limit_scale * high_nm)


LEGS = ("lf", "rf", "lh", "rh")


def per_joint(values: dict[str, float], n_joints: int = 12) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(gain, delay [s], sensor gain) per joint from global and per-leg parameters (legs of three joints in
    the order LF, RF, LH, RH)."""
    gain = np.full(n_joints, values.get("torque_gain", 1.0))
    delay = np.full(n_joints, values.get("actuator_delay_s", 0.0))
    sensor = np.ones(n_joints)
    for i, leg in enumerate(LEGS):
        cols = slice(3 * i, 3 * i + 3)
        if f"torque_gain_{leg}" in values:
            gain[cols] = values[f"torque_gain_{leg}"]
        if f"actuator_delay_{leg}_s" in values:
            delay[cols] = values[f"actuator_delay_{leg}_s"]
        if f"torque_sensor_gain_{leg}" in values:
            sensor[cols] = values[f"torque_sensor_gain_{leg}"]
    return gain, delay, sensor


class TorquePathProblem:
    """Residuals of the measured joint torques against the re-simulated torque path. The commands in force
    and the torque limits are computed once; every residual runs the path from the first sample (the lag
    and delay start from rest there, as on the robot) and returns the requested window."""

    def __init__(self, data: MeasuredData, description: RobotDescription) -> None:
        if data.effort_nm is None:
            raise ValueError("no measured joint torques")
        self.data = data
        self.effort = data.effort_nm
        self.command = data.command_in_force()
        self.low, self.high = torque_limits(description, data.q_rad, every=5)

    def noise_std_nm(self, window: slice | np.ndarray) -> float:
        """White-noise level [N m] of the measured torques in the window."""
        return white_noise_std(self.effort[window])

    def residual(self, values: dict[str, float], window: slice | np.ndarray) -> np.ndarray:
        """Flattened (measured - predicted) joint torques [N m] over the window."""
        return self.residual_matrix(values, window).ravel()

    def residual_matrix(self, values: dict[str, float], window: slice | np.ndarray) -> np.ndarray:
        """(samples, joints) measured - predicted joint torques [N m] over the window. Besides the global
        parameters, ``values`` may hold per-leg variants (``torque_gain_rf``, ``actuator_delay_rf_s``: the
        leg's value replaces the global one; ``torque_sensor_gain_rf``: the leg's sensors read that times
        the delivered torque)."""
        gain, delay, sensor = per_joint(values, self.effort.shape[1])
        predicted = delivered_torque(
            self.command,
            self.data.dt_s,
            self.low,
            self.high,
            delay_s=delay,
            lag_s=values.get("actuator_lag_s", 0.0),
            gain=gain,
            limit_scale=values.get("torque_limit_scale", 1.0),
        )
        return self.effort[window] - sensor * predicted[window]

    def max_limit_fraction(self, window: slice | np.ndarray) -> float:
        """Largest commanded torque in the window as a fraction of the nominal limit: a torque limit above
        it leaves no trace in the data."""
        cmd = self.command[window]
        return float(np.max(np.maximum(cmd / self.high[window], cmd / self.low[window])))
