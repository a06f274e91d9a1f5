"""State estimator (attitude + leg odometry + KF): robot-agnostic standing, input errors, gaps, standing
initialisation and the offline replay's equivalence with hand-fed ticks."""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import cache

import numpy as np
import pytest
from tal_lab.offline_estimation import SensorArrays, run_estimator

from tal_core.errors import InputError
from tal_core.robot_model import RobotModel
from tal_core.rotations import so3_exp
from tal_estimation.leg_odometry import LegImpedance, LegOdometrySettings
from tal_estimation.state_estimator import (
    EstimatorInputError,
    StateEstimate,
    StateEstimator,
    StateEstimatorSettings,
    legs_from_impedance_arrays,
)

G = 9.81
PERIOD_S = 0.003
AT_REST = np.array([0.0, 0.0, G])  # specific force of an IMU at rest, level [m/s^2]
ZERO = np.zeros(3)
MAGNETIC_FIELD_WORLD = np.array([0.2, 0.0, -0.45])


@cache
def robot(name: str) -> RobotModel:
    return RobotModel.from_name(name)


def nominal_joints(model: RobotModel) -> np.ndarray:
    return np.asarray(model.description.nominal_joint_positions_rad, dtype=float).copy()


def standing_torques(model: RobotModel, joint_positions: np.ndarray) -> np.ndarray:
    """Joint torques [N m] holding the robot's weight equally on its four feet, level base at rest:
    tau = h_leg - J_leg^T F with F = (0, 0, m g / 4)."""
    quat = np.array([0.0, 0.0, 0.0, 1.0])
    model.update(model.make_q(np.array([0.0, 0.0, model.nominal_base_height_m]), quat, joint_positions),
                 np.zeros(model.nv))
    h = model.nonlinear_effects()
    grf = np.array([0.0, 0.0, model.total_mass_kg * G / 4.0])
    tau = np.empty(12)
    for leg in range(4):
        tau[3 * leg:3 * leg + 3] = h[model.leg_joint_v_indices(leg)] + model.leg_torques_for_foot_force(leg, grf)
    return tau


def standing_estimator(name: str = "hyq", settings: StateEstimatorSettings | None = None,
                       magnetic_field_world: np.ndarray | None = None) -> StateEstimator:
    model = robot(name)
    estimator = StateEstimator(model, settings, magnetic_field_world)
    estimator.initialise_standing(0.0, nominal_joints(model))
    return estimator


def kf_position(estimator: StateEstimator) -> np.ndarray:
    assert estimator.kf is not None
    return estimator.kf.x[:3, 0].copy()


def assert_same_estimate(a: StateEstimate, b: StateEstimate, atol: float = 0.0) -> None:
    assert a.t_s == pytest.approx(b.t_s, abs=max(atol, 1e-15))
    for field in ("position", "quat_xyzw", "linear_velocity", "angular_velocity_base", "position_covariance",
                  "velocity_covariance", "attitude_covariance", "gyro_bias"):
        np.testing.assert_allclose(getattr(a, field), getattr(b, field), rtol=0.0, atol=atol, err_msg=field)
    np.testing.assert_allclose(a.legs.force, b.legs.force, rtol=0.0, atol=atol * 1e3)


def assert_finite(estimate: StateEstimate) -> None:
    for field in ("position", "quat_xyzw", "linear_velocity", "position_covariance", "velocity_covariance",
                  "gyro_bias"):
        assert np.all(np.isfinite(getattr(estimate, field))), field


# --------------------------------------------------------------------------------------------------------
# (a) Robot agnostic: standing still
# --------------------------------------------------------------------------------------------------------
def standing_with_noisy_imu(name: str, settings: StateEstimatorSettings | None = None,
                            duration_s: float = 5.0) -> tuple[StateEstimator, StateEstimate, float]:
    """Feed ``duration_s`` of standing still (static joints, weight on four legs) with a noisy IMU at rest;
    the estimator, the last estimate and the largest distance [m] of the position from its start."""
    model = robot(name)
    joints = nominal_joints(model)
    tau = standing_torques(model, joints)
    estimator = standing_estimator(name, settings)
    start = kf_position(estimator)
    rng = np.random.default_rng(0)
    worst = 0.0
    for k in range(1, int(round(duration_s / PERIOD_S)) + 1):
        estimate = estimator.update(k * PERIOD_S, AT_REST + rng.normal(0.0, 0.01, 3), rng.normal(0.0, 5e-4, 3),
                                    joints, np.zeros(12), tau)
        worst = max(worst, float(np.linalg.norm(estimate.position - start)))
    return estimator, estimate, worst


