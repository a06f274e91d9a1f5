"""Leg odometry on kinematically exact synthetic data: rigid (thesis) and terrain aware, HyQ and Solo12."""

from __future__ import annotations

import math
from dataclasses import dataclass
from dataclasses import replace as dataclass_replace
from functools import cache

import numpy as np
import pinocchio as pin
import pytest

from tal_core.errors import InputError
from tal_core.robot_model import RobotModel
from tal_core.rotations import quat_xyzw_from_rotation, so3_exp
from tal_estimation.leg_odometry import LegImpedance, LegOdometry, LegOdometrySettings

G = 9.81
DT_S = 0.003
ROBOTS = ("hyq", "solo12", "go1")


@cache
def robot(name: str) -> RobotModel:
    return RobotModel.from_name(name)


@dataclass(frozen=True)
class Sample:
    """Joint velocities [rad/s] and torques [N m] (canonical order) that realise the requested motion, and
    the resulting foot-sphere centre velocities [m/s] and foot-link angular velocities [rad/s], world."""

    qd: np.ndarray
    tau: np.ndarray
    centre_velocity: np.ndarray
    foot_angular_velocity: np.ndarray


def foot_angular_velocities(model: RobotModel) -> np.ndarray:
    """(4, 3) angular velocities [rad/s], world axes, of the frames at the feet, at the last update."""
    return np.array([pin.getFrameVelocity(model.model, model.data, model.model.getFrameId(name),
                                          pin.ReferenceFrame.LOCAL_WORLD_ALIGNED).angular
                     for name in model.description.foot_frames])


def make_sample(model: RobotModel, world_R_base: np.ndarray, base_position: np.ndarray,
                base_velocity: np.ndarray, angular_velocity: np.ndarray, joint_positions: np.ndarray,
                foot_velocity: dict[int, np.ndarray], foot_force: np.ndarray,
                free_joint_velocities: np.ndarray, rolling_normals: np.ndarray | None = None) -> Sample:
    """Joint velocities and torques for a base twist (base_velocity, angular_velocity, world frame).

    The legs listed in ``foot_velocity`` are solved (full base state, leg Jacobians) so that a point of
    the foot moves at the given world velocity: the foot-sphere centre (the foot frame) when
    ``rolling_normals`` is None, else the sphere's contact point centre - radius n (a sphere rolling on a
    ground of normal n). The other legs get ``free_joint_velocities``. Torques make the leg's joint rows of
    the dynamics hold with ground reaction force ``foot_force[leg]`` (world, on the foot) for a base moving
    at a constant world velocity and zero joint accelerations: tau = h_leg - J_leg^T F."""
    quat = quat_xyzw_from_rotation(world_R_base)
    q = model.make_q(base_position, quat, joint_positions)
    radius = model.description.foot_radius_m

    def point_velocities(qd: np.ndarray) -> np.ndarray:
        model.update(q, model.make_v(base_velocity, angular_velocity, qd, quat))
        centre = model.foot_velocities().copy()
        if rolling_normals is None:
            return centre
        return centre - radius * np.cross(foot_angular_velocities(model), rolling_normals)

    # The point velocities are affine in the joint velocities, and each leg's only in its own joints.
    base_part = point_velocities(np.zeros(12))
    columns = []
    for j in range(3):
        unit = np.zeros(12)
        unit[[3 * leg + j for leg in foot_velocity]] = 1.0
        columns.append(point_velocities(unit) - base_part)
    qd = np.array(free_joint_velocities, dtype=float)
    for leg, target in foot_velocity.items():
        jacobian = np.stack([c[leg] for c in columns], axis=1)
        qd[3 * leg:3 * leg + 3] = np.linalg.solve(jacobian, target - base_part[leg])
    achieved = point_velocities(qd)
    for leg, target in foot_velocity.items():
        np.testing.assert_allclose(achieved[leg], target, atol=1e-12)
    v = model.make_v(base_velocity, angular_velocity, qd, quat)
    model.update(q, v)
    # Pinocchio's base velocity is in the base frame, so "zero acceleration" of v would accelerate the base
    # by w x v in the world; add M a for the base acceleration that keeps its world velocity constant.
    acceleration = np.zeros(model.nv)
    acceleration[0:3] = -np.cross(v[3:6], v[0:3])
    h = model.nonlinear_effects() + model.mass_matrix() @ acceleration
    tau = np.empty(12)
    for leg in range(4):
        tau[3 * leg:3 * leg + 3] = (h[model.leg_joint_v_indices(leg)]
                                    + model.leg_torques_for_foot_force(leg, foot_force[leg]))
    return Sample(qd, tau, model.foot_velocities().copy(), foot_angular_velocities(model))


