"""Run the state estimator on recorded arrays (a bag read into memory, or a simulation log) through the
node's own streaming tick (``tal_estimation.streaming.StreamingEstimator``), so offline and live give the
same estimates.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from tal_core.legs import NUM_LEGS
from tal_core.robot_model import RobotModel
from tal_estimation.leg_odometry import LegImpedance
from tal_estimation.state_estimator import StateEstimate, StateEstimatorSettings
from tal_estimation.streaming import StreamingEstimator

ImpedanceSource = Callable[[float], "LegImpedance | None"]


@dataclass(frozen=True)
class SensorArrays:
    """Proprioceptive samples, one row per sensor sample. t [s]; specific_force [m/s^2] and angular_rate
    [rad/s] IMU frame; joint_position [rad], joint_velocity [rad/s], joint_torque [N m] canonical order;
    magnetic_field (optional) [T] IMU frame. A robot without them: joint_velocity None (derived by the
    estimator), joint_torque None (with a sensor contact_source); foot_contact (T, 4) the feet's sensor
    values (force, raw or [N], or 0/1 flags) for such a source."""

    t: np.ndarray
    specific_force: np.ndarray
    angular_rate: np.ndarray
    joint_position: np.ndarray
    joint_velocity: np.ndarray | None
    joint_torque: np.ndarray | None
    magnetic_field: np.ndarray | None = None
    foot_contact: np.ndarray | None = None


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


def run_estimator(model: RobotModel, sensors: SensorArrays, settings: StateEstimatorSettings | None = None,
                  *, initial_position: np.ndarray | None = None, initial_world_R_base: np.ndarray | None = None,
                  impedance: ImpedanceSource | None = None,
                  magnetic_field_world: np.ndarray | None = None,
                  on_tick: Callable[[StateEstimate], None] | None = None) -> EstimateArrays:
    """Estimate along ``sensors`` (paired IMU and joint samples) as the node does. The first sample
    initialises the filter (at ``initial_position`` or, by default, standing on flat ground at z = 0 above
    the origin); ``impedance(t)`` gives the terrain impedance the terrain-aware leg odometry sees at each
    tick. Rejected samples are left out as the node leaves them out (``StreamingEstimator``)."""
    stream = StreamingEstimator(model, settings, initial_position=initial_position,
                                initial_world_R_base=initial_world_R_base, magnetic_field_world=magnetic_field_world)
    stamps = np.round(np.asarray(sensors.t, float) * 1e9).astype(np.int64)
    rows: list[StateEstimate] = []
    for i, stamp in enumerate(stamps):
        stream.magnetic_field = None if sensors.magnetic_field is None else sensors.magnetic_field[i]
        stream.impedance = None if impedance is None else impedance(stamp * 1e-9)
        qd = None if sensors.joint_velocity is None else sensors.joint_velocity[i]
        tau = None if sensors.joint_torque is None else sensors.joint_torque[i]
        contact = None if sensors.foot_contact is None else sensors.foot_contact[i]
        for out in stream.add_sample(int(stamp), sensors.specific_force[i], sensors.angular_rate[i],
                                     sensors.joint_position[i], qd, tau, foot_contact=contact):
            if out.estimate is not None:
                rows.append(out.estimate)
                if on_tick is not None:
                    on_tick(out.estimate)
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