@pytest.mark.parametrize("name", ["solo12", "hyq", "go1"])
def test_standing_still_holds_position(name: str) -> None:
    """5 s standing on four legs, IMU at rest with white noise (which alone, without the legs' velocity
    updates, moves the estimate by about 5 mm): the leg odometry keeps the position within 1 mm."""
    model = robot(name)
    estimator, estimate, worst = standing_with_noisy_imu(name)
    assert worst < 1e-3
    assert np.linalg.norm(estimate.linear_velocity) < 2e-3
    assert np.all(estimate.legs.in_contact) and estimate.legs.weight_sum == 4.0
    np.testing.assert_allclose(estimate.legs.force[:, 2], model.total_mass_kg * G / 4.0, rtol=1e-3)
    assert estimator.reinitialisations == 0


def test_standing_drifts_without_the_legs() -> None:
    """Control for the test above: the same data without leg updates (min_support unreachable) drifts."""
    _, estimate, worst = standing_with_noisy_imu("solo12", StateEstimatorSettings(min_support=10.0))
    assert worst > 2e-3  # twice the 1 mm the legs hold it to
    assert estimate.legs.weight_sum == 4.0  # the legs were there, only unused


@pytest.mark.parametrize("name", ["solo12", "hyq", "go1"])
def test_standing_without_noise_is_exact(name: str) -> None:
    """Consistent noiseless standing data leave the state exactly where it started."""
    model = robot(name)
    joints = nominal_joints(model)
    tau = standing_torques(model, joints)
    estimator = standing_estimator(name)
    start = kf_position(estimator)
    for k in range(1, 101):
        estimate = estimator.update(k * PERIOD_S, AT_REST, ZERO, joints, np.zeros(12), tau)
    np.testing.assert_allclose(estimate.position, start, atol=1e-12)
    np.testing.assert_allclose(estimate.linear_velocity, 0.0, atol=1e-12)
    np.testing.assert_allclose(estimate.quat_xyzw, [0.0, 0.0, 0.0, 1.0], atol=1e-12)


# --------------------------------------------------------------------------------------------------------
# (b) Bad input
# --------------------------------------------------------------------------------------------------------
def good_tick(k: int, name: str = "hyq") -> tuple:
    model = robot(name)
    joints = nominal_joints(model)
    return (k * PERIOD_S, AT_REST + 0.01 * math.sin(k), np.array([0.01, -0.02, 0.03]) * math.cos(k), joints,
            np.zeros(12), standing_torques(model, joints))


def replace(tick: tuple, **changes) -> tuple:
    names = ("t", "f", "w", "q", "qd", "tau")
    return tuple(changes.get(n, v) for n, v in zip(names, tick))


Corruption = Callable[[tuple, StateEstimatorSettings], tuple]
BAD_INPUTS: list[tuple[str, str, Corruption]] = [
    ("imu_nan", "specific force has NaN or inf", lambda t, s: replace(t, f=np.array([0.0, math.nan, G]))),
    ("imu_nan", "angular rate has NaN or inf", lambda t, s: replace(t, w=np.array([0.0, 0.0, math.inf]))),
    ("imu_nan", "specific force must have 3 values", lambda t, s: replace(t, f=np.zeros(4))),
    ("imu_saturated", "at or beyond its range", lambda t, s: replace(t, f=np.array([0.0, 0.0, 200.0]))),
    ("imu_saturated", "at or beyond its range",
     lambda t, s: replace(t, f=np.array([0.0, 0.0, s.accel_range_m_s2]))),  # at the range counts
    ("imu_saturated", "at or beyond its range",
     lambda t, s: replace(t, w=np.array([-s.gyro_range_rad_s, 0.0, 0.0]))),
    ("joints", "joint positions must have 12 values", lambda t, s: replace(t, q=t[3][:11])),
    ("joints", "joint velocities has NaN or inf", lambda t, s: replace(t, qd=np.full(12, math.nan))),
    ("joints", "joint torques must have 12 values", lambda t, s: replace(t, tau=np.zeros(13))),
    ("out_of_order", "is not after the previous one", lambda t, s: replace(t, t=1.5 * PERIOD_S)),  # backwards
    ("out_of_order", "is not after the previous one", lambda t, s: replace(t, t=2 * PERIOD_S)),  # same stamp
    ("out_of_order", "is not after the previous one", lambda t, s: replace(t, t=math.nan)),
]
SATURATION_SETTINGS = StateEstimatorSettings(accel_range_m_s2=160.0, gyro_range_rad_s=8.7)  # +-16 g, 500 deg/s