BASE_ROTATION = so3_exp(np.array([0.1, -0.05, 0.7]))
BASE_VELOCITY = np.array([0.4, -0.1, 0.05])
ANGULAR_VELOCITY = np.array([0.1, -0.2, 0.3])


def joint_positions(model: RobotModel, seed: int = 1) -> np.ndarray:
    """Nominal stance with a few degrees of perturbation (a generic, non-symmetric configuration)."""
    return model.description.nominal_joint_positions_rad + np.random.default_rng(seed).normal(0.0, 0.1, 12)


# --------------------------------------------------------------------------------------------------------
# Rigid leg odometry (the thesis)
# --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ROBOTS)
@pytest.mark.parametrize("stance", [(0, 3), (1, 2), (0, 1, 2), (0, 1, 2, 3)], ids=str)
def test_rigid_recovers_base_velocity_and_stance_legs(name: str, stance: tuple[int, ...]) -> None:
    """Static stance feet, moving swing feet with ~zero force: exact base velocity, exact contact flags."""
    model = robot(name)
    weight = model.total_mass_kg * G
    odometry = LegOdometry(model)
    rng = np.random.default_rng(len(stance))
    force = np.zeros((4, 3))
    for leg in range(4):
        if leg in stance:
            force[leg] = weight / len(stance) * np.array([0.05, -0.03, 1.0])
        else:
            force[leg] = 0.01 * odometry.threshold_n * rng.normal(size=3) / math.sqrt(3.0)
    qj = joint_positions(model)
    sample = make_sample(model, BASE_ROTATION, np.array([0.3, -0.2, model.nominal_base_height_m]),
                         BASE_VELOCITY, ANGULAR_VELOCITY, qj, {leg: np.zeros(3) for leg in stance}, force,
                         free_joint_velocities=rng.uniform(-3.0, 3.0, 12))
    out = odometry.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, sample.tau)

    np.testing.assert_allclose(out.base_velocity, BASE_VELOCITY, atol=1e-9)
    expected_contact = np.array([leg in stance for leg in range(4)])
    np.testing.assert_array_equal(out.in_contact, expected_contact)
    np.testing.assert_array_equal(out.probability, expected_contact.astype(float))
    assert out.weight_sum == len(stance)
    np.testing.assert_allclose(out.force, force, atol=1e-9 * weight)
    for leg in stance:
        np.testing.assert_allclose(out.leg_velocity[leg], BASE_VELOCITY, atol=1e-9)
    for leg in set(range(4)) - set(stance):  # a swinging foot reads nonsense, which must not leak in
        assert np.linalg.norm(out.leg_velocity[leg] - BASE_VELOCITY) > 0.05
    np.testing.assert_array_equal(out.foot_velocity, 0.0)
    np.testing.assert_array_equal(out.penetration, 0.0)


def test_threshold_scales_with_robot_weight() -> None:
    """Robot agnostic: the contact threshold is a fraction of m g (85 N for HyQ, 2.5 N for Solo12), so
    Solo12's stance forces (~6-12 N) count as contact although they are far below HyQ's threshold."""
    thresholds = {}
    for name in ROBOTS:
        model = robot(name)
        odometry = LegOdometry(model, LegOdometrySettings(contact_threshold_weight_fraction=0.1))
        assert odometry.threshold_n == pytest.approx(0.1 * model.total_mass_kg * G, rel=1e-12)
        thresholds[name] = odometry.threshold_n
    assert thresholds["hyq"] == pytest.approx(85.1, abs=0.1)
    assert thresholds["hyq"] / thresholds["solo12"] == pytest.approx(
        robot("hyq").total_mass_kg / robot("solo12").total_mass_kg, rel=1e-12)
    assert LegOdometry(robot("hyq"), LegOdometrySettings(contact_threshold_weight_fraction=0.2)).threshold_n \
        == pytest.approx(2.0 * thresholds["hyq"], rel=1e-12)


