"""Run the state estimator on recorded arrays (a bag read into memory, or a simulation log), with the same
tick grid and IMU pre-integration as the ``state_estimator`` node, so offline and live give the same
estimates.

Samples are at the sensor rate (1 kHz). A tick falls on the sim-time grid k * period_s; its IMU input is
the mean of the IMU samples after the previous tick up to and including the tick's sample.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from tal_core.legs import NUM_LEGS
from tal_core.robot_model import RobotModel
from tal_core.ticks import reaches_tick, tick_after

from .leg_odometry import LegImpedance
from .state_estimator import StateEstimate, StateEstimator, StateEstimatorSettings

ImpedanceSource = Callable[[float], "LegImpedance | None"]


@dataclass(frozen=True)
class SensorArrays:
    """Proprioceptive samples, one row per sensor sample. t [s]; specific_force [m/s^2] and angular_rate
    [rad/s] IMU frame; joint_position [rad], joint_velocity [rad/s], joint_torque [N m] canonical order;
    magnetic_field (optional) [T] IMU frame."""

    t: np.ndarray
    specific_force: np.ndarray
    angular_rate: np.ndarray
    joint_position: np.ndarray
    joint_velocity: np.ndarray
    joint_torque: np.ndarray
    magnetic_field: np.ndarray | None = None


@dataclass(frozen=True)
class EstimateArrays:
    """Estimates at the ticks. Shapes (T,), (T, 3), (T, 4) quaternion xyzw, (T, 3) world velocity,
    (T, 4) per leg, (T, 4, 3) per leg forces [N] world, (T, 3) raw leg-odometry velocity [m/s] world."""

    t: np.ndarray
    position: np.ndarray
    quat_xyzw: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity_base: np.ndarray
    gyro_bias: np.ndarray
    position_std: np.ndarray
    contact: np.ndarray
    contact_probability: np.ndarray
    force: np.ndarray
    leg_odometry_velocity: np.ndarray
    support: np.ndarray


class StreamingEstimator:
    """The node's tick logic for a stream of samples (one at a time, constant memory): the first sample
    initialises, then a tick falls on the grid k * period_s with the mean of the IMU samples since the
    previous tick."""

    def __init__(self, model: RobotModel, settings: StateEstimatorSettings | None = None, *,
                 initial_position: np.ndarray | None = None, initial_world_R_base: np.ndarray | None = None,
                 magnetic_field_world: np.ndarray | None = None) -> None:
        self.settings = settings or StateEstimatorSettings()
        self.estimator = StateEstimator(model, self.settings, magnetic_field_world)
        self.period_ns = round(self.settings.period_s * 1e9)
        self.initial_position = initial_position
        self.initial_world_R_base = initial_world_R_base
        self._f_sum, self._w_sum, self._count = np.zeros(3), np.zeros(3), 0
        self._next_tick = 0

    def add(self, stamp_ns: int, specific_force: np.ndarray, angular_rate: np.ndarray,
            joint_position: np.ndarray, joint_velocity: np.ndarray, joint_torque: np.ndarray,
            impedance: LegImpedance | None = None, magnetic_field: np.ndarray | None = None) -> StateEstimate | None:
        """One sensor sample at ``stamp_ns``; returns the estimate when the sample completes a tick."""
        t = stamp_ns * 1e-9
        if not self.estimator.initialised:
            if self.initial_position is None:
                self.estimator.initialise_standing(t, joint_position, world_R_base=self.initial_world_R_base)
            else:
                self.estimator.initialise(t, self.initial_position, self.initial_world_R_base)
            self._next_tick = tick_after(int(stamp_ns), self.period_ns)
            return None
        self._f_sum += specific_force
        self._w_sum += angular_rate
        self._count += 1
        if not reaches_tick(int(stamp_ns), self._next_tick):
            return None
        self._next_tick = tick_after(int(stamp_ns), self.period_ns)
        f, w = self._f_sum / self._count, self._w_sum / self._count
        self._f_sum, self._w_sum, self._count = np.zeros(3), np.zeros(3), 0
        return self.estimator.update(t, f, w, joint_position, joint_velocity, joint_torque, impedance=impedance,
                                     magnetic_field=magnetic_field)


def run_estimator(model: RobotModel, sensors: SensorArrays, settings: StateEstimatorSettings | None = None,
                  *, initial_position: np.ndarray | None = None, initial_world_R_base: np.ndarray | None = None,
                  impedance: ImpedanceSource | None = None,
                  magnetic_field_world: np.ndarray | None = None,
                  on_tick: Callable[[StateEstimate], None] | None = None) -> EstimateArrays:
    """Estimate along ``sensors``. The first sample initialises the filter (at ``initial_position`` or,
    by default, standing on flat ground at z = 0 above the origin); ``impedance(t)`` gives the terrain
    impedance the terrain-aware leg odometry sees at each tick."""
    stream = StreamingEstimator(model, settings, initial_position=initial_position,
                                initial_world_R_base=initial_world_R_base, magnetic_field_world=magnetic_field_world)
    stamps = np.round(np.asarray(sensors.t, float) * 1e9).astype(np.int64)
    rows: list[StateEstimate] = []
    for i, stamp in enumerate(stamps):
        mag = None if sensors.magnetic_field is None else sensors.magnetic_field[i]
        estimate = stream.add(int(stamp), sensors.specific_force[i], sensors.angular_rate[i],
                              sensors.joint_position[i], sensors.joint_velocity[i], sensors.joint_torque[i],
                              impedance=None if impedance is None else impedance(stamp * 1e-9), magnetic_field=mag)
        if estimate is not None:
            rows.append(estimate)
            if on_tick is not None:
                on_tick(estimate)
    return _stack(rows)


def _stack(rows: list[StateEstimate]) -> EstimateArrays:
    def column(get, shape):
        return np.array([get(r) for r in rows]) if rows else np.zeros((0, *shape))

    return EstimateArrays(
        t=column(lambda r: r.t_s, ()),
        position=column(lambda r: r.position, (3,)),
        quat_xyzw=column(lambda r: r.quat_xyzw, (4,)),
        linear_velocity=column(lambda r: r.linear_velocity, (3,)),
        angular_velocity_base=column(lambda r: r.angular_velocity_base, (3,)),
        gyro_bias=column(lambda r: r.gyro_bias, (3,)),
        position_std=column(lambda r: np.sqrt(np.diag(r.position_covariance)), (3,)),
        contact=column(lambda r: r.legs.in_contact, (NUM_LEGS,)),
        contact_probability=column(lambda r: r.legs.probability, (NUM_LEGS,)),
        force=column(lambda r: r.legs.force, (NUM_LEGS, 3)),
        leg_odometry_velocity=column(lambda r: r.legs.base_velocity, (3,)),
        support=column(lambda r: r.legs.weight_sum, ()),
    )
