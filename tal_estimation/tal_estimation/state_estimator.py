"""The proprioceptive state estimator of the thesis (state-estimation chapter): attitude observer (NLO +
XKF), leg odometry and a linear time-varying Kalman filter on base position and velocity (filterpy).

One ``update`` is one estimator tick (333 Hz by default). Its IMU input is the mean of the IMU samples
since the previous tick (specific force [m/s^2] and angular rate [rad/s], IMU frame; the 1 kHz samples
are pre-integrated, which for the linear parts is the same as integrating them one by one); its joint
input is the joint state of the tick. The KF (thesis eq. kf):

    x = (p, v) world frame,   x+ = F x + B u,  u = world_R_base f + g   (g = (0, 0, -9.81))
    z = v_leg_odometry,       H = [0 I],       R = sigma_lo^2 / (supporting legs) I

Position is not observable (only velocity is measured), so it drifts; that drift on soft ground is what
the thesis studies. Nothing here imports rclpy: the node and the offline replay use the same class.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from filterpy.kalman import KalmanFilter

from tal_core.errors import InputError
from tal_core.legs import NUM_LEGS
from tal_core.robot_model import RobotModel
from tal_core.rotations import cross3, quat_xyzw_from_rotation, rotation_from_quat_xyzw
from tal_core.state import BaseState

from .attitude import AttitudeEstimator, AttitudeSettings
from .leg_odometry import LegImpedance, LegOdometry, LegOdometryOutput, LegOdometrySettings, weighted_base_velocity

GRAVITY_WORLD = np.array([0.0, 0.0, -9.81])
KNOWN_ATTITUDE_STD_RAD = 0.01  # [rad] uncertainty of an initial attitude that is given (e.g. ground truth)


class EstimatorInputError(InputError):
    """A sample the estimator cannot use; ``reason`` is a short key for diagnostics counters."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class StateEstimatorSettings:
    """Noise figures (SI) and limits of the position/velocity filter, plus the parts' settings.

    accel_noise_m_s2: std of the acceleration input per tick (IMU noise and unmodelled motion).
    leg_velocity_noise_m_s: std of one leg's velocity reading. motion_compensation_tau_s: time constant of
    the low-pass filter of the motion-compensated gravity direction given to the attitude observer.
    min_support [-]: below this weight sum of supporting legs there is no velocity update (flight).
    max_gap_periods: a larger gap between ticks re-initialises the velocity filter. accel_range_m_s2,
    gyro_range_rad_s: saturation limits of the IMU (a sample at or beyond them is rejected; defaults: a
    +-40 g, +-2000 deg/s MEMS IMU, since touchdown impacts on rigid ground reach 20-30 g at the trunk in
    simulation). joint_velocity_cutoff_hz: cut-off of the first-order low-pass on the finite-difference joint
    velocities the streaming estimator derives when a joint state has none. tick_tolerance_s: a joint
    sample this much before a tick's grid point is that tick's sample (raise it to the stamps' jitter,
    below half a period, for a robot whose stamps are not exact multiples of its period).
    vertical_crossover_rad_s: 0 publishes the KF's height and vertical velocity; > 0 passes them through a
    complementary vertical channel (``VerticalChannel``): the IMU's vertical acceleration above this
    crossover, the KF below it. The KF follows the legs' velocity within ~70 ms, so a stance foot's modelled
    sinking (from the TCE) moves the estimate as a real sinking would; a TCE fed with that estimate sees its
    own model again and cannot tell soft from rigid ground. With the channel the base's motion within a
    stance is the IMU's.
    leg_velocity_gate_m_s: 0 off; > 0: a supporting leg whose implied base velocity is further than this from
    the KF's prediction (its velocity plus the IMU's acceleration over the tick) gets no weight in that tick's
    velocity measurement (a landing foot that still moves, a slipping one); counted in ``gated_legs``. When
    that would leave less than ``min_support`` the legs stay (they agree that the prediction is off).
    """

    period_s: float = 0.003
    accel_noise_m_s2: float = 0.5
    leg_velocity_noise_m_s: float = 0.05
    initial_position_std_m: float = 0.01
    initial_velocity_std_m_s: float = 0.1
    min_support: float = 0.5
    max_gap_periods: int = 10
    motion_compensation_tau_s: float = 0.03
    accel_range_m_s2: float = 392.0
    gyro_range_rad_s: float = 34.9
    joint_velocity_cutoff_hz: float = 40.0
    tick_tolerance_s: float = 1e-4
    vertical_crossover_rad_s: float = 0.0
    leg_velocity_gate_m_s: float = 0.08
    attitude: AttitudeSettings = field(default_factory=AttitudeSettings)
    leg_odometry: LegOdometrySettings = field(default_factory=LegOdometrySettings)

    def __post_init__(self) -> None:
        for name in ("period_s", "accel_noise_m_s2", "leg_velocity_noise_m_s", "motion_compensation_tau_s",
                     "initial_position_std_m",
                     "initial_velocity_std_m_s", "min_support", "accel_range_m_s2", "gyro_range_rad_s",
                     "joint_velocity_cutoff_hz", "tick_tolerance_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise InputError(f"StateEstimatorSettings.{name} must be finite and > 0, got {value!r}")
        for name in ("vertical_crossover_rad_s", "leg_velocity_gate_m_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise InputError(f"StateEstimatorSettings.{name} must be finite and >= 0, got {value!r}")
        if self.tick_tolerance_s >= 0.5 * self.period_s:
            raise InputError(f"StateEstimatorSettings.tick_tolerance_s must be below half the period "
                             f"({0.5 * self.period_s} s), got {self.tick_tolerance_s!r}")
        if int(self.max_gap_periods) < 1:
            raise InputError(f"StateEstimatorSettings.max_gap_periods must be >= 1, got {self.max_gap_periods!r}")


@dataclass(frozen=True)
class StateEstimate:
    """One tick's estimate. World frame unless noted; quaternion (x, y, z, w) is world_R_base.

    position_covariance (3, 3) [m^2], velocity_covariance (3, 3) [m^2/s^2] world; attitude_covariance
    (3, 3) [rad^2] about the world axes; angular_velocity_base [rad/s] is the bias-corrected gyro.
    """

    t_s: float
    position: np.ndarray
    quat_xyzw: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity_base: np.ndarray
    position_covariance: np.ndarray
    velocity_covariance: np.ndarray
    attitude_covariance: np.ndarray
    gyro_bias: np.ndarray
    legs: LegOdometryOutput

    @property
    def world_R_base(self) -> np.ndarray:
        return rotation_from_quat_xyzw(self.quat_xyzw)

    @property
    def base_state(self) -> BaseState:
        """The estimate as a base state (angular velocity in the world frame), as controllers and the TCE
        take it."""
        return BaseState(self.position, self.quat_xyzw, self.linear_velocity,
                         self.world_R_base @ self.angular_velocity_base)


def _checked(value: np.ndarray, size: int, name: str, reason: str) -> np.ndarray:
    array = np.asarray(value, dtype=float)
    if array.shape != (size,):
        raise EstimatorInputError(reason, f"{name} must have {size} values, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise EstimatorInputError(reason, f"{name} has NaN or inf: {array}")
    return array


class StateEstimator:
    """Attitude observer + leg odometry + LTV Kalman filter; robot agnostic (URDF + robot YAML)."""

    def __init__(self, model: RobotModel, settings: StateEstimatorSettings | None = None,
                 magnetic_field_world: np.ndarray | None = None) -> None:
        self.model = model
        self.settings = settings or StateEstimatorSettings()
        self.legs = LegOdometry(model, self.settings.leg_odometry)
        self._magnetic_field_world = magnetic_field_world
        imu = model.description
        self._base_R_imu = rotation_from_quat_xyzw(np.asarray(imu.base_quat_imu_xyzw, float))
        self._imu_position = np.asarray(imu.imu_position_base_m, float)
        self._previous_gyro_base: np.ndarray | None = None
        self.attitude: AttitudeEstimator | None = None
        self.kf: KalmanFilter | None = None
        self.t_s: float | None = None
        self.reinitialisations = 0
        self.gated_legs = 0   # supporting legs left out of a tick's velocity measurement (leg_velocity_gate_m_s)
        self._model_dt = -1.0
        self._measurement_noise = np.eye(3) * self.settings.leg_velocity_noise_m_s**2
        self._vertical = VerticalChannel()

    # -- initialisation -----------------------------------------------------------------------------------
    def initialise(self, t_s: float, position: np.ndarray, world_R_base: np.ndarray | None = None,
                   velocity: np.ndarray | None = None, attitude_std_rad: float | None = None) -> None:
        """Start (or restart) at ``position`` [m] world, optional attitude (with its uncertainty
        ``attitude_std_rad``; default: known to 0.01 rad if given, unknown otherwise) and velocity [m/s]."""
        s = self.settings
        if attitude_std_rad is None and world_R_base is not None:
            attitude_std_rad = KNOWN_ATTITUDE_STD_RAD
        self.attitude = AttitudeEstimator(s.attitude, world_R_base, self._magnetic_field_world, attitude_std_rad)
        kf = KalmanFilter(dim_x=6, dim_z=3, dim_u=3)
        kf.x = np.concatenate([_checked(position, 3, "initial position", "initial"),
                               np.zeros(3) if velocity is None else _checked(velocity, 3, "initial velocity",
                                                                             "initial")]).reshape(6, 1)
        kf.P = np.diag([s.initial_position_std_m**2] * 3 + [s.initial_velocity_std_m_s**2] * 3)
        kf.H = np.hstack([np.zeros((3, 3)), np.eye(3)])
        self.kf = kf
        self._model_dt = -1.0
        self.legs.reset()
        self._previous_gyro_base = None
        self._gravity = MotionCompensatedGravity(s.motion_compensation_tau_s)
        self._last_acceleration = None
        self._vertical.reset()
        self.t_s = float(t_s)

    def initialise_standing(self, t_s: float, joint_positions: np.ndarray, xy: tuple[float, float] = (0.0, 0.0),
                            ground_height_m: float = 0.0, world_R_base: np.ndarray | None = None) -> None:
        """Start with the base above ``xy`` at the height its legs reach down to the ground (all feet on
        flat ground at ``ground_height_m``), level unless ``world_R_base`` is given."""
        rotation = np.eye(3) if world_R_base is None else world_R_base
        q = self.model.make_q(np.zeros(3), quat_xyzw_from_rotation(rotation),
                              _checked(joint_positions, len(self.model.description.joint_names),
                                       "joint positions", "joints"))
        self.model.update(q, np.zeros(self.model.nv))
        feet = self.model.foot_positions()
        height = ground_height_m + self.model.description.foot_radius_m - float(np.mean(feet[:, 2]))
        self.initialise(t_s, np.array([xy[0], xy[1], height]), world_R_base)

    @property
    def initialised(self) -> bool:
        return self.kf is not None

    def reconfigure(self, settings: StateEstimatorSettings) -> None:
        """Apply ``settings`` from the next tick (noise figures, limits, gains, contact threshold), keeping
        the estimated state. The tick period and the leg odometry mode are fixed (InputError)."""
        if settings.period_s != self.settings.period_s:
            raise InputError(f"the estimator's period is fixed at {self.settings.period_s} s; got {settings.period_s}")
        self.legs.reconfigure(settings.leg_odometry)
        self.settings = settings
        self._measurement_noise = np.eye(3) * settings.leg_velocity_noise_m_s**2
        self._model_dt = -1.0  # the KF's process noise is rebuilt at the next tick
        if self.attitude is not None:
            self.attitude.reconfigure(settings.attitude)
            self._gravity.tau_s = settings.motion_compensation_tau_s

    # -- one tick -----------------------------------------------------------------------------------------
    def check_imu(self, specific_force: np.ndarray, angular_rate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Validated (specific force, angular rate) of one IMU sample; EstimatorInputError otherwise."""
        s = self.settings
        f = _checked(specific_force, 3, "specific force", "imu_nan")
        w = _checked(angular_rate, 3, "angular rate", "imu_nan")
        if np.abs(f).max() >= s.accel_range_m_s2 or np.abs(w).max() >= s.gyro_range_rad_s:
            raise EstimatorInputError("imu_saturated", f"IMU sample at or beyond its range "
                                      f"(|f| max {np.max(np.abs(f)):.1f} m/s^2, |w| max {np.max(np.abs(w)):.2f} rad/s)")
        return f, w

    def update(self, t_s: float, specific_force: np.ndarray, angular_rate: np.ndarray,
               joint_positions: np.ndarray, joint_velocities: np.ndarray, joint_torques: np.ndarray | None,
               impedance: LegImpedance | None = None, magnetic_field: np.ndarray | None = None,
               foot_contact: np.ndarray | None = None) -> StateEstimate:
        """One tick at ``t_s`` [s] with IMU means since the previous tick (IMU frame) and the joint state
        of the tick (canonical order). ``foot_contact`` (4,): the feet's sensor values (force or flags) when
        the leg odometry's contact_source is a sensor; then the torques are optional (None). Raises
        EstimatorInputError (reason key) for unusable input; a gap of more than ``max_gap_periods``
        re-initialises the velocity filter (counted)."""
        if self.kf is None or self.attitude is None or self.t_s is None:
            raise EstimatorInputError("not_initialised", "state estimator: call initialise() first")
        s = self.settings
        n = len(self.model.description.joint_names)
        q = _checked(joint_positions, n, "joint positions", "joints")
        qd = _checked(joint_velocities, n, "joint velocities", "joints")
        source = s.leg_odometry.contact_source
        if source == "torque":
            if joint_torques is None:
                raise EstimatorInputError("joints", "joint torques are needed with contact_source 'torque'")
            tau = _checked(joint_torques, n, "joint torques", "joints")
            contact = None
        else:  # the torques are not read
            tau = None if joint_torques is None else np.asarray(joint_torques, dtype=float)
            if foot_contact is None:
                raise EstimatorInputError("no_contacts", f"contact_source {source!r}: no foot contact sample")
            contact = _checked(foot_contact, NUM_LEGS, "foot contact", "contacts")
        f_imu, w_imu = self.check_imu(specific_force, angular_rate)
        mag_imu = None if magnetic_field is None else _checked(magnetic_field, 3, "magnetic field", "mag_nan")
        if not math.isfinite(t_s) or t_s <= self.t_s:
            raise EstimatorInputError("out_of_order", f"tick at {t_s:.6f} s is not after the previous one "
                                      f"({self.t_s:.6f} s)")
        dt = t_s - self.t_s
        if dt > s.max_gap_periods * s.period_s:
            self._reinitialise_velocity()
            dt = s.period_s
        self.t_s = float(t_s)

        gyro = self._base_R_imu @ w_imu
        f_base = self._base_R_imu @ f_imu
        if self._previous_gyro_base is not None:  # lever arm of an IMU away from the base origin
            alpha = (gyro - self._previous_gyro_base) / dt
            f_base = f_base - cross3(alpha, self._imu_position) - cross3(gyro, cross3(gyro, self._imu_position))
        self._previous_gyro_base = gyro
        mag = None if mag_imu is None else self._base_R_imu @ mag_imu
        # Leg odometry first, with the previous attitude: its base-frame velocity does not depend on it,
        # and it turns the specific force into a gravity direction free of the trunk's own acceleration.
        previous_R = self.attitude.world_R_base
        previous_omega_base = gyro - self.attitude.gyro_bias
        legs = self.legs.update(dt, previous_R, previous_R @ previous_omega_base, q, qd, tau,
                                base_acceleration_world=self._last_acceleration, impedance=impedance,
                                foot_contact=contact)
        if s.leg_velocity_gate_m_s > 0.0 and self._last_acceleration is not None:
            legs = self._gated(legs, self.kf.x.ravel()[3:] + self._last_acceleration * dt, s.leg_velocity_gate_m_s)
        supported = legs.weight_sum >= s.min_support
        velocity_base = previous_R.T @ legs.base_velocity if supported else None
        self.attitude.update(dt, self._gravity.update(dt, f_base, previous_omega_base, velocity_base), gyro, mag)
        world_R_base = self.attitude.world_R_base
        omega_base = gyro - self.attitude.gyro_bias
        acceleration = world_R_base @ f_base + GRAVITY_WORLD
        self._last_acceleration = acceleration

        kf = self.kf
        if abs(dt - self._model_dt) > 1e-9:  # the discrete model only changes with the interval
            self._model_dt = dt
            kf.F = np.kron([[1.0, dt], [0.0, 1.0]], np.eye(3))
            kf.B = np.kron([[0.5 * dt * dt], [dt]], np.eye(3))
            kf.Q = np.kron([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]], np.eye(3)) * s.accel_noise_m_s2**2
        kf.predict(u=acceleration.reshape(3, 1))
        if supported:
            measured = world_R_base @ velocity_base  # the legs' reading with the updated attitude
            kf.update(measured.reshape(3, 1), R=self._measurement_noise / legs.weight_sum)
        x = kf.x.ravel().copy()
        if s.vertical_crossover_rad_s > 0.0:
            x[2], x[5] = self._vertical.update(dt, float(acceleration[2]), float(x[2]), float(x[5]),
                                               s.vertical_crossover_rad_s)
        p = kf.P
        attitude_cov = world_R_base @ self.attitude.attitude_covariance @ world_R_base.T
        return StateEstimate(self.t_s, x[:3].copy(), quat_xyzw_from_rotation(world_R_base), x[3:].copy(),
                             omega_base, p[:3, :3].copy(), p[3:, 3:].copy(), attitude_cov,
                             self.attitude.gyro_bias.copy(), legs)

    def _gated(self, legs: LegOdometryOutput, predicted: np.ndarray, gate: float) -> LegOdometryOutput:
        """``legs`` with the supporting legs whose implied base velocity is further than ``gate`` [m/s] from
        ``predicted`` (world) taken out of the weighted mean (their contact flags and probabilities stay)."""
        far = (legs.probability > 0.0) & (np.linalg.norm(legs.leg_velocity - predicted, axis=1) > gate)
        if not far.any():
            return legs
        base, weight_sum = weighted_base_velocity(np.where(far, 0.0, legs.probability), legs.leg_velocity)
        if weight_sum < self.settings.min_support:
            return legs   # the legs agree the prediction is off (the IMU's): they stay the measurement
        self.gated_legs += int(far.sum())
        return replace(legs, base_velocity=base, weight_sum=weight_sum)

    def _reinitialise_velocity(self) -> None:
        """After a gap: keep position and attitude, forget the velocity and the leg states."""
        assert self.kf is not None
        s = self.settings
        self.kf.x[3:] = 0.0
        self.kf.P[3:, :] = 0.0
        self.kf.P[:, 3:] = 0.0
        self.kf.P[3:, 3:] = np.eye(3) * s.initial_velocity_std_m_s**2
        self.legs.reset()
        self._previous_gyro_base = None
        self._gravity = MotionCompensatedGravity(s.motion_compensation_tau_s)
        self._last_acceleration = None
        self._vertical.reset()
        self.reinitialisations += 1


class VerticalChannel:
    """Complementary vertical channel: height and vertical velocity that follow the IMU's vertical acceleration
    above the crossover w [rad/s] and a reference (the KF's) below it. The deviation d = (z, v) - reference
    obeys d_v' = a - a_ref - 2 w d_v - w^2 d_z, d_z' = d_v (a critically damped second-order high-pass of
    the acceleration the reference does not have), with a_ref the reference velocity's finite difference."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._dz = self._dv = 0.0
        self._previous_v: float | None = None

    def update(self, dt: float, acceleration: float, z_ref: float, v_ref: float, w: float) -> tuple[float, float]:
        a_ref = 0.0 if self._previous_v is None else (v_ref - self._previous_v) / dt
        self._previous_v = v_ref
        self._dv += dt * (acceleration - a_ref - 2.0 * w * self._dv - w * w * self._dz)
        self._dz += dt * self._dv
        return z_ref + self._dz, v_ref + self._dv


class MotionCompensatedGravity:
    """The specific force with the trunk's own acceleration removed, for the attitude observer.

    In the base frame f = dv/dt + w x v - g, with v the base velocity in the base frame. Leg odometry gives
    v without the attitude, so f - dv/dt - w x v is -g: a gravity direction that forward accelerations
    and sway do not tilt (uncompensated, a 1 m/s^2 push reads as 6 deg of tilt and the XKF books it as
    gyro bias). Both terms are low-pass filtered alike (time constant ``tau_s``) to tame impacts; without
    leg support (``velocity_base`` None) the raw specific force passes.
    """

    def __init__(self, tau_s: float) -> None:
        self.tau_s = tau_s
        self._velocity: np.ndarray | None = None
        self._filtered: np.ndarray | None = None

    def update(self, dt: float, specific_force: np.ndarray, omega_base: np.ndarray,
               velocity_base: np.ndarray | None) -> np.ndarray:
        if velocity_base is None or not np.isfinite(velocity_base).all():
            self._velocity = None
            self._filtered = None
            return specific_force
        alpha = dt / (self.tau_s + dt)
        previous = self._velocity
        self._velocity = velocity_base if previous is None else previous + alpha * (velocity_base - previous)
        derivative = np.zeros(3) if previous is None else (self._velocity - previous) / dt
        gravity_up = specific_force - cross3(omega_base, self._velocity) - derivative
        if self._filtered is None:
            self._filtered = specific_force
        self._filtered = self._filtered + alpha * (gravity_up - self._filtered)
        return self._filtered


def legs_from_impedance_arrays(stiffness: np.ndarray, damping: np.ndarray, valid: np.ndarray,
                               normal: np.ndarray | None = None, confidence: np.ndarray | None = None,
                               rigid: np.ndarray | None = None) -> LegImpedance:
    """LegImpedance from per-leg arrays (normal defaults to world z; confidence and rigid flags, the TCE's,
    are optional: see LegImpedance)."""
    normals = np.tile([0.0, 0.0, 1.0], (NUM_LEGS, 1)) if normal is None else np.asarray(normal, float)
    return LegImpedance(np.asarray(stiffness, float), np.asarray(damping, float), normals,
                        np.asarray(valid, bool) & np.isfinite(stiffness) & np.isfinite(damping),
                        None if confidence is None else np.nan_to_num(np.asarray(confidence, float), nan=0.0),
                        None if rigid is None else np.asarray(rigid, bool))