@pytest.mark.parametrize("mode", ["rigid", "terrain_aware"])
def test_no_support_gives_nan_velocity(mode: str) -> None:
    model = robot("hyq")
    qj = joint_positions(model)
    sample = make_sample(model, BASE_ROTATION, np.zeros(3), BASE_VELOCITY, ANGULAR_VELOCITY, qj, {},
                         np.zeros((4, 3)), free_joint_velocities=np.full(12, 0.5))
    out = LegOdometry(model, LegOdometrySettings(mode=mode)).update(
        DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, sample.tau)
    assert out.weight_sum == 0.0
    assert np.all(np.isnan(out.base_velocity))
    assert not np.any(out.in_contact)


# --------------------------------------------------------------------------------------------------------
# Terrain-aware leg odometry
# --------------------------------------------------------------------------------------------------------
STIFFNESS_N_PER_M = 10000.0
DAMPING_NS_PER_M = 3000.0
SINK_RATE_M_S = 0.05


def tilted_normals() -> np.ndarray:
    """(4, 3) unit ground normals, slightly different per leg (not all world z)."""
    n = np.array([[0.1, 0.05, 1.0], [-0.08, 0.0, 1.0], [0.0, -0.1, 1.0], [0.05, 0.05, 1.0]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def tangent(normal: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The part of ``direction`` orthogonal to ``normal`` (a friction force)."""
    return direction - (direction @ normal) * normal


def test_terrain_aware_reads_sinking_feet_better_than_rigid() -> None:
    """Swing, then touchdown at t = 0 on a Kelvin-Voigt ground into which all four feet sink at a constant
    rate (the foot spheres rolling, their contact points moving only along -n) while the base moves and
    turns. With the normal force of that model (F_n = K p + D dp/dt, p = rate t) the terrain-aware
    odometry reads the base velocity; the rigid one reads base - foot-centre velocity (sinking + rolling)."""
    model = robot("hyq")
    normals = tilted_normals()
    impedance = LegImpedance(np.full(4, STIFFNESS_N_PER_M), np.full(4, DAMPING_NS_PER_M), normals,
                             np.ones(4, dtype=bool))
    terrain = LegOdometry(model, LegOdometrySettings(mode="terrain_aware", use_leg_inertia=False))
    rigid = LegOdometry(model, LegOdometrySettings(mode="rigid"))
    base_velocity = np.array([0.3, 0.05, -0.02])
    angular_velocity = np.array([0.05, -0.03, 0.1])
    rotation_0 = so3_exp(np.array([0.05, -0.02, 0.3]))
    qj = model.description.nominal_joint_positions_rad.copy()
    rng = np.random.default_rng(2)

    for k in range(-5, 0):  # swing: no force, feet moving
        rotation = so3_exp(angular_velocity * k * DT_S) @ rotation_0
        sample = make_sample(model, rotation, np.zeros(3), base_velocity, angular_velocity, qj, {},
                             np.zeros((4, 3)), free_joint_velocities=rng.uniform(-2.0, 2.0, 12))
        out = terrain.update(DT_S, rotation, angular_velocity, qj, sample.qd, sample.tau, impedance=impedance)
        assert out.weight_sum == 0.0 and np.all(out.probability == 0.0)
        np.testing.assert_array_equal(out.penetration, 0.0)

    terrain_errors, rigid_errors = [], []
    for k in range(1, 101):
        t = k * DT_S
        rotation = so3_exp(angular_velocity * t) @ rotation_0
        penetration = SINK_RATE_M_S * t
        normal_force = STIFFNESS_N_PER_M * penetration + DAMPING_NS_PER_M * SINK_RATE_M_S
        force = np.array([normal_force * n + tangent(n, np.array([15.0, -10.0, 0.0])) for n in normals])
        contact_points = {leg: -SINK_RATE_M_S * normals[leg] for leg in range(4)}
        sample = make_sample(model, rotation, np.zeros(3), base_velocity, angular_velocity, qj, contact_points,
                             force, free_joint_velocities=np.zeros(12), rolling_normals=normals)
        out_t = terrain.update(DT_S, rotation, angular_velocity, qj, sample.qd, sample.tau, impedance=impedance)
        out_r = rigid.update(DT_S, rotation, angular_velocity, qj, sample.qd, sample.tau, impedance=impedance)
        qj = qj + sample.qd * DT_S

        np.testing.assert_allclose(out_t.force, force, atol=1e-6)
        np.testing.assert_array_equal(out_t.probability, 1.0)
        assert np.all(out_t.in_contact) and out_t.weight_sum == 4.0
        # rigid takes the foot centres for still: it reads base - their mean velocity, exactly
        np.testing.assert_allclose(out_r.base_velocity, base_velocity - sample.centre_velocity.mean(axis=0),
                                   atol=1e-9)
        # the modelled penetration follows p = rate t (ZOH of the force: within one step of sinking)
        np.testing.assert_allclose(out_t.penetration, penetration, atol=SINK_RATE_M_S * DT_S)
        terrain_errors.append(np.linalg.norm(out_t.base_velocity - base_velocity))
        rigid_errors.append(np.linalg.norm(out_r.base_velocity - base_velocity))

    terrain_errors, rigid_errors = np.array(terrain_errors), np.array(rigid_errors)
    assert np.all(rigid_errors > 0.8 * SINK_RATE_M_S)
    assert np.max(terrain_errors) < 0.05 * np.min(rigid_errors)
    assert np.mean(terrain_errors) < 0.02 * np.mean(rigid_errors)


def test_terrain_aware_accounts_for_rolling_feet() -> None:
    """Rigid ground (no impedance), the base turning fast: the foot spheres roll, their centres move by
    radius w_foot x n. Terrain aware reads the base velocity exactly; rigid is off by the rolling."""
    model = robot("hyq")
    weight = model.total_mass_kg * G
    force = np.tile([0.0, 0.0, weight / 4], (4, 1))
    qj = joint_positions(model)
    angular_velocity = np.array([0.8, -1.2, 0.5])
    sample = make_sample(model, BASE_ROTATION, np.zeros(3), BASE_VELOCITY, angular_velocity, qj,
                         {leg: np.zeros(3) for leg in range(4)}, force, free_joint_velocities=np.zeros(12),
                         rolling_normals=np.tile([0.0, 0.0, 1.0], (4, 1)))
    terrain = LegOdometry(model, LegOdometrySettings(mode="terrain_aware", use_leg_inertia=False))
    out = terrain.update(DT_S, BASE_ROTATION, angular_velocity, qj, sample.qd, sample.tau)
    np.testing.assert_allclose(out.base_velocity, BASE_VELOCITY, atol=1e-9)
    np.testing.assert_allclose(out.foot_velocity, sample.centre_velocity, atol=1e-9)
    rolling = model.description.foot_radius_m * np.linalg.norm(sample.foot_angular_velocity[:, :2], axis=1)
    assert np.all(rolling > 1e-3)  # the rolling is not negligible in this test
    out_r = LegOdometry(model).update(DT_S, BASE_ROTATION, angular_velocity, qj, sample.qd, sample.tau)
    assert np.linalg.norm(out_r.base_velocity - BASE_VELOCITY) > 1e-3


def test_swing_legs_get_exactly_zero_weight() -> None:
    """Terrain aware: a leg without force has probability exactly 0, so its (large) velocity reading
    cannot leak into the average; the base velocity comes from the stance legs alone."""
    model = robot("hyq")
    odometry = LegOdometry(model, LegOdometrySettings(mode="terrain_aware", use_leg_inertia=False))
    weight = model.total_mass_kg * G
    stance = (0, 3)
    force = np.zeros((4, 3))
    force[list(stance)] = [0.0, 0.0, weight / 2]
    qj = joint_positions(model)
    sample = make_sample(model, BASE_ROTATION, np.zeros(3), BASE_VELOCITY, ANGULAR_VELOCITY, qj,
                         {leg: np.zeros(3) for leg in stance}, force, free_joint_velocities=np.full(12, 4.0),
                         rolling_normals=np.tile([0.0, 0.0, 1.0], (4, 1)))
    out = odometry.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, sample.tau)  # no impedance
    np.testing.assert_array_equal(out.probability, [1.0, 0.0, 0.0, 1.0])
    assert out.weight_sum == 2.0
    np.testing.assert_allclose(out.base_velocity, BASE_VELOCITY, atol=1e-9)
    for leg in (1, 2):
        assert np.linalg.norm(out.leg_velocity[leg] - BASE_VELOCITY) > 0.05
    np.testing.assert_array_equal(out.penetration, 0.0)  # without an impedance the ground is rigid


def standing_on_four_feet():
    """HyQ (model, joint positions, sample) with a quarter of its weight on each static foot."""
    model = robot("hyq")
    force = np.tile([0.0, 0.0, model.total_mass_kg * G / 4], (4, 1))
    qj = joint_positions(model)
    sample = make_sample(model, BASE_ROTATION, np.zeros(3), BASE_VELOCITY, ANGULAR_VELOCITY, qj,
                         {leg: np.zeros(3) for leg in range(4)}, force, free_joint_velocities=np.zeros(12),
                         rolling_normals=np.tile([0.0, 0.0, 1.0], (4, 1)))
    return model, qj, sample


def test_a_stance_interruption_holds_the_sinking_and_a_swing_resets_it() -> None:
    """The modelled penetration is the foot's sinking since touchdown. A tick whose impedance is unusable (the
    TCE's confidence dips) or whose force drops out for a sample holds it and the integration goes on from
    there; resetting it mid-stance made the recount from zero count the sinking so far twice (on graph_tour's
    T1, up to 0.1 m a step and 0.2 m of z per metre walked). Only a swing of min_swing_s resets it."""
    model, qj, loaded = standing_on_four_feet()
    unloaded = make_sample(model, BASE_ROTATION, np.zeros(3), BASE_VELOCITY, ANGULAR_VELOCITY, qj, {},
                           np.zeros((4, 3)), free_joint_velocities=np.zeros(12))
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    usable = LegImpedance(np.full(4, 1e4), np.full(4, 3e3), normals, np.ones(4, bool), confidence=np.ones(4))
    doubtful = LegImpedance(np.full(4, 1e4), np.full(4, 3e3), normals, np.ones(4, bool), confidence=np.zeros(4))
    settings = LegOdometrySettings(mode="terrain_aware", use_leg_inertia=False, min_swing_s=0.02)
    odometry = LegOdometry(model, settings)

    def tick(sample, impedance):
        return odometry.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, sample.tau, impedance=impedance)

    for _ in range(20):
        sunk = tick(loaded, usable).penetration.copy()
    assert np.all(sunk > 1e-3)
    held = tick(loaded, doubtful)                                   # confidence dips for a tick: held
    np.testing.assert_array_equal(held.penetration, sunk)
    np.testing.assert_allclose(held.foot_velocity, loaded.centre_velocity, atol=1e-9)   # rolling only
    resumed = tick(loaded, usable).penetration
    assert np.all(resumed > sunk)                                   # from the held value, not from zero
    dropped = tick(unloaded, usable)                                 # one sample without force: held
    assert np.all(dropped.probability == 0.0)
    np.testing.assert_array_equal(dropped.penetration, resumed)
    for _ in range(round(settings.min_swing_s / DT_S) + 1):           # a swing: reset
        out = tick(unloaded, usable)
    np.testing.assert_array_equal(out.penetration, 0.0)
    with pytest.raises(InputError, match="min_swing_s"):
        LegOdometrySettings(min_swing_s=-1.0)


def test_invalid_impedance_is_treated_as_rigid() -> None:
    """Legs whose impedance is flagged invalid or has K <= 0 or D < 0 get no sinking (rolling only);
    a valid soft leg loaded by a static force starts sinking."""
    model, qj, sample = standing_on_four_feet()
    invalid = LegImpedance(np.array([1e4, 0.0, 1e4, 1e4]), np.array([3e3, 3e3, -1.0, 3e3]),
                           np.tile([0.0, 0.0, 1.0], (4, 1)), np.array([False, True, True, True]))
    odometry = LegOdometry(model, LegOdometrySettings(mode="terrain_aware", use_leg_inertia=False))
    for _ in range(3):
        out = odometry.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, sample.tau,
                              impedance=invalid)
    np.testing.assert_allclose(out.foot_velocity[:3], sample.centre_velocity[:3], atol=1e-9)
    np.testing.assert_array_equal(out.penetration[:3], 0.0)
    assert out.penetration[3] > 0.0
    assert out.foot_velocity[3, 2] - sample.centre_velocity[3, 2] < -1e-3  # sinking


def test_contact_probability_is_a_smoothstep_of_the_threshold() -> None:
    odometry = LegOdometry(robot("hyq"), LegOdometrySettings(mode="terrain_aware"))
    threshold, width = odometry.threshold_n, 0.5 * odometry.threshold_n
    assert odometry.contact_probability(np.array([0.0]))[0] == 0.0
    np.testing.assert_allclose(
        odometry.contact_probability(np.array([threshold - width, threshold, threshold + width, 1e5])),
        [0.0, 0.5, 1.0, 1.0], atol=1e-12)
    forces = np.linspace(0.0, 3.0 * threshold, 301)
    probability = odometry.contact_probability(forces)
    assert np.all(np.diff(probability) >= 0.0)
    assert np.all((probability >= 0.0) & (probability <= 1.0))
    np.testing.assert_array_equal(probability[forces <= threshold - width], 0.0)


# --------------------------------------------------------------------------------------------------------
# Settings validation
# --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs, message", [
    ({"mode": "soft"}, "mode must be one of"),
    ({"mode": "Rigid"}, "mode must be one of"),
    ({"contact_threshold_weight_fraction": 0.0}, "contact_threshold_weight_fraction must be in"),
    ({"contact_threshold_weight_fraction": 1.5}, "contact_threshold_weight_fraction must be in"),
    ({"probability_width_fraction": 1.0}, "probability_width_fraction must be in"),
    ({"swing_probability": math.nan}, "swing_probability must be in"),
])
def test_settings_reject_invalid_values(kwargs: dict, message: str) -> None:
    with pytest.raises(InputError, match=message):
        LegOdometrySettings(**kwargs)


def test_a_damping_fit_clamped_to_zero_cannot_make_the_sinking_rate_explode() -> None:
    """The TCE reports D = 0 when its damping fit is clamped: the sinking model floors D and bounds the rate
    (an unbounded (F - K p) / D read a 300 N foot as sinking at hundreds of m/s and threw HyQ over)."""
    model, qj, sample = standing_on_four_feet()
    undamped = LegImpedance(np.full(4, 1e4), np.zeros(4), np.tile([0.0, 0.0, 1.0], (4, 1)), np.ones(4, bool))
    settings = LegOdometrySettings(mode="terrain_aware", use_leg_inertia=False)
    odometry = LegOdometry(model, settings)
    out = odometry.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, sample.tau, impedance=undamped)
    sinking = sample.centre_velocity[:, 2] - out.foot_velocity[:, 2]
    assert np.all(sinking > 0.0) and np.all(sinking <= settings.max_penetration_rate_m_s + 1e-9)
    assert np.all(np.isfinite(out.base_velocity))


def test_an_implausibly_soft_stiffness_is_ignored_and_the_sinking_is_bounded() -> None:
    """A TCE fit clamped at 100 N/m read a 210 N foot as 2 m deep: replaying the STANCE course, the
    estimate sank 87 m. Below min_stiffness the leg counts as rigid; the sinking is capped per foot."""
    model, qj, sample = standing_on_four_feet()
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    settings = LegOdometrySettings(mode="terrain_aware", use_leg_inertia=False, max_penetration_m=0.1)
    reference = LegOdometry(model, settings)
    for _ in range(50):
        rigid = reference.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, sample.tau, impedance=None)
    clamped = LegImpedance(np.full(4, 100.0), np.full(4, 400.0), normals, np.ones(4, bool))
    odometry = LegOdometry(model, settings)
    for _ in range(50):
        out = odometry.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, sample.tau, impedance=clamped)
    np.testing.assert_allclose(out.penetration, 0.0)
    np.testing.assert_allclose(out.foot_velocity, rigid.foot_velocity, atol=1e-9)  # as on rigid ground
    soft = LegImpedance(np.full(4, 1000.0), np.full(4, 50.0), normals, np.ones(4, bool))  # F/K = 0.21 m
    odometry = LegOdometry(model, settings)
    for _ in range(400):
        out = odometry.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, sample.tau, impedance=soft)
    np.testing.assert_allclose(out.penetration, 0.1)
    # At the cap the modelled foot neither sinks nor (sunk deeper than its radius) rolls.
    np.testing.assert_allclose(out.foot_velocity, 0.0, atol=1e-12)


def test_unconfident_or_rigid_impedance_models_no_sinking() -> None:
    """The TCE's confidence and rigid flag gate the sinking model: on graph_tour the odometry sank feet by
    F / K from the TCE's rigid lower bound (~1e5 N/m) and from unconfident soft fits, and the estimate ran
    away (replay: -0.5 m of z per m on rigid ground). Legs 0 (confidence below min_confidence) and 1
    (flagged rigid) are treated as rigid; leg 2 (confident) and leg 3 (no confidence given) sink."""
    model, qj, sample = standing_on_four_feet()
    impedance = LegImpedance(np.full(4, 1e4), np.full(4, 3e3), np.tile([0.0, 0.0, 1.0], (4, 1)), np.ones(4, bool),
                             confidence=np.array([0.05, 0.9, 0.9, 1.0]), rigid=np.array([False, True, False, False]))
    settings = LegOdometrySettings(mode="terrain_aware", use_leg_inertia=False, min_confidence=0.1)
    odometry = LegOdometry(model, settings)
    for _ in range(3):
        out = odometry.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, sample.tau, impedance=impedance)
    np.testing.assert_array_equal(out.penetration[:2], 0.0)
    np.testing.assert_allclose(out.foot_velocity[:2], sample.centre_velocity[:2], atol=1e-9)
    assert np.all(out.penetration[2:] > 0.0)
    assert np.all(out.foot_velocity[2:, 2] - sample.centre_velocity[2:, 2] < -1e-3)  # sinking
    np.testing.assert_array_equal(impedance.usable(0.1), [False, False, True, True])
    with pytest.raises(InputError, match="min_confidence"):
        LegOdometrySettings(min_confidence=1.5)


# --------------------------------------------------------------------------------------------------------
# Contact from sensors at the feet (force sensors, binary flags): no joint torques needed
# --------------------------------------------------------------------------------------------------------
SCALE = np.array([0.5, 0.4, 0.6, 0.55])    # [N per count] a per-leg calibration (synthetic)
OFFSET = np.array([20.0, 35.0, 10.0, 0.0])  # [counts] unloaded readings (synthetic)


def counts(force_n: np.ndarray) -> np.ndarray:
    """Raw sensor counts that the calibration above turns into ``force_n`` [N]."""
    return np.asarray(force_n, float) / SCALE + OFFSET


@pytest.mark.parametrize("source", ["force_sensor", "contact_flags"])
@pytest.mark.parametrize("stance", [(0, 3), (0, 1, 2, 3)], ids=str)
def test_sensed_contact_recovers_base_velocity_without_torques(source: str, stance: tuple[int, ...]) -> None:
    """Same motion as the rigid torque test, contact from the feet's sensors and no torques at all."""
    model = robot("hyq")
    weight = model.total_mass_kg * G
    settings = LegOdometrySettings(contact_source=source, foot_force_scale=tuple(SCALE),
                                   foot_force_offset=tuple(OFFSET))
    odometry = LegOdometry(model, settings)
    force = np.zeros((4, 3))
    for leg in stance:
        force[leg] = weight / len(stance) * np.array([0.0, 0.0, 1.0])
    rng = np.random.default_rng(3)
    qj = joint_positions(model)
    sample = make_sample(model, BASE_ROTATION, np.zeros(3), BASE_VELOCITY, ANGULAR_VELOCITY, qj,
                         {leg: np.zeros(3) for leg in stance}, force, free_joint_velocities=rng.uniform(-3, 3, 12))
    stance_flags = np.array([leg in stance for leg in range(4)])
    sensor = counts(force[:, 2]) if source == "force_sensor" else stance_flags.astype(float)
    out = odometry.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, None, foot_contact=sensor)
    np.testing.assert_allclose(out.base_velocity, BASE_VELOCITY, atol=1e-9)
    np.testing.assert_array_equal(out.in_contact, stance_flags)
    assert out.weight_sum == len(stance)
    if source == "force_sensor":
        np.testing.assert_allclose(out.force, force, atol=1e-9 * weight)  # calibrated, along the normal
    else:  # flags: each stance foot carries its share of the weight
        np.testing.assert_allclose(out.force[:, 2], np.where(stance_flags, weight / len(stance), 0.0))


def test_force_sensor_contact_has_hysteresis() -> None:
    """On above the threshold, held until below (1 - hysteresis) x threshold; a force between the two does
    not start a contact. Terrain aware: the probability ramps between the thresholds while in contact."""
    model, qj, sample = standing_on_four_feet()
    settings = LegOdometrySettings(contact_source="force_sensor", contact_hysteresis_fraction=0.4,
                                   foot_force_scale=tuple(SCALE), foot_force_offset=tuple(OFFSET))
    odometry = LegOdometry(model, settings)
    on = odometry.threshold_n
    off = 0.6 * on
    middle = 0.5 * (on + off)
    sequence = [0.0, middle, 1.1 * on, middle, 0.9 * off, middle, 1.1 * on]
    expected = [False, False, True, True, False, False, True]
    seen = []
    for force_n in sequence:
        out = odometry.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, None,
                              foot_contact=counts(np.full(4, force_n)))
        seen.append(bool(out.in_contact[0]))
        assert np.all(out.in_contact == out.in_contact[0])
    assert seen == expected
    aware = LegOdometry(model, dataclass_replace(settings, mode="terrain_aware"))
    probabilities = [aware.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, None,
                                  foot_contact=counts(np.full(4, f))).probability[0] for f in sequence]
    np.testing.assert_allclose(probabilities, [0.0, 0.0, 1.0, 0.5, 0.0, 0.0, 1.0], atol=1e-12)