@pytest.mark.parametrize("reason, message, corrupt", BAD_INPUTS,
                         ids=[f"{r}-{i}" for i, (r, _, _) in enumerate(BAD_INPUTS)])
def test_bad_input_is_rejected_without_side_effects(reason: str, message: str, corrupt: Corruption) -> None:
    """The bad tick (3) raises EstimatorInputError with its reason key; it leaves no trace: the following
    valid ticks give exactly what an estimator that never saw it gives."""
    estimator = standing_estimator(settings=SATURATION_SETTINGS)
    twin = standing_estimator(settings=SATURATION_SETTINGS)
    for k in (1, 2):
        estimator.update(*good_tick(k))
        twin.update(*good_tick(k))
    with pytest.raises(EstimatorInputError, match=message) as error:
        estimator.update(*corrupt(good_tick(3), estimator.settings))
    assert error.value.reason == reason
    assert isinstance(error.value, InputError)
    for k in (3, 4):
        assert_same_estimate(estimator.update(*good_tick(k)), twin.update(*good_tick(k)))
    assert estimator.reinitialisations == 0


def test_bad_magnetometer_is_rejected_without_side_effects() -> None:
    estimator = standing_estimator(magnetic_field_world=MAGNETIC_FIELD_WORLD)
    twin = standing_estimator(magnetic_field_world=MAGNETIC_FIELD_WORLD)
    for k in (1, 2):
        estimator.update(*good_tick(k), magnetic_field=MAGNETIC_FIELD_WORLD)
        twin.update(*good_tick(k), magnetic_field=MAGNETIC_FIELD_WORLD)
    with pytest.raises(EstimatorInputError, match="magnetic field has NaN or inf") as error:
        estimator.update(*good_tick(3), magnetic_field=np.array([math.nan, 0.0, 0.0]))
    assert error.value.reason == "mag_nan"
    assert_same_estimate(estimator.update(*good_tick(3), magnetic_field=MAGNETIC_FIELD_WORLD),
                         twin.update(*good_tick(3), magnetic_field=MAGNETIC_FIELD_WORLD))


def test_update_before_initialise_is_rejected() -> None:
    estimator = StateEstimator(robot("hyq"))
    assert not estimator.initialised
    with pytest.raises(EstimatorInputError, match="call initialise") as error:
        estimator.update(*good_tick(1))
    assert error.value.reason == "not_initialised"
    estimator.initialise_standing(0.0, nominal_joints(robot("hyq")))
    assert estimator.initialised
    assert_finite(estimator.update(*good_tick(1)))


def test_bad_initial_state_is_rejected() -> None:
    estimator = StateEstimator(robot("hyq"))
    with pytest.raises(EstimatorInputError, match="initial position must have 3 values") as error:
        estimator.initialise(0.0, np.zeros(2))
    assert error.value.reason == "initial"
    with pytest.raises(EstimatorInputError, match="joint positions has NaN") as error:
        estimator.initialise_standing(0.0, np.full(12, math.nan))
    assert error.value.reason == "joints"
    assert not estimator.initialised


@pytest.mark.parametrize("kwargs, message", [
    ({"period_s": 0.0}, "period_s must be finite and > 0"),
    ({"accel_noise_m_s2": math.nan}, "accel_noise_m_s2 must be finite"),
    ({"min_support": -1.0}, "min_support must be finite and > 0"),
    ({"max_gap_periods": 0}, "max_gap_periods must be >= 1"),
])
def test_settings_reject_invalid_values(kwargs: dict, message: str) -> None:
    with pytest.raises(InputError, match=message):
        StateEstimatorSettings(**kwargs)


