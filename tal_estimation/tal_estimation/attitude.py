"""Attitude estimation: the thesis' globally exponentially stable nonlinear observer (NLO, Grip et al.
2015) with gyro-bias estimation, cascaded with an exogenous Kalman filter (XKF, Johansen et al. 2017).

Frames: ``world_R_base`` maps base-frame vectors to the world frame (z up). Vector measurements are
pairs (y_b, y_n): a unit direction measured in the base frame and the same direction known in the world
frame. The accelerometer gives gravity's direction (specific force, up when standing still); a
magnetometer, when there is one, gives heading. With gravity alone the yaw angle and the z gyro bias are
unobservable (the observer keeps integrating the gyro about z), as for every IMU-only estimator.

NLO (thesis eq. NLO), discretised on SO(3) with the injection projected onto its tangent space:

    R' = R Exp((w - b) dt),   c = vex(P_a(R'^T K_p J(R'))),   J(R) = sum_j (y_n - R y_b) y_b^T
    R <- R' Exp(sigma c dt),  b <- Proj(b - dt k_I c)             (||b|| <= M_b)

The thesis prints P(X) = (X + X^T)/2, whose vex is zero; Grip et al. use the antisymmetric part
P_a(X) = (X - X^T)/2, which is what is implemented.

XKF: an error-state Kalman filter on (delta, b), where the estimate is world_R_base = Exp(delta) R_nlo,
linearised about the NLO's estimate (the exogenous signal) instead of about its own estimate, so it
inherits the NLO's global stability and is near-optimal once the NLO has converged.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from tal_core.errors import InputError
from tal_core.rotations import nearest_rotation, skew, so3_exp, so3_log

UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class AttitudeSettings:
    """Gains and noise figures of the attitude observer (SI units).

    k_p [rad/s]: NLO injection gain (K_p = k_p I). k_i [1/s^2]: gyro-bias adaptation gain. sigma [-]:
    injection scaling (>= 1). max_gyro_bias_rad_s: projection bound M_b on ||b||.
    gyro_noise_rad_s_sqrt_hz / gyro_bias_walk_rad_s2_sqrt_hz: XKF process noise densities.
    accel_direction_noise [-]: std of the measured gravity direction at rest; accel_dynamic_scale_m_s2:
    the deviation of ||f|| from g at which the accelerometer's weight halves (NLO) and its variance
    doubles (XKF). mag_direction_noise [-]: std of the measured heading direction.
    """

    k_p: float = 1.0
    k_i: float = 0.3
    sigma: float = 1.0
    max_gyro_bias_rad_s: float = 0.2
    gyro_noise_rad_s_sqrt_hz: float = 2e-3
    gyro_bias_walk_rad_s2_sqrt_hz: float = 1e-4
    accel_direction_noise: float = 0.2
    accel_dynamic_scale_m_s2: float = 2.0
    mag_direction_noise: float = 0.05
    initial_attitude_std_rad: float = 1.0
    initial_bias_std_rad_s: float = 0.05
    gravity_m_s2: float = 9.81

    def __post_init__(self) -> None:
        for name in ("k_p", "k_i", "max_gyro_bias_rad_s", "gyro_noise_rad_s_sqrt_hz",
                     "gyro_bias_walk_rad_s2_sqrt_hz", "accel_direction_noise", "accel_dynamic_scale_m_s2",
                     "mag_direction_noise", "initial_attitude_std_rad", "initial_bias_std_rad_s", "gravity_m_s2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise InputError(f"AttitudeSettings.{name} must be finite and > 0, got {value!r}")
        if not (math.isfinite(self.sigma) and self.sigma >= 1.0):
            raise InputError(f"AttitudeSettings.sigma must be >= 1, got {self.sigma!r}")


@dataclass(frozen=True)
class VectorMeasurement:
    """A unit direction measured in the base frame (``base``) and known in the world frame (``world``),
    with its NLO weight [-] and XKF variance [-^2]."""

    base: np.ndarray
    world: np.ndarray
    weight: float
    variance: float


def _inverse3(matrix: np.ndarray) -> np.ndarray:
    """Inverse of an invertible 3 x 3 matrix from its adjugate in scalar arithmetic (a LAPACK solve costs
    several times more at this size; the XKF's innovation covariance is positive definite)."""
    (a, b, c), (d, e, f), (g, h, i) = matrix.tolist()
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * c00 + b * c01 + c * c02
    if not (math.isfinite(det) and det != 0.0):
        raise np.linalg.LinAlgError(f"singular 3 x 3 matrix (determinant {det})")
    return np.array([[c00, c * h - b * i, b * f - c * e],
                     [c01, a * i - c * g, c * d - a * f],
                     [c02, b * g - a * h, a * e - b * d]]) / det


def _vex(matrix: np.ndarray) -> np.ndarray:
    return np.array([matrix[2, 1], matrix[0, 2], matrix[1, 0]])


class NonlinearAttitudeObserver:
    """The NLO: world_R_base and gyro bias [rad/s] (base frame), globally exponentially stable given two
    non-collinear directions (or one persistently exciting one)."""

    def __init__(self, settings: AttitudeSettings, world_R_base: np.ndarray | None = None,
                 gyro_bias: np.ndarray | None = None) -> None:
        self.settings = settings
        self.rotation = np.eye(3) if world_R_base is None else nearest_rotation(np.asarray(world_R_base, float))
        self.bias = np.zeros(3) if gyro_bias is None else np.asarray(gyro_bias, float).copy()

    def update(self, dt: float, gyro: np.ndarray, measurements: Sequence[VectorMeasurement]) -> None:
        """Advance by ``dt`` [s] with the mean angular rate ``gyro`` [rad/s] (base frame) over it.

        The injection sigma K_p J is applied through its projection onto the tangent space of SO(3) at R,
        R P_a(R^T sigma K_p J) (the symmetric part does not rotate), so R stays a rotation without an SVD.
        """
        s = self.settings
        # Predict with the gyro first, so the correction uses the measurements and the rotation of the
        # same instant (the end of the interval).
        predicted = self.rotation @ so3_exp((gyro - self.bias) * dt)
        injection = np.zeros((3, 3))
        for m in measurements:
            injection += m.weight * np.outer(m.world - predicted @ m.base, m.base)
        injection *= s.k_p
        x = predicted.T @ injection
        correction = _vex(0.5 * (x - x.T))
        self.rotation = predicted @ so3_exp(s.sigma * correction * dt)
        bias = self.bias - dt * s.k_i * correction  # R_s = sat(R) = R for a rotation matrix
        norm = float(np.linalg.norm(bias))
        if norm > s.max_gyro_bias_rad_s:  # parameter projection onto the ball ||b|| <= M_b
            bias *= s.max_gyro_bias_rad_s / norm
        self.bias = bias


class ExogenousKalmanFilter:
    """XKF on x = (delta [rad] world frame, b [rad/s] base frame) with world_R_base = Exp(delta) R_nlo,
    linearised about the NLO's estimate. Without a heading measurement the world-z component of delta is
    unobservable; it is then held at zero, so the XKF takes its heading from the NLO."""

    def __init__(self, settings: AttitudeSettings, nlo: NonlinearAttitudeObserver,
                 attitude_std_rad: float | None = None) -> None:
        self.settings = settings
        self.rotation = nlo.rotation.copy()
        self.bias = nlo.bias.copy()
        std = settings.initial_attitude_std_rad if attitude_std_rad is None else attitude_std_rad
        self.covariance = np.diag([std**2] * 3 + [settings.initial_bias_std_rad_s**2] * 3)
        self._process_noise_density = self._noise_density(settings)

    @staticmethod
    def _noise_density(settings: AttitudeSettings) -> np.ndarray:
        return np.diag([settings.gyro_noise_rad_s_sqrt_hz**2] * 3 + [settings.gyro_bias_walk_rad_s2_sqrt_hz**2] * 3)

    def reconfigure(self, settings: AttitudeSettings) -> None:
        """New noise figures from the next update; the state and its covariance stay."""
        self.settings = settings
        self._process_noise_density = self._noise_density(settings)

    def update(self, dt: float, gyro: np.ndarray, nlo: NonlinearAttitudeObserver,
               measurements: Sequence[VectorMeasurement], has_heading: bool) -> None:
        """Propagate with the gyro, then correct with the directions, linearised about the (already
        updated) NLO estimate ``nlo``."""
        # Prediction: own state integrated exactly; covariance with the Jacobian at the NLO's attitude.
        self.rotation = self.rotation @ so3_exp((gyro - self.bias) * dt)
        phi = np.eye(6)
        phi[:3, 3:] = -nlo.rotation * dt
        p = phi @ self.covariance @ phi.T + self._process_noise_density * dt
        delta = so3_log(self.rotation @ nlo.rotation.T)
        if not has_heading:
            delta[2] = 0.0
        x = np.concatenate([delta, self.bias])
        if measurements:
            # h(delta) = R_nlo^T Exp(-delta) y_n ~ R_nlo^T y_n + R_nlo^T S(y_n) delta.
            k = len(measurements)
            h = np.zeros((3 * k, 6))
            innovation = np.empty(3 * k)
            variances = np.empty(3 * k)
            for j, m in enumerate(measurements):
                rows = slice(3 * j, 3 * j + 3)
                h[rows, :3] = nlo.rotation.T @ skew(m.world)
                innovation[rows] = m.base - nlo.rotation.T @ m.world - h[rows, :3] @ delta
                variances[rows] = m.variance
            r = np.diag(variances)
            hp = h @ p
            innovation_cov = hp @ h.T + r
            gain = (_inverse3(innovation_cov) @ hp).T if k == 1 else np.linalg.solve(innovation_cov, hp).T
            x = x + gain @ innovation
            ikh = np.eye(6) - gain @ h
            p = ikh @ p @ ikh.T + gain @ r @ gain.T  # Joseph form: stays symmetric positive definite
        if not has_heading:
            x[2] = 0.0
        self.covariance = p
        self.rotation = so3_exp(x[:3]) @ nlo.rotation
        self.bias = x[3:]


class AttitudeEstimator:
    """NLO cascaded with the XKF. ``update`` takes IMU means over an interval, base frame:
    specific force [m/s^2], angular rate [rad/s] and optionally a magnetic field [any unit]."""

    def __init__(self, settings: AttitudeSettings | None = None, world_R_base: np.ndarray | None = None,
                 magnetic_field_world: np.ndarray | None = None, attitude_std_rad: float | None = None) -> None:
        """``world_R_base``: initial attitude (identity if None); ``attitude_std_rad``: its uncertainty
        (default: the settings' initial_attitude_std_rad, i.e. unknown)."""
        self.settings = settings or AttitudeSettings()
        self.nlo = NonlinearAttitudeObserver(self.settings, world_R_base)
        self.xkf = ExogenousKalmanFilter(self.settings, self.nlo, attitude_std_rad)
        self._heading_world: np.ndarray | None = None
        if magnetic_field_world is not None:
            self._heading_world = self._heading(np.asarray(magnetic_field_world, float), UP, "world field")

    def reconfigure(self, settings: AttitudeSettings) -> None:
        """Apply new gains and noise figures from the next update, keeping the attitude, bias and covariance."""
        self.settings = settings
        self.nlo.settings = settings
        self.xkf.reconfigure(settings)

    @staticmethod
    def _heading(field: np.ndarray, up: np.ndarray, what: str) -> np.ndarray:
        """The horizontal direction (up x field) / |.|: heading information decoupled from tilt."""
        direction = np.cross(up, field)
        norm = float(np.linalg.norm(direction))
        if norm < 1e-9:
            raise InputError(f"{what} is vertical or zero: it gives no heading")
        return direction / norm

    def measurements(self, specific_force: np.ndarray, magnetic_field: np.ndarray | None) -> list[VectorMeasurement]:
        """The directions one IMU sample gives, weighted by how dynamic the motion is."""
        s = self.settings
        out = []
        norm = float(np.linalg.norm(specific_force))
        if norm > 0.2 * s.gravity_m_s2:
            excess = (norm - s.gravity_m_s2) / s.accel_dynamic_scale_m_s2
            out.append(VectorMeasurement(specific_force / norm, UP, 1.0 / (1.0 + excess**2),
                                         s.accel_direction_noise**2 * (1.0 + excess**2)))
        if magnetic_field is not None and self._heading_world is not None and out:
            try:
                heading = self._heading(np.asarray(magnetic_field, float), out[0].base, "measured field")
            except InputError:
                return out
            out.append(VectorMeasurement(heading, self._heading_world, 1.0, s.mag_direction_noise**2))
        return out

    def update(self, dt: float, specific_force: np.ndarray, angular_rate: np.ndarray,
               magnetic_field: np.ndarray | None = None) -> None:
        """Advance by ``dt`` [s] > 0 with finite IMU means over the interval."""
        measurements = self.measurements(specific_force, magnetic_field)
        self.nlo.update(dt, angular_rate, measurements)
        self.xkf.update(dt, angular_rate, self.nlo, measurements, has_heading=len(measurements) > 1)

    @property
    def world_R_base(self) -> np.ndarray:
        """The XKF's estimate of world_R_base."""
        return self.xkf.rotation

    @property
    def gyro_bias(self) -> np.ndarray:
        """The XKF's gyro-bias estimate [rad/s], base frame."""
        return self.xkf.bias

    @property
    def attitude_covariance(self) -> np.ndarray:
        """(3, 3) covariance of the attitude error [rad^2], base frame."""
        return self.xkf.covariance[:3, :3]