def test_terrain_aware_sinking_from_force_sensors() -> None:
    """A soft leg sinks from the sensed force as it does from the torque-derived one (no leg inertia)."""
    model, qj, sample = standing_on_four_feet()
    impedance = LegImpedance(np.full(4, 1e4), np.full(4, 3e3), np.tile([0.0, 0.0, 1.0], (4, 1)), np.ones(4, bool))
    by_torque = LegOdometry(model, LegOdometrySettings(mode="terrain_aware", use_leg_inertia=False))
    by_sensor = LegOdometry(model, LegOdometrySettings(mode="terrain_aware", contact_source="force_sensor"))
    for _ in range(5):
        a = by_torque.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, sample.tau, impedance=impedance)
        b = by_sensor.update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, None, impedance=impedance,
                             foot_contact=a.force[:, 2])
    assert np.all(b.penetration > 1e-4)
    np.testing.assert_allclose(b.penetration, a.penetration, rtol=1e-9)
    np.testing.assert_allclose(b.base_velocity, a.base_velocity, atol=1e-9)


def test_a_contact_source_needs_its_input() -> None:
    model, qj, sample = standing_on_four_feet()
    with pytest.raises(InputError, match="needs the feet's sensor values"):
        LegOdometry(model, LegOdometrySettings(contact_source="contact_flags")).update(
            DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, sample.tau)
    with pytest.raises(InputError, match="needs the joint torques"):
        LegOdometry(model).update(DT_S, BASE_ROTATION, ANGULAR_VELOCITY, qj, sample.qd, None)
    with pytest.raises(InputError, match="contact_source is fixed"):
        LegOdometry(model).reconfigure(LegOdometrySettings(contact_source="force_sensor"))


@pytest.mark.parametrize("kwargs, message", [
    ({"contact_source": "pressure"}, "contact_source must be one of"),
    ({"foot_force_scale": (1.0, 1.0, 1.0)}, "foot_force_scale needs 4 finite values"),
    ({"foot_force_scale": (1.0, 1.0, 0.0, 1.0)}, "foot_force_scale must be > 0"),
    ({"foot_force_offset": (0.0, math.nan, 0.0, 0.0)}, "foot_force_offset needs 4 finite values"),
    ({"contact_hysteresis_fraction": 1.0}, "contact_hysteresis_fraction must be in"),
])
def test_contact_source_settings_reject_invalid_values(kwargs: dict, message: str) -> None:
    with pytest.raises(InputError, match=message):
        LegOdometrySettings(**kwargs)