# --------------------------------------------------------------------------------------------------------
# (c) Gaps
# --------------------------------------------------------------------------------------------------------
def test_gap_reinitialises_velocity() -> None:
    """A gap of 6 periods is bridged; one of 25 periods (> max_gap_periods = 10) re-initialises the
    velocity filter once, keeps the position and stays finite."""
    estimator = standing_estimator()
    for k in range(1, 11):
        estimator.update(*good_tick(k))
    before = estimator.update(*good_tick(16))
    assert estimator.reinitialisations == 0
    after = estimator.update(*good_tick(16 + 25))
    assert estimator.reinitialisations == 1
    assert_finite(after)
    np.testing.assert_allclose(after.position, before.position, atol=1e-3)
    assert np.trace(after.velocity_covariance) > np.trace(before.velocity_covariance)  # forgot the velocity
    for k in range(42, 60):
        assert_finite(estimator.update(*good_tick(k)))
    assert estimator.reinitialisations == 1


def test_gap_forgets_the_velocity_but_not_the_position() -> None:
    """Without leg updates (min_support unreachable) and an IMU at rest, the initial 1 m/s is kept until
    a gap: then the velocity restarts at zero and the position does not jump over the gap."""
    model = robot("hyq")
    settings = StateEstimatorSettings(min_support=10.0)
    estimator = StateEstimator(model, settings)
    estimator.initialise(0.0, np.zeros(3), np.eye(3), velocity=np.array([1.0, 0.0, 0.0]))
    joints = nominal_joints(model)
    for k in range(1, 11):
        estimate = estimator.update(k * PERIOD_S, AT_REST, ZERO, joints, np.zeros(12), np.zeros(12))
    np.testing.assert_allclose(estimate.linear_velocity, [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(estimate.position, [10 * PERIOD_S, 0.0, 0.0], atol=1e-12)
    estimate = estimator.update(1.0, AT_REST, ZERO, joints, np.zeros(12), np.zeros(12))
    assert estimator.reinitialisations == 1
    np.testing.assert_allclose(estimate.linear_velocity, 0.0, atol=1e-12)
    np.testing.assert_allclose(estimate.position, [10 * PERIOD_S, 0.0, 0.0], atol=1e-12)


# --------------------------------------------------------------------------------------------------------
# (d) Standing initialisation
# --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["hyq", "solo12", "go1"])
def test_initialise_standing_puts_feet_on_the_ground(name: str) -> None:
    model = robot(name)
    estimator = StateEstimator(model)
    estimator.initialise_standing(2.0, nominal_joints(model))
    np.testing.assert_allclose(kf_position(estimator), [0.0, 0.0, model.nominal_base_height_m], atol=1e-6)
    if name == "hyq":
        assert kf_position(estimator)[2] == pytest.approx(0.587, abs=1e-3)
    assert estimator.t_s == 2.0
    estimator.initialise_standing(0.0, nominal_joints(model), xy=(1.5, -2.0), ground_height_m=0.25,
                                  world_R_base=so3_exp(np.array([0.0, 0.0, 1.2])))  # yaw: same height
    np.testing.assert_allclose(kf_position(estimator), [1.5, -2.0, 0.25 + model.nominal_base_height_m],
                               atol=1e-6)


def test_legs_from_impedance_arrays() -> None:
    impedance = legs_from_impedance_arrays(np.array([8e3, np.nan, 5e3, 9e3]), np.array([300.0, 300.0, np.inf, 0.0]),
                                           np.array([True, True, True, False]))
    assert isinstance(impedance, LegImpedance)
    np.testing.assert_array_equal(impedance.valid, [True, False, False, False])
    np.testing.assert_array_equal(impedance.normal, np.tile([0.0, 0.0, 1.0], (4, 1)))
    normal = np.tile([0.0, 0.6, 0.8], (4, 1))
    np.testing.assert_array_equal(legs_from_impedance_arrays(np.ones(4), np.ones(4), np.ones(4), normal).normal,
                                  normal)
    assert impedance.confidence is None and impedance.rigid is None
    gated = legs_from_impedance_arrays(np.full(4, 8e3), np.full(4, 300.0), np.ones(4, bool),
                                       confidence=np.array([0.9, 0.05, np.nan, 0.9]),
                                       rigid=np.array([False, False, False, True]))
    np.testing.assert_array_equal(gated.confidence, [0.9, 0.05, 0.0, 0.9])
    np.testing.assert_array_equal(gated.usable(0.1), [True, False, False, False])


# --------------------------------------------------------------------------------------------------------
# (e) Offline replay == hand-fed ticks
# --------------------------------------------------------------------------------------------------------
def sensor_arrays(model: RobotModel, start_s: float = 1.2, samples: int = 601) -> SensorArrays:
    """1 kHz samples of a swaying, standing robot with noisy IMU, torques and magnetometer."""
    rng = np.random.default_rng(11)
    t = start_s + np.arange(samples) * 1e-3
    phase = rng.uniform(0.0, 2.0 * math.pi, 12)
    nominal = nominal_joints(model)
    joint_position = nominal + 0.03 * np.sin(2.0 * math.pi * 1.5 * t[:, None] + phase)
    joint_velocity = 0.03 * 2.0 * math.pi * 1.5 * np.cos(2.0 * math.pi * 1.5 * t[:, None] + phase)
    joint_torque = standing_torques(model, nominal) + rng.normal(0.0, 0.5, (samples, 12))
    specific_force = AT_REST + 0.3 * np.sin(3.0 * t[:, None] + [0.0, 1.0, 2.0]) + rng.normal(0.0, 0.05, (samples, 3))
    angular_rate = 0.05 * np.sin(2.0 * t[:, None] + [0.5, 1.5, 2.5]) + rng.normal(0.0, 2e-3, (samples, 3))
    magnetic_field = MAGNETIC_FIELD_WORLD + rng.normal(0.0, 5e-3, (samples, 3))
    return SensorArrays(t, specific_force, angular_rate, joint_position, joint_velocity, joint_torque,
                        magnetic_field)


def impedance_at(t: float) -> LegImpedance:
    """A time-varying impedance, so feeding it at the wrong stamp would show."""
    return legs_from_impedance_arrays(np.full(4, 8000.0 + 3000.0 * math.sin(5.0 * t)), np.full(4, 300.0),
                                      np.array([True, True, False, True]))


@pytest.mark.parametrize("mode", ["rigid", "terrain_aware"])
@pytest.mark.parametrize("initial_position", [None, np.array([0.1, -0.2, 0.6])], ids=["standing", "given"])
def test_run_estimator_matches_hand_fed_ticks(mode: str, initial_position: np.ndarray | None) -> None:
    """run_estimator on 1 kHz arrays == StateEstimator.update on the 333 Hz grid with the means of the
    three IMU samples since the previous tick (to 1e-12)."""
    model = robot("hyq")
    sensors = sensor_arrays(model)
    settings = StateEstimatorSettings(leg_odometry=LegOdometrySettings(mode=mode))
    initial_rotation = so3_exp(np.array([0.02, -0.01, 0.3]))
    result = run_estimator(model, sensors, settings, initial_position=initial_position,
                           initial_world_R_base=initial_rotation, impedance=impedance_at,
                           magnetic_field_world=MAGNETIC_FIELD_WORLD)

    estimator = StateEstimator(model, settings, MAGNETIC_FIELD_WORLD)
    if initial_position is None:
        estimator.initialise_standing(sensors.t[0], sensors.joint_position[0], world_R_base=initial_rotation)
    else:
        estimator.initialise(sensors.t[0], initial_position, initial_rotation)
    expected = []
    for j in range(3, len(sensors.t), 3):
        group = slice(j - 2, j + 1)
        expected.append(estimator.update(
            sensors.t[j], sensors.specific_force[group].mean(axis=0), sensors.angular_rate[group].mean(axis=0),
            sensors.joint_position[j], sensors.joint_velocity[j], sensors.joint_torque[j],
            impedance=impedance_at(sensors.t[j]), magnetic_field=sensors.magnetic_field[j]))

    assert len(result.t) == len(expected) == 200
    np.testing.assert_allclose(result.t, [e.t_s for e in expected], rtol=0.0, atol=1e-12)
    for field, values in (("position", result.position), ("quat_xyzw", result.quat_xyzw),
                          ("linear_velocity", result.linear_velocity), ("gyro_bias", result.gyro_bias),
                          ("angular_velocity_base", result.angular_velocity_base)):
        np.testing.assert_allclose(values, [getattr(e, field) for e in expected], rtol=0.0, atol=1e-12,
                                   err_msg=field)
    np.testing.assert_allclose(result.force, [e.legs.force for e in expected], rtol=0.0, atol=1e-9)
    np.testing.assert_array_equal(result.contact, [e.legs.in_contact for e in expected])
    np.testing.assert_allclose(result.support, [e.legs.weight_sum for e in expected], rtol=0.0, atol=1e-12)
    # the legs did support the robot: the KF was corrected (the swaying legs disagree now and then: some gated)
    assert np.all(result.support >= settings.min_support) and np.median(result.support) >= 3.0
    assert np.all(np.isfinite(result.position))


def test_the_vertical_channel_follows_the_imu_above_its_crossover_and_the_reference_below() -> None:
    """A reference (the KF) that misses a 2 cm, 2.5 Hz bounce the IMU measures, and a reference climbing at
    0.1 m/s that the IMU does not see (its bias-free mean is zero): the channel (crossover 1 rad/s) has the
    bounce's amplitude within 5 % (a second-order high-pass leads it by 2 atan(1/15.7) = 0.13 rad) and the
    climb after a few time constants."""
    from tal_estimation.state_estimator import VerticalChannel
    dt, w_bounce = 0.003, 2 * np.pi * 2.5
    channel = VerticalChannel()
    t = np.arange(0.0, 20.0, dt)
    bounce = 0.02 * np.sin(w_bounce * t)
    out = np.array([channel.update(dt, -0.02 * w_bounce**2 * np.sin(w_bounce * ti), 0.0, 0.0, 1.0)[0] for ti in t])
    late = t > 10.0
    assert np.std(out[late]) == pytest.approx(np.std(bounce[late]), rel=0.05)
    assert np.max(np.abs(out[late] - bounce[late])) < 0.2 * 0.02
    climb = VerticalChannel()
    z = [climb.update(dt, 0.0, 0.1 * ti, 0.1, 1.0) for ti in t]
    assert z[-1][0] == pytest.approx(0.1 * t[-1], abs=1e-3) and z[-1][1] == pytest.approx(0.1, abs=1e-3)
    with pytest.raises(InputError, match="vertical_crossover_rad_s"):
        StateEstimatorSettings(vertical_crossover_rad_s=-1.0)


def test_the_velocity_gate_leaves_out_a_leg_whose_foot_still_moves() -> None:
    """One stance leg's knee turning at 1 rad/s (a landing foot still moving, 0.3-0.4 m/s at the foot) pulls the
    ungated estimate along; with leg_velocity_gate_m_s that leg is left out of the measurement and counted."""
    model = robot("hyq")
    joints = nominal_joints(model)
    tau = standing_torques(model, joints)
    qd = np.zeros(12)
    qd[11] = 1.0   # RH knee
    results = {}
    for gate in (0.0, 0.1):
        estimator = standing_estimator(settings=StateEstimatorSettings(leg_velocity_gate_m_s=gate))
        for k in range(1, 6):
            estimate = estimator.update(k * PERIOD_S, AT_REST, np.zeros(3), joints, np.zeros(12) if k < 3 else qd, tau)
        results[gate] = (float(np.linalg.norm(estimate.linear_velocity)), estimator.gated_legs,
                         float(estimate.legs.weight_sum), bool(estimate.legs.in_contact[3]))
    ungated, gated = results[0.0], results[0.1]
    assert ungated[1] == 0 and ungated[0] > 0.03
    assert gated[1] == 3 and gated[0] < 0.01          # the three ticks with the moving knee
    assert gated[2] == pytest.approx(3.0) and gated[3]  # weight from the other three legs; RH still in contact


def test_the_velocity_gate_setting_is_checked() -> None:
    with pytest.raises(InputError, match="leg_velocity_gate_m_s"):
        StateEstimatorSettings(leg_velocity_gate_m_s=-0.1)


def test_the_velocity_gate_keeps_the_legs_when_they_all_disagree_with_the_prediction() -> None:
    """An IMU that reads a push the legs do not feel (2 m/s^2 along x for 40 ticks): every leg is soon further
    than the gate from the prediction, and the legs, which agree with each other, stay the measurement."""
    model = robot("hyq")
    joints = nominal_joints(model)
    tau = standing_torques(model, joints)
    estimator = standing_estimator(settings=StateEstimatorSettings(leg_velocity_gate_m_s=0.02))
    push = AT_REST + np.array([2.0, 0.0, 0.0])
    for k in range(1, 41):
        estimate = estimator.update(k * PERIOD_S, push, np.zeros(3), joints, np.zeros(12), tau)
    assert estimator.gated_legs == 0
    assert abs(float(estimate.linear_velocity[0])) < 0.05   # 40 ticks of the push alone: 0.24 m/s
