"""Tests of tal_core.robot_model against independent Pinocchio computations and finite differences."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from tal_core.errors import InputError, RobotConfigError
from tal_core.legs import LEGS, Leg
from tal_core.robot_description import load_robot_description
from tal_core.robot_model import RobotModel

FD_STEP = 1e-6
LWA = pin.LOCAL_WORLD_ALIGNED


@pytest.fixture(scope="module")
def hyq() -> RobotModel:
    return RobotModel.from_name("hyq")


@pytest.fixture(scope="module")
def solo() -> RobotModel:
    return RobotModel.from_name("solo12")


def random_state(robot: RobotModel, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A configuration near the nominal pose with a tilted, displaced base, and a random velocity."""
    rng = np.random.default_rng(seed)
    q = pin.integrate(robot.model, robot.neutral_q(), 0.3 * rng.standard_normal(robot.nv))
    return q, rng.standard_normal(robot.nv)


def independent_foot_positions(robot: RobotModel, q: np.ndarray) -> np.ndarray:
    """Foot origins [m] from Pinocchio directly, looked up by the URDF frame names."""
    model, data = robot.model, robot.model.createData()
    pin.framesForwardKinematics(model, data, q)
    return np.array([data.oMf[model.getFrameId(name)].translation for name in robot.description.foot_frames])


def independent_foot_jacobians(robot: RobotModel, q: np.ndarray) -> np.ndarray:
    model, data = robot.model, robot.model.createData()
    pin.computeJointJacobians(model, data, q)
    pin.updateFramePlacements(model, data)
    return np.vstack(
        [
            pin.getFrameJacobian(model, data, model.getFrameId(name), LWA)[:3]
            for name in robot.description.foot_frames
        ]
    )


def finite_difference_foot_jacobians(robot: RobotModel, q: np.ndarray) -> np.ndarray:
    """Central differences of the foot positions along every tangent direction (pin.integrate)."""
    jacobian = np.zeros((12, robot.nv))
    for k in range(robot.nv):
        step = np.zeros(robot.nv)
        step[k] = FD_STEP
        plus = independent_foot_positions(robot, pin.integrate(robot.model, q, step))
        minus = independent_foot_positions(robot, pin.integrate(robot.model, q, -step))
        jacobian[:, k] = ((plus - minus) / (2.0 * FD_STEP)).ravel()
    return jacobian


# ----------------------------------------------------------------------------------------------------
# Model and nominal pose
# ----------------------------------------------------------------------------------------------------
def test_hyq_total_mass(hyq: RobotModel) -> None:
    assert hyq.total_mass_kg == pytest.approx(86.77, abs=0.01)
    hyq.update(hyq.neutral_q(), np.zeros(hyq.nv))
    assert hyq.mass_matrix()[0, 0] == pytest.approx(86.77, abs=0.01)  # M's linear block is m * I


def test_canonical_indices_follow_the_joint_names(hyq: RobotModel) -> None:
    expected = [hyq.model.joints[hyq.model.getJointId(name)].idx_v for name in hyq.description.joint_names]
    np.testing.assert_array_equal(hyq.canonical_joint_v_indices(), expected)
    lh = hyq.model.joints[hyq.model.getJointId("lh_haa_joint")].idx_v
    np.testing.assert_array_equal(hyq.leg_joint_v_indices(Leg.LH), [lh, lh + 1, lh + 2])
    np.testing.assert_array_equal(hyq.leg_joint_v_indices("LH"), hyq.leg_joint_v_indices(2))


def test_neutral_pose_feet_touch_the_ground_under_the_hips(hyq: RobotModel) -> None:
    q = hyq.neutral_q()
    hyq.update(q, np.zeros(hyq.nv))
    feet, hips = hyq.foot_positions(), hyq.hip_positions()
    np.testing.assert_allclose(feet, independent_foot_positions(hyq, q), atol=1e-12)
    np.testing.assert_allclose(feet[:, 2], hyq.description.foot_radius_m, atol=1e-12)
    np.testing.assert_allclose(feet[:, :2], hips[:, :2], atol=5e-3)
    assert 0.55 <= q[2] <= 0.6
    assert hyq.nominal_base_height_m == pytest.approx(0.5867, abs=1e-4)
    np.testing.assert_allclose(hips[Leg.LF], [0.3735, 0.207, q[2]], atol=1e-9)  # URDF lf_haa_joint origin


