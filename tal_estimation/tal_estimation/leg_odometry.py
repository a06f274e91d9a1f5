"""Leg odometry: the base velocity from the stance feet (thesis eq. lo), rigid or terrain aware.

For every leg, with the joint positions q, joint velocities qd, measured torques tau, the base attitude
world_R_base and the base angular velocity w (world frame):

* ground reaction force (thesis eq. grf): J_leg^T F = h_leg (+ M_leg vdot) - tau_leg, world frame;
* the foot's velocity relative to a base origin that does not translate, world frame:
  v_rel = w x (world_R_base r_foot) + world_R_base J_leg(q) qd;
* the base velocity this leg reads: v_base = v_foot - v_rel, where v_foot is the foot's own velocity.

``rigid`` (the thesis): v_foot = 0, binary contact alpha = ||F|| > threshold, v = mean over the legs in
contact. ``terrain_aware`` (beyond the thesis, its future-work item): the foot sphere rolls (its centre moves at
radius * w_foot x n while the contact point stays; not once sunk deeper than its radius) and the stance
foot sinks into and
rises with a Kelvin-Voigt ground F_n = K p + D dp/dt whose K and D come from the TCE. Given the measured
normal force the penetration obeys D dp/dt = F_n - K p, integrated exactly per interval (stable for any
K/D) from p = 0 at touchdown, so v_foot = -(dp/dt) n; the legs are averaged with a continuous contact
probability (a smoothstep of the normal force) instead of the binary threshold, so the loading
and unloading phases neither chatter nor vanish. A leg without a valid impedance is treated as rigid, and so
is a leg whose impedance the TCE is not confident in (below ``min_confidence``) or reports as rigid (a
lower bound on the stiffness, not a value): sinking is modelled only from a trusted soft-ground fit.
Why: on graph_tour's rigid ground the odometry sank modelled feet by F / K from the TCE's rigid lower bound
(~1e5 N/m, 3-4 mm a stance), the TCE, running on the estimate, read the lowered base as deeper penetration
and fitted softer ground, and the loop ran away to ~400 N/m and -0.5 m of z per m walked (replay, measured).

Contact source (``contact_source``): ``torque`` (the above: the force from the joint torques), or, for robots
that sense contact at the feet and may log no torques, ``force_sensor`` (one force value per foot, raw counts
calibrated per leg as scale * (raw - offset) [N], or newtons with the default calibration; thresholded with
hysteresis: on above the threshold, off below (1 - contact_hysteresis_fraction) x threshold; terrain aware,
the contact probability ramps from the off to the on threshold while in contact) or ``contact_flags`` (one
binary flag per foot; terrain aware, each stance foot carries an equal share of the weight for the sinking
model). With a sensor source no torque is read: the force reported is the sensed normal force along the
contact normal, and the leg inertia term is not used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tal_core.errors import InputError
from tal_core.legs import NUM_LEGS
from tal_core.robot_model import RobotModel
from tal_core.rotations import cross_rows

LEG_ODOMETRY_MODES = ("rigid", "terrain_aware")
CONTACT_SOURCES = ("torque", "force_sensor", "contact_flags")
VERTICAL_NORMALS = np.tile([0.0, 0.0, 1.0], (NUM_LEGS, 1))   # flat ground's contact normals (read only)
VERTICAL_NORMALS.setflags(write=False)


@dataclass(frozen=True)
class LegOdometrySettings:
    """mode: rigid | terrain_aware. contact_threshold_weight_fraction [-]: contact force threshold as a
    fraction of the robot's weight (robot agnostic; 0.1 -> 85 N for HyQ). probability_width_fraction [-]:
    half-width of the contact probability ramp (smoothstep), as a fraction of the threshold.
    swing_probability [-]: below it a leg is in swing; min_swing_s [s]: a swing this long resets its
    penetration state (a force that drops out for a sample mid-stance does not). use_leg_inertia:
    include M_leg vdot in the force (vdot from the IMU and finite differences; terrain_aware only, the
    thesis uses the static form). min_damping_ns_per_m: floor of the ground damping used in the sinking
    model (a TCE fit clamped near zero must not make dp/dt explode); max_penetration_rate_m_s: bound on
    the modelled sinking or rising speed of a stance foot. min_stiffness_n_per_m: a stiffness below it is
    implausible for ground that carries the robot (an unconverged or clamped TCE fit) and the leg is
    treated as on rigid ground; max_penetration_m: bound on the modelled sinking of one foot (a wrong
    stiffness must not sink the estimate by metres per step). min_confidence [-]: a leg whose impedance
    confidence (the TCE's fill ratio x R^2, zero for an inconsistent window) is below it is treated as on
    rigid ground (as the c3WBC's ImpedanceGate, which adopts an estimate from 0.1 on).
    contact_source: torque | force_sensor | contact_flags (module docstring); contact_hysteresis_fraction
    [-]: a sensed contact ends below (1 - it) x the threshold; foot_force_scale [N per sensor unit] and
    foot_force_offset [sensor units, the unloaded reading], per leg (LF, RF, LH, RH): force_sensor
    calibration (defaults: the values are newtons)."""

    mode: str = "rigid"
    contact_threshold_weight_fraction: float = 0.1
    probability_width_fraction: float = 0.5
    swing_probability: float = 1e-6
    min_swing_s: float = 0.02
    use_leg_inertia: bool = True
    min_damping_ns_per_m: float = 50.0
    max_penetration_rate_m_s: float = 2.0
    min_stiffness_n_per_m: float = 500.0
    max_penetration_m: float = 0.3
    min_confidence: float = 0.1
    contact_source: str = "torque"
    contact_hysteresis_fraction: float = 0.3
    foot_force_scale: tuple[float, ...] = (1.0,) * NUM_LEGS
    foot_force_offset: tuple[float, ...] = (0.0,) * NUM_LEGS

    def __post_init__(self) -> None:
        if self.mode not in LEG_ODOMETRY_MODES:
            raise InputError(f"leg odometry mode must be one of {LEG_ODOMETRY_MODES}, got {self.mode!r}")
        if self.contact_source not in CONTACT_SOURCES:
            raise InputError(f"contact_source must be one of {CONTACT_SOURCES}, got {self.contact_source!r}")
        for name in ("foot_force_scale", "foot_force_offset"):
            values = tuple(float(v) for v in getattr(self, name))
            if len(values) != NUM_LEGS or not all(math.isfinite(v) for v in values):
                raise InputError(f"LegOdometrySettings.{name} needs {NUM_LEGS} finite values (LF, RF, LH, RH), "
                                 f"got {getattr(self, name)!r}")
            object.__setattr__(self, name, values)
        if not all(v > 0.0 for v in self.foot_force_scale):
            raise InputError(f"LegOdometrySettings.foot_force_scale must be > 0, got {self.foot_force_scale!r}")
        for name in ("contact_threshold_weight_fraction", "probability_width_fraction", "swing_probability",
                     "contact_hysteresis_fraction"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 < value < 1.0):
                raise InputError(f"LegOdometrySettings.{name} must be in (0, 1), got {value!r}")
        if not (math.isfinite(self.min_confidence) and 0.0 <= self.min_confidence <= 1.0):
            raise InputError(f"LegOdometrySettings.min_confidence must be in [0, 1], got {self.min_confidence!r}")
        if not (math.isfinite(self.min_swing_s) and self.min_swing_s >= 0.0):
            raise InputError(f"LegOdometrySettings.min_swing_s must be finite and >= 0, got {self.min_swing_s!r}")


@dataclass(frozen=True)
class LegImpedance:
    """Per-leg Kelvin-Voigt ground along the contact normal: stiffness [N/m], damping [N s/m], unit normal
    (world frame), valid flags. Shapes (4,), (4,), (4, 3), (4,). Optional, (4,) each: confidence [0, 1] of
    the TCE (None: fully confident) and rigid flags (the stiffness is a lower bound: ground at least that
    stiff; None: none)."""

    stiffness_n_per_m: np.ndarray
    damping_ns_per_m: np.ndarray
    normal: np.ndarray
    valid: np.ndarray
    confidence: np.ndarray | None = None
    rigid: np.ndarray | None = None

    def usable(self, min_confidence: float) -> np.ndarray:
        """(4,) bool: legs whose impedance is a soft-ground fit to model sinking with (valid, confident,
        not a rigid lower bound)."""
        use = np.asarray(self.valid, dtype=bool).copy()
        if self.confidence is not None:
            use &= np.asarray(self.confidence, dtype=float) >= min_confidence
        if self.rigid is not None:
            use &= ~np.asarray(self.rigid, dtype=bool)
        return use


@dataclass(frozen=True)
class LegOdometryOutput:
    """base_velocity [m/s] world frame (NaN when no leg supports); weight_sum [-] (number of supporting
    legs, fractional when terrain aware); per leg: force [N] world, contact flag, probability [0, 1],
    leg_velocity [m/s] world (the base velocity this leg reads), foot_velocity [m/s] world (modelled),
    penetration [m] (terrain aware; 0 otherwise), foot_offset [m] foot centre minus base origin, world."""

    base_velocity: np.ndarray
    weight_sum: float
    force: np.ndarray
    in_contact: np.ndarray
    probability: np.ndarray
    leg_velocity: np.ndarray
    foot_velocity: np.ndarray
    penetration: np.ndarray
    foot_offset: np.ndarray


def weighted_base_velocity(weights: np.ndarray, leg_velocity: np.ndarray) -> tuple[np.ndarray, float]:
    """(the legs' weighted mean base velocity (NaN without support), the weight sum) of per-leg weights (4,)
    and the base velocities the legs read (4, 3)."""
    weight_sum = float(weights.sum())
    return ((weights @ leg_velocity) / weight_sum if weight_sum > 1e-6 else np.full(3, np.nan)), weight_sum


class LegOdometry:
    """Base velocity from the legs; robot agnostic (everything from the RobotModel's URDF + YAML)."""

    def __init__(self, model: RobotModel, settings: LegOdometrySettings | None = None,
                 gravity_m_s2: float = 9.81) -> None:
        self.model = model
        self.settings = settings or LegOdometrySettings()
        self._gravity_m_s2 = gravity_m_s2
        self._set_thresholds()
        self._origin = np.zeros(3)
        self._radius = model.description.foot_radius_m
        self.penetration = np.zeros(NUM_LEGS)
        self._previous_v: np.ndarray | None = None
        self._penetration_rate = np.zeros(NUM_LEGS)
        self._swing_s = np.zeros(NUM_LEGS)   # [s] time each leg has been in swing
        self._sensed_contact = np.zeros(NUM_LEGS, dtype=bool)  # force_sensor: the hysteresis state

    def _set_thresholds(self) -> None:
        fraction = self.settings.contact_threshold_weight_fraction
        self.threshold_n = fraction * self.model.total_mass_kg * self._gravity_m_s2
        self._width_n = self.settings.probability_width_fraction * self.threshold_n
        self._release_n = (1.0 - self.settings.contact_hysteresis_fraction) * self.threshold_n
        self._scale = np.array(self.settings.foot_force_scale)
        self._offset = np.array(self.settings.foot_force_offset)

    def reconfigure(self, settings: LegOdometrySettings) -> None:
        """Apply ``settings`` from the next update (thresholds, bounds, calibration), keeping the legs' state;
        the mode and the contact source are fixed for the odometry's lifetime (InputError)."""
        if settings.mode != self.settings.mode:
            raise InputError(f"leg odometry mode is fixed at {self.settings.mode!r}; got {settings.mode!r}")
        if settings.contact_source != self.settings.contact_source:
            raise InputError(f"contact_source is fixed at {self.settings.contact_source!r}; "
                             f"got {settings.contact_source!r}")
        self.settings = settings
        self._set_thresholds()

    def contact_probability(self, normal_force_n: np.ndarray) -> np.ndarray:
        """Smoothstep from 0 at threshold - width to 1 at threshold + width: exactly zero for a swinging
        foot, whose large velocity would otherwise leak into the average even with a tiny weight."""
        x = np.clip((normal_force_n - self.threshold_n + self._width_n) / (2.0 * self._width_n), 0.0, 1.0)
        return x * x * (3.0 - 2.0 * x)

    def reset(self) -> None:
        self.penetration[:] = 0.0
        self._penetration_rate[:] = 0.0
        self._swing_s[:] = 0.0
        self._previous_v = None
        self._sensed_contact[:] = False

    def sensed_contact(self, foot_contact: np.ndarray, terrain_aware: bool) -> tuple[np.ndarray, np.ndarray]:
        """(normal force [N] (4,), contact probability [0, 1] (4,)) from the per-foot sensor values of
        ``contact_source`` force_sensor (hysteresis) or contact_flags; updates the hysteresis state."""
        values = np.asarray(foot_contact, dtype=float)
        if self.settings.contact_source == "contact_flags":
            flags = values > 0.5
            share = self.model.total_mass_kg * self._gravity_m_s2 / max(int(flags.sum()), 1)
            return np.where(flags, share, 0.0), flags.astype(float)
        force = np.maximum(self._scale * (values - self._offset), 0.0)
        on, off = self.threshold_n, self._release_n
        self._sensed_contact = np.where(self._sensed_contact, force >= off, force > on)
        if not terrain_aware:
            return force, self._sensed_contact.astype(float)
        x = np.clip((force - off) / (on - off), 0.0, 1.0)
        return force, np.where(self._sensed_contact, x * x * (3.0 - 2.0 * x), 0.0)

    def update(self, dt: float, world_R_base: np.ndarray, angular_velocity_world: np.ndarray,
               joint_positions: np.ndarray, joint_velocities: np.ndarray, joint_torques: np.ndarray | None,
               base_acceleration_world: np.ndarray | None = None,
               impedance: LegImpedance | None = None, foot_contact: np.ndarray | None = None) -> LegOdometryOutput:
        """One odometry sample. Joint arrays in canonical order [rad, rad/s, N m]; ``dt`` [s] since the
        previous sample (for the penetration integration and finite differences). ``foot_contact`` (4,):
        the per-foot sensor values of a sensor ``contact_source`` (then ``joint_torques`` is not read and
        may be None)."""
        m, s = self.model, self.settings
        sensed = s.contact_source != "torque"
        if sensed and foot_contact is None:
            raise InputError(f"contact_source {s.contact_source!r} needs the feet's sensor values")
        if not sensed and joint_torques is None:
            raise InputError("contact_source 'torque' needs the joint torques")
        q, v = m.make_q_v(self._origin, world_R_base, joint_positions, self._origin, angular_velocity_world,
                          joint_velocities)
        terrain_aware = s.mode == "terrain_aware"
        inertia = terrain_aware and s.use_leg_inertia and not sensed
        feet = m.foot_dynamics(q, v, with_mass_matrix=inertia)
        h = feet.nonlinear_effects
        if inertia:
            if self._previous_v is not None and base_acceleration_world is not None and dt > 0.0:
                vdot = (v - self._previous_v) / dt
                vdot[0:3] = world_R_base.T @ base_acceleration_world  # the IMU's, not a difference of zeros
                h = h + feet.mass_matrix @ vdot
            self._previous_v = v
        relative = feet.foot_velocities
        normals = VERTICAL_NORMALS if impedance is None else impedance.normal
        if sensed:
            assert foot_contact is not None
            sensed_force, sensed_probability = self.sensed_contact(foot_contact, terrain_aware)
            force = sensed_force[:, None] * normals
        else:
            assert joint_torques is not None
            force = m.foot_forces_from_joint_torques(feet.foot_jacobians, joint_torques, h)
        foot_velocity = np.zeros((NUM_LEGS, 3))
        if terrain_aware:
            # A foot sphere that rolls without slipping: its contact point is still, its centre is not. A
            # foot sunk deeper than its radius is held by the ground around it and does not roll.
            rolling = self._radius * cross_rows(feet.foot_angular_velocities, normals)
            foot_velocity = np.where((self.penetration < self._radius)[:, None], rolling, 0.0)
            if sensed:
                normal_force, probability = sensed_force, sensed_probability
            else:
                normal_force = np.maximum(np.einsum("lk,lk->l", force, normals), 0.0)
                probability = self.contact_probability(normal_force)
            weights = probability
            in_contact = probability > 0.5
            self._integrate_penetration(dt, normal_force, probability, impedance)
            if impedance is not None:
                foot_velocity = foot_velocity - self._penetration_rate[:, None] * normals
        elif sensed:
            probability = sensed_probability
            in_contact = probability > 0.5
            weights = probability
        else:
            norm = np.linalg.norm(force, axis=1)
            in_contact = norm > self.threshold_n
            probability = in_contact.astype(float)
            weights = probability
        leg_velocity = foot_velocity - relative
        base_velocity, weight_sum = weighted_base_velocity(weights, leg_velocity)
        return LegOdometryOutput(base_velocity, weight_sum, force, in_contact, probability, leg_velocity,
                                 foot_velocity, self.penetration.copy(), feet.foot_positions)

    def _integrate_penetration(self, dt: float, normal_force: np.ndarray, probability: np.ndarray,
                               impedance: LegImpedance | None) -> None:
        """p(t + dt) of D dp/dt + K p = F_n with F_n held over dt (exact); dp/dt at the end of the step.

        The penetration is the foot's sinking since its touchdown: it resets only after a swing of at least
        min_swing_s. A stance leg without a usable impedance (the TCE not confident for a while, or the
        force dropping out for a sample) holds it, and the integration goes on from there: on graph_tour's
        T1 such an interruption reset it mid-stance, the recount from zero counted the sinking so far twice
        (up to 0.1 m a step) and the estimate sank 0.2 m per metre walked (replay, measured)."""
        rate = np.zeros(NUM_LEGS)
        swing = probability < self.settings.swing_probability
        self._swing_s = np.where(swing, self._swing_s + dt, 0.0)
        self.penetration[self._swing_s >= self.settings.min_swing_s] = 0.0
        if impedance is not None and dt > 0.0:
            usable = impedance.usable(self.settings.min_confidence)
            for leg in range(NUM_LEGS):
                k, d = float(impedance.stiffness_n_per_m[leg]), float(impedance.damping_ns_per_m[leg])
                if (swing[leg] or not usable[leg] or not (math.isfinite(d) and d >= 0.0)
                        or not k >= self.settings.min_stiffness_n_per_m):
                    continue   # the modelled foot holds its sinking (rate 0)
                # An estimated damping near zero (clamped fits) would make dp/dt = (F - K p) / D explode.
                d = max(d, self.settings.min_damping_ns_per_m)
                static = normal_force[leg] / k
                p = static + (self.penetration[leg] - static) * math.exp(-k * dt / d)
                bounded = min(max(p, 0.0), self.settings.max_penetration_m)
                self.penetration[leg] = bounded
                if bounded != p:  # at a bound the modelled foot does not move
                    continue
                limit = self.settings.max_penetration_rate_m_s
                rate[leg] = float(np.clip((normal_force[leg] - k * bounded) / d, -limit, limit))
        self._penetration_rate = rate
