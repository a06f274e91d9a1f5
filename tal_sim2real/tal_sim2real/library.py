"""The library of candidate effects: each one a named set of model parameters (tal_sim2real.model, i.e.
parameters of the sim_bridge), the subsystem whose residual shows it, the signals it needs, and the
experiment that would excite it when the data do not.

Subsystems: ``torque_path`` (commanded vs measured joint torque), ``imu`` (IMU vs the measured base
motion) and ``dynamics`` (open-loop segments driven by the measured torques).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Parameter:
    """One fitted parameter: model name, bounds, log scaling, screening probe and its unit (for reports)."""

    name: str
    lower: float
    upper: float
    probe: float
    log: bool = False
    unit: str = ""

    def to_internal(self, value: float) -> float:
        return math.log(value) if self.log else value

    def from_internal(self, value: float) -> float:
        return math.exp(value) if self.log else value


@dataclass(frozen=True)
class Candidate:
    """A candidate missing effect."""

    name: str
    subsystem: str
    parameters: tuple[Parameter, ...]
    required_signals: tuple[str, ...]
    experiment: str
    description: str

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)


CANDIDATES: tuple[Candidate, ...] = (
    Candidate(
        "ground",
        "dynamics",
        (
            Parameter("ground_stiffness_n_per_m", 1e3, 1e7, 3e4, True, "N/m"),
            Parameter("ground_damping_ns_per_m", 20.0, 2e4, 600.0, True, "N s/m"),
        ),
        ("joint_states.effort", "base_state"),
        "standing still and shifting weight between legs (stance penetration under known loads)",
        "Kelvin-Voigt ground (stiffness and damping per contact point)",
    ),
    Candidate(
        "ground_nonlinear",
        "dynamics",
        (
            Parameter("ground_stiffness_n_per_m", 1e3, 1e7, 3e4, True, "N/m"),
            Parameter("ground_damping_ns_per_m", 20.0, 2e4, 600.0, True, "N s/m"),
            Parameter("ground_contact_exponent", 0.7, 2.5, 1.5, False, "-"),
        ),
        ("joint_states.effort", "base_state"),
        "standing still and shifting weight between legs (stance penetration under known loads)",
        "power-law (Hunt-Crossley-type) ground: stiffness and damping grow as (sinkage / 0.01 m)^(n-1)",
    ),
    Candidate(
        "foot_friction",
        "dynamics",
        (Parameter("foot_friction", 0.05, 1.0, 0.35, False, "-"),),
        ("joint_states.effort", "base_state"),
        "a push or a slope that drives the stance feet to the edge of the friction cone",
        "foot/ground Coulomb friction coefficient",
    ),
    Candidate(
        "joint_viscous_friction",
        "dynamics",
        (Parameter("joint_viscous_friction_nms_per_rad", 0.0, 30.0, 1.0, False, "N m s/rad"),),
        ("joint_states.effort", "base_state"),
        "fast swing motions (large joint velocities)",
        "viscous joint friction",
    ),
    Candidate(
        "joint_coulomb_friction",
        "dynamics",
        (Parameter("joint_coulomb_friction_nm", 0.0, 30.0, 2.0, False, "N m"),),
        ("joint_states.effort", "base_state"),
        "slow joint reversals with small torques",
        "Coulomb joint friction",
    ),
    Candidate(
        "payload",
        "dynamics",
        (
            Parameter("payload_mass_kg", 0.0, 60.0, 5.0, False, "kg"),
            Parameter("payload_offset_x_m", -0.5, 0.5, 0.0, False, "m"),
            Parameter("payload_offset_y_m", -0.3, 0.3, 0.0, False, "m"),
        ),
        ("joint_states.effort", "base_state"),
        "standing and trotting (weight and its distribution)",
        "extra trunk mass and its centre-of-mass offset",
    ),
    Candidate(
        "actuator_delay",
        "torque_path",
        (Parameter("actuator_delay_s", 0.0, 0.05, 0.005, False, "s"),),
        ("joint_command", "joint_states.effort"),
        "fast torque changes (a gait with sharp touchdowns)",
        "transport delay of the joint torques",
    ),
    Candidate(
        "actuator_lag",
        "torque_path",
        (Parameter("actuator_lag_s", 0.0, 0.05, 0.005, False, "s"),),
        ("joint_command", "joint_states.effort"),
        "fast torque changes (a gait with sharp touchdowns)",
        "first-order lag of the joint torques",
    ),
    Candidate(
        "torque_gain",
        "torque_path",
        (Parameter("torque_gain", 0.3, 2.0, 0.9, False, "-"),),
        ("joint_command", "joint_states.effort"),
        "any motion with non-zero torques",
        "delivered/commanded torque gain",
    ),
    Candidate(
        "torque_limit",
        "torque_path",
        (Parameter("torque_limit_scale", 0.05, 1.0, 0.5, False, "-"),),
        ("joint_command", "joint_states.effort"),
        "a motion whose commanded torques approach the nominal limits (jumps, stairs, heavy payload)",
        "reduced joint torque limits",
    ),
    Candidate(
        "imu_bias",
        "imu",
        tuple(Parameter(f"imu_gyro_bias_{a}_rad_s", -1.0, 1.0, 0.0, False, "rad/s") for a in "xyz")
        + tuple(Parameter(f"imu_accel_bias_{a}_m_s2", -5.0, 5.0, 0.0, False, "m/s^2") for a in "xyz"),
        ("imu", "base_state"),
        "any recording with ground truth (or a static period)",
        "constant gyroscope and accelerometer biases",
    ),
)
CANDIDATES_BY_NAME = {c.name: c for c in CANDIDATES}


LEGS = ("LF", "RF", "LH", "RH")


@dataclass(frozen=True)
class Variant:
    """A per-leg or per-joint version of an effect whose physics is per actuator or per sensor (issue 34,
    item 3). It is tried only where the remainder of the chosen model points (the leg or joint holding most
    of the excess), and chosen over the global effect only when an information criterion that charges for
    the extra parameters says so: a global effect stays global.

    ``template`` is the parameter with ``{}`` where the leg (``lf``) or joint (``lh_kfe``) goes; ``base``
    the global candidate it refines ("" for none). These parameters are not sim_bridge parameters (its
    effects are global): a named variant is reported, not written into the updated model."""

    name: str
    base: str
    scope: str  # "leg" | "joint"
    subsystem: str
    template: Parameter
    description: str

    def parameter(self, where: str) -> Parameter:
        t = self.template
        return Parameter(t.name.format(where.lower()), t.lower, t.upper, t.probe, t.log, t.unit)

    def candidate(self, where: str) -> Candidate:
        """The variant at ``where`` (a leg such as "RF" or a joint such as "lh_kfe") as a one-parameter
        candidate named ``<name>``."""
        base = CANDIDATES_BY_NAME.get(self.base)
        return Candidate(
            self.name,
            self.subsystem,
            (self.parameter(where),),
            base.required_signals if base else ("joint_states.effort", "base_state"),
            base.experiment if base else "any motion",
            f"{self.description} ({where})",
        )


VARIANTS: tuple[Variant, ...] = (
    Variant(
        "leg_torque_gain",
        "torque_gain",
        "leg",
        "torque_path",
        Parameter("torque_gain_{}", 0.3, 2.0, 0.9, False, "-"),
        "delivered/commanded torque gain of one leg's actuators",
    ),
    Variant(
        "leg_actuator_delay",
        "actuator_delay",
        "leg",
        "torque_path",
        Parameter("actuator_delay_{}_s", 0.0, 0.05, 0.005, False, "s"),
        "transport delay of one leg's joint torques",
    ),
    Variant(
        "leg_torque_sensor_gain",
        "",
        "leg",
        "torque_path",
        Parameter("torque_sensor_gain_{}", 0.3, 2.0, 0.9, False, "-"),
        "gain of one leg's torque sensors (measured/delivered): the torque path sees it as the leg's torque "
        "gain, the dynamics driven by the measured torques tells it apart (the delivered torque is the "
        "measured one divided by it)",
    ),
    Variant(
        "encoder_offset",
        "",
        "joint",
        "dynamics",
        Parameter("encoder_offset_{}_rad", -0.3, 0.3, 0.03, False, "rad"),
        "constant offset of one joint's encoder (measured - true angle)",
    ),
    Variant(
        "leg_link_mass",
        "payload",
        "leg",
        "dynamics",
        Parameter("link_mass_{}_kg", -0.5, 10.0, 0.5, False, "kg"),
        "extra mass at the centre of mass of one leg's lower link (a sensor, a clamp, mud; the trunk's payload "
        "is the global effect)",
    ),
)
VARIANTS_BY_NAME = {v.name: v for v in VARIANTS}


def where_of(parameter_name: str, variant: Variant) -> str:
    """The leg ("RF") or joint ("lh_kfe") a variant parameter name refers to."""
    head, _, tail = variant.template.name.partition("{}")
    core = parameter_name[len(head) : len(parameter_name) - len(tail)]
    return core.upper() if variant.scope == "leg" else core


def missing_signals(candidate: Candidate, available: set[str]) -> list[str]:
    """Signals the candidate needs that the data lack."""
    return [s for s in candidate.required_signals if s not in available]