def test_neutral_q_with_an_explicit_height(hyq: RobotModel) -> None:
    assert hyq.neutral_q(base_height=0.5)[2] == 0.5
    with pytest.raises(InputError, match="base_height"):
        hyq.neutral_q(base_height=float("nan"))


def test_base_frame_must_be_the_floating_base(tmp_path: Path) -> None:
    document = yaml.safe_load(Path(load_robot_description("hyq").source).read_text(encoding="utf-8"))
    document["base_frame"] = "lf_foot"
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    with pytest.raises(RobotConfigError, match="'base_frame': frame 'lf_foot' does not coincide"):
        RobotModel(load_robot_description(path))


# ----------------------------------------------------------------------------------------------------
# q and v conventions
# ----------------------------------------------------------------------------------------------------
def test_make_q_split_q_round_trip(hyq: RobotModel) -> None:
    joints = np.arange(12) * 0.1 - 0.5
    quat = np.array([0.1, -0.2, 0.3, 0.9])
    quat /= np.linalg.norm(quat)
    q = hyq.make_q([1.0, 2.0, 0.6], quat, joints)
    assert q[hyq.model.joints[hyq.model.getJointId("lh_kfe_joint")].idx_q] == pytest.approx(joints[8])
    position, quat_back, joints_back = hyq.split_q(q)
    np.testing.assert_allclose(position, [1.0, 2.0, 0.6])
    np.testing.assert_allclose(quat_back, quat)
    np.testing.assert_allclose(joints_back, joints)


def test_make_v_uses_world_frame_base_velocities(hyq: RobotModel) -> None:
    quat = np.array([0.2, 0.1, -0.4, 0.85])
    quat /= np.linalg.norm(quat)
    q = hyq.make_q([0.0, 0.0, 0.6], quat, hyq.description.nominal_joint_positions_rad)
    lin_world, ang_world, joint_vel = (
        np.array([0.5, -0.2, 0.1]),
        np.array([0.3, 0.2, -0.6]),
        np.linspace(-1, 1, 12),
    )
    v = hyq.make_v(lin_world, ang_world, joint_vel, quat)
    for expected, actual in zip((lin_world, ang_world, joint_vel), hyq.split_v(v, quat), strict=True):
        np.testing.assert_allclose(actual, expected, atol=1e-12)
    # Independent check of the convention: integrate q along v and look at the base motion in the world.
    dt = 1e-7
    world_M_base = pin.XYZQUATToSE3(q[:7])
    world_M_base_next = pin.XYZQUATToSE3(pin.integrate(hyq.model, q, v * dt)[:7])
    np.testing.assert_allclose(
        (world_M_base_next.translation - world_M_base.translation) / dt, lin_world, atol=1e-6
    )
    rotation_rate = pin.log3(world_M_base_next.rotation @ world_M_base.rotation.T) / dt
    np.testing.assert_allclose(rotation_rate, ang_world, atol=1e-6)


# ----------------------------------------------------------------------------------------------------
# Kinematics against finite differences
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("robot_name", ["hyq", "solo"])
def test_foot_jacobians_match_finite_differences(robot_name: str, hyq: RobotModel, solo: RobotModel) -> None:
    robot = {"hyq": hyq, "solo": solo}[robot_name]
    q, v = random_state(robot, seed=1)
    robot.update(q, v)
    np.testing.assert_allclose(robot.foot_jacobians(), finite_difference_foot_jacobians(robot, q), atol=1e-6)
    np.testing.assert_allclose(robot.foot_jacobian(Leg.RH), robot.foot_jacobians()[9:12])
    np.testing.assert_allclose(robot.foot_positions(), independent_foot_positions(robot, q), atol=1e-12)
    # The foot velocity is the derivative of the foot position along v.
    step = FD_STEP * v
    velocity = (
        independent_foot_positions(robot, pin.integrate(robot.model, q, step))
        - independent_foot_positions(robot, pin.integrate(robot.model, q, -step))
    ) / (2.0 * FD_STEP)
    np.testing.assert_allclose(robot.foot_velocities(), velocity, atol=1e-6)


