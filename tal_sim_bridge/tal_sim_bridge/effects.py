"""Model effects of the simulated robot that the nominal controller model does not know about.

All effects are off by default. The sim-vs-measured workflow (tal_sim2real) turns them on to explain
the gap between simulation and measured data, so each one is a single named, validated parameter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np

from .errors import BridgeConfigError

COULOMB_SMOOTHING_RAD_S = 0.01  # joint speed at which Coulomb friction reaches 76% of its magnitude
GROUND_REFERENCE_DEPTH_M = 0.01
"""[m] sinkage at which a power-law (Hunt-Crossley-type) ground has its patch's stiffness and damping."""
GROUND_MIN_DEPTH_M = 1e-3
"""[m] depth used for the power-law scale at first contact (the scale of a zero depth would be zero)."""


@dataclass(frozen=True)
class ModelEffects:
    """Effects applied by the bridge on top of the nominal PyBullet model.

    Attributes (units in the names):
        actuator_delay_s: pure transport delay of the torque command [s], rounded to physics steps.
        actuator_lag_s: time constant of a first-order lag on the torque [s]; 0 = no lag.
        torque_gain: multiplicative error of the delivered torque [-]; 1 = exact.
        torque_limit_scale: scale on the robot's torque limits [-]; 1 = nominal limits.
        joint_viscous_friction_nms_per_rad: viscous joint friction b in tau_f = -b * qd [N m s/rad].
        joint_coulomb_friction_nm: Coulomb joint friction c in tau_f = -c * sign(qd) [N m].
        payload_mass_kg: extra point mass rigidly attached to the trunk [kg].
        payload_offset_m: position of the payload relative to the trunk's CoM, base frame [m].
        imu_gyro_bias_rad_s: constant gyroscope bias, base frame [rad/s].
        imu_accel_bias_m_s2: constant accelerometer bias, base frame [m/s^2].
        ground_contact_exponent: exponent n of a power-law (Hunt-Crossley-type) ground [-]: the normal force
            is (delta / delta_ref)^(n - 1) * (k * delta + d * delta_dot) with the patch's stiffness k and
            damping d, delta the sinkage and delta_ref = GROUND_REFERENCE_DEPTH_M; so, as in Hunt and
            Crossley's model, stiffness and damping vanish at first contact and grow with depth when n > 1.
            1 = the linear Kelvin-Voigt ground (nominal).
    """

    actuator_delay_s: float = 0.0
    actuator_lag_s: float = 0.0
    torque_gain: float = 1.0
    torque_limit_scale: float = 1.0
    joint_viscous_friction_nms_per_rad: float = 0.0
    joint_coulomb_friction_nm: float = 0.0
    payload_mass_kg: float = 0.0
    payload_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    imu_gyro_bias_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    imu_accel_bias_m_s2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ground_contact_exponent: float = 1.0

    def __post_init__(self) -> None:
        nonneg = ("actuator_delay_s", "actuator_lag_s", "joint_viscous_friction_nms_per_rad",
                  "joint_coulomb_friction_nm", "payload_mass_kg")
        for name in nonneg:
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0.0:
                raise BridgeConfigError(f"effect '{name}' must be a finite number >= 0, got {value!r}")
        for name in ("torque_gain", "torque_limit_scale"):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0.0:
                raise BridgeConfigError(f"effect '{name}' must be a finite number > 0, got {value!r}")
        n = self.ground_contact_exponent
        if not math.isfinite(n) or not 0.5 <= n <= 3.0:
            raise BridgeConfigError(f"effect 'ground_contact_exponent' must be in [0.5, 3], got {n!r}")
        for name in ("payload_offset_m", "imu_gyro_bias_rad_s", "imu_accel_bias_m_s2"):
            value = getattr(self, name)
            if len(value) != 3 or not all(math.isfinite(v) for v in value):
                raise BridgeConfigError(f"effect '{name}' must be 3 finite numbers, got {value!r}")

    @classmethod
    def from_mapping(cls, values: dict[str, object]) -> ModelEffects:
        """Build from a mapping (e.g. ROS parameters or a YAML dict); unknown keys are an error."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise BridgeConfigError(f"unknown model effect(s) {unknown}; known: {sorted(known)}")
        kwargs: dict[str, object] = {}
        for key, value in values.items():
            if key in ("payload_offset_m", "imu_gyro_bias_rad_s", "imu_accel_bias_m_s2"):
                kwargs[key] = tuple(float(v) for v in value)  # type: ignore[union-attr]
            else:
                kwargs[key] = float(value)  # type: ignore[arg-type]
        return cls(**kwargs)  # type: ignore[arg-type]

    def active(self) -> dict[str, object]:
        """The effects that differ from the nominal (default) model."""
        default = ModelEffects()
        return {f.name: getattr(self, f.name) for f in fields(self)
                if getattr(self, f.name) != getattr(default, f.name)}


@dataclass
class ActuatorModel:
    """Torque path from the commanded to the delivered joint torque, run once per physics step.

    command -> transport delay -> first-order lag -> gain -> saturation at the (scaled) limits.
    Joint friction is returned separately because it acts on the joint, not inside the torque sensor.
    """

    effects: ModelEffects
    dt_s: float
    tau_min: np.ndarray
    tau_max: np.ndarray
    _queue: list[np.ndarray] = field(default_factory=list, init=False)
    _lagged: np.ndarray | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        if not (self.dt_s > 0.0):
            raise BridgeConfigError(f"physics time step must be > 0 s, got {self.dt_s}")
        self.delay_steps = int(round(self.effects.actuator_delay_s / self.dt_s))
        lag = self.effects.actuator_lag_s
        # Exact discretisation of dx/dt = (u - x) / T with a zero-order-held input.
        self._lag_alpha = 1.0 if lag == 0.0 else 1.0 - math.exp(-self.dt_s / lag)

    def reset(self) -> None:
        self._queue.clear()
        self._lagged = None

    def delivered_torque(self, commanded: np.ndarray, tau_min: np.ndarray | None = None,
                         tau_max: np.ndarray | None = None) -> np.ndarray:
        """Torque the actuators deliver this step [N m] (what a joint torque sensor reads).

        ``tau_min``/``tau_max`` [N m] override the construction-time limits (joint-angle-dependent tables).
        """
        self._queue.append(np.asarray(commanded, dtype=float).copy())
        if len(self._queue) > self.delay_steps + 1:
            self._queue.pop(0)
        delayed = self._queue[0] if len(self._queue) == self.delay_steps + 1 else np.zeros_like(commanded)
        if self._lagged is None:
            self._lagged = np.zeros_like(delayed)
        self._lagged = self._lagged + self._lag_alpha * (delayed - self._lagged)
        scale = self.effects.torque_limit_scale
        low = self.tau_min if tau_min is None else tau_min
        high = self.tau_max if tau_max is None else tau_max
        return np.clip(self.effects.torque_gain * self._lagged, scale * low, scale * high)

    def friction_torque(self, joint_velocity: np.ndarray) -> np.ndarray:
        """Joint friction torque [N m] opposing the joint velocity [rad/s]."""
        qd = np.asarray(joint_velocity, dtype=float)
        # tanh instead of sign: a 1 kHz explicit step would chatter around zero velocity.
        coulomb = self.effects.joint_coulomb_friction_nm * np.tanh(qd / COULOMB_SMOOTHING_RAD_S)
        return -self.effects.joint_viscous_friction_nms_per_rad * qd - coulomb


def power_law_ground_scale(depth_m: np.ndarray, exponent: float) -> np.ndarray:
    """Factor (delta / delta_ref)^(n - 1) on a power-law ground's stiffness and damping [-] for sinkage
    ``depth_m`` [m] (floored at GROUND_MIN_DEPTH_M; see ``ModelEffects.ground_contact_exponent``)."""
    depth = np.maximum(np.asarray(depth_m, dtype=float), GROUND_MIN_DEPTH_M)
    return (depth / GROUND_REFERENCE_DEPTH_M) ** (exponent - 1.0)