@pytest.mark.parametrize("robot_name", ["hyq", "solo"])
def test_djdq_matches_finite_differences_of_the_jacobian(
    robot_name: str, hyq: RobotModel, solo: RobotModel
) -> None:
    robot = {"hyq": hyq, "solo": solo}[robot_name]
    q, v = random_state(robot, seed=2)
    robot.update(q, v)
    jacobian_rate = (
        independent_foot_jacobians(robot, pin.integrate(robot.model, q, FD_STEP * v))
        - independent_foot_jacobians(robot, pin.integrate(robot.model, q, -FD_STEP * v))
    ) / (2 * FD_STEP)
    expected = (jacobian_rate @ v).reshape(4, 3)
    assert np.abs(expected).max() > 0.1  # the test would be empty at a trivial state
    np.testing.assert_allclose(robot.foot_djdqs(), expected, atol=1e-6)
    np.testing.assert_allclose(robot.foot_djdq("LH"), expected[Leg.LH], atol=1e-6)


# ----------------------------------------------------------------------------------------------------
# Dynamics against Pinocchio's own algorithms
# ----------------------------------------------------------------------------------------------------
def test_mass_matrix_is_symmetric_positive_definite_and_gives_the_kinetic_energy(hyq: RobotModel) -> None:
    q, v = random_state(hyq, seed=3)
    hyq.update(q, v)
    M = hyq.mass_matrix()
    np.testing.assert_array_equal(M, M.T)
    assert np.linalg.eigvalsh(M).min() > 0.0
    kinetic_energy = pin.computeKineticEnergy(hyq.model, hyq.model.createData(), q, v)
    assert 0.5 * v @ M @ v == pytest.approx(kinetic_energy, rel=1e-12)


def test_nonlinear_effects_match_gravity_and_rnea(hyq: RobotModel) -> None:
    q, v = random_state(hyq, seed=4)
    hyq.update(q, np.zeros(hyq.nv))
    gravity = pin.computeGeneralizedGravity(hyq.model, hyq.model.createData(), q)
    np.testing.assert_allclose(hyq.nonlinear_effects(), gravity, atol=1e-9)
    hyq.update(q, v)
    rnea = pin.rnea(hyq.model, hyq.model.createData(), q, v, np.zeros(hyq.nv))
    np.testing.assert_allclose(hyq.nonlinear_effects(), rnea, atol=1e-9)


def test_com_matches_pinocchio(hyq: RobotModel) -> None:
    q, v = random_state(hyq, seed=5)
    hyq.update(q, v)
    data = hyq.model.createData()
    np.testing.assert_allclose(hyq.com(), pin.centerOfMass(hyq.model, data, q, v), atol=1e-12)
    np.testing.assert_allclose(hyq.com_velocity(), data.vcom[0], atol=1e-12)


# ----------------------------------------------------------------------------------------------------
# Per-leg statics
# ----------------------------------------------------------------------------------------------------
def test_standing_torques_match_rnea_with_external_foot_forces(hyq: RobotModel) -> None:
    """Weight shared by the 4 feet: our per-leg torques plus each leg's own gravity term must equal
    Pinocchio's RNEA with the foot forces applied as external forces, and the base must be balanced."""
    q = hyq.neutral_q()
    hyq.update(q, np.zeros(hyq.nv))
    gravity = hyq.nonlinear_effects()
    # Ground reaction forces that balance the base rows exactly (minimum-norm solution). The CoM sits
    # ahead of and left of the base origin, so the shares differ but they carry the whole weight.
    grfs, *_ = np.linalg.lstsq(hyq.foot_jacobians()[:, :6].T, gravity[:6], rcond=None)
    grfs = grfs.reshape(4, 3)
    assert grfs[:, 2].sum() == pytest.approx(hyq.total_mass_kg * 9.81, rel=1e-9)
    assert np.all(grfs[:, 2] > 0.15 * hyq.total_mass_kg * 9.81)

    model, data = hyq.model, hyq.model.createData()
    pin.framesForwardKinematics(model, data, q)
    external = [pin.Force.Zero() for _ in range(model.njoints)]
    for leg, grf in zip(LEGS, grfs, strict=True):
        frame = model.frames[model.getFrameId(hyq.description.foot_frames[leg])]
        world_force = pin.Force(grf, np.cross(data.oMf[model.getFrameId(frame.name)].translation, grf))
        external[frame.parentJoint] = data.oMi[frame.parentJoint].actInv(world_force)
    tau_rnea = pin.rnea(model, data, q, np.zeros(hyq.nv), np.zeros(hyq.nv), external)
    np.testing.assert_allclose(tau_rnea[:6], 0.0, atol=1e-8)
    for leg, grf in zip(LEGS, grfs, strict=True):
        indices = hyq.leg_joint_v_indices(leg)
        ours = hyq.leg_torques_for_foot_force(leg, grf) + gravity[indices]
        np.testing.assert_allclose(ours, tau_rnea[indices], atol=1e-8)
        # and back: with h_leg the estimator recovers the force exactly
        recovered = hyq.foot_force_from_leg_torques(leg, tau_rnea[indices], h_leg=gravity[indices])
        np.testing.assert_allclose(recovered, grf, atol=1e-8)


def test_force_torque_round_trip_and_sign(hyq: RobotModel) -> None:
    q, _ = random_state(hyq, seed=6)
    hyq.update(q, np.zeros(hyq.nv))
    grf = np.array([30.0, -20.0, 250.0])
    for leg in LEGS:
        tau = hyq.leg_torques_for_foot_force(leg, grf)
        np.testing.assert_allclose(tau, -hyq.leg_jacobian(leg).T @ grf)
        np.testing.assert_allclose(hyq.foot_force_from_leg_torques(leg, tau), grf, atol=1e-9)


# ----------------------------------------------------------------------------------------------------
# Second robot
# ----------------------------------------------------------------------------------------------------
def test_solo12_model_works(solo: RobotModel) -> None:
    assert solo.total_mass_kg == pytest.approx(2.5, abs=0.01)
    q = solo.neutral_q()
    solo.update(q, np.zeros(solo.nv))
    np.testing.assert_allclose(solo.foot_positions()[:, 2], solo.description.foot_radius_m, atol=1e-12)
    assert 0.2 < q[2] < 0.3
    assert solo.foot_jacobians().shape == (12, 18)
    np.testing.assert_allclose(solo.hip_positions()[Leg.RH, :2], [-0.1946, -0.0875], atol=1e-9)


# ----------------------------------------------------------------------------------------------------
# Input errors
# ----------------------------------------------------------------------------------------------------
def test_wrong_size_q(hyq: RobotModel) -> None:
    with pytest.raises(InputError, match=r"q: expected shape \(19,\), got \(18,\)"):
        hyq.update(np.zeros(18), np.zeros(18))


def test_nan_in_v(hyq: RobotModel) -> None:
    v = np.zeros(hyq.nv)
    v[7] = np.nan
    with pytest.raises(InputError, match=r"v: non-finite value\(s\) at index \[7\]"):
        hyq.update(hyq.neutral_q(), v)


def test_bad_quaternion(hyq: RobotModel) -> None:
    q = hyq.neutral_q()
    q[6] = 1.1
    with pytest.raises(InputError, match="quaternion norm 1.1 is not 1"):
        hyq.update(q, np.zeros(hyq.nv))
    with pytest.raises(InputError, match="base_quat_xyzw: quaternion norm 0 is not 1"):
        hyq.make_q(np.zeros(3), np.zeros(4), np.zeros(12))


def test_almost_unit_quaternion_is_normalised(hyq: RobotModel) -> None:
    q = hyq.neutral_q()
    q[3:7] = [0.0, 0.0, 0.0, 1.0005]
    hyq.update(q, np.zeros(hyq.nv))
    np.testing.assert_allclose(
        hyq.foot_positions(), independent_foot_positions(hyq, hyq.neutral_q()), atol=1e-12
    )


def test_unknown_leg(hyq: RobotModel) -> None:
    hyq.update(hyq.neutral_q(), np.zeros(hyq.nv))
    with pytest.raises(InputError, match="unknown leg 'XX'"):
        hyq.foot_jacobian("XX")
    with pytest.raises(InputError, match="unknown leg 4"):
        hyq.leg_torques_for_foot_force(4, np.zeros(3))


def test_wrong_force_and_torque_sizes(hyq: RobotModel) -> None:
    hyq.update(hyq.neutral_q(), np.zeros(hyq.nv))
    with pytest.raises(InputError, match=r"grf_world: expected shape \(3,\)"):
        hyq.leg_torques_for_foot_force(Leg.LF, np.zeros(2))
    with pytest.raises(InputError, match=r"h_leg: non-finite"):
        hyq.foot_force_from_leg_torques(Leg.LF, np.zeros(3), h_leg=[0.0, np.inf, 0.0])


def test_accessors_need_an_update() -> None:
    fresh = RobotModel.from_name("solo12")
    with pytest.raises(RuntimeError, match=r"call update\(q, v\)"):
        fresh.foot_positions()
