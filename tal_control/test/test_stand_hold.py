"""Tests of tal_control.stand_hold against an independent Pinocchio computation of the static torques."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from tal_control.stand_hold import GRAVITY_M_S2, StandHold, balanced_vertical_forces
from tal_core.errors import InputError
from tal_core.legs import LEGS
from tal_core.robot_description import load_robot_description
from tal_core.robot_model import RobotModel

KP, KD = 1500.0, 40.0


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel(load_robot_description("hyq"))


@pytest.fixture(scope="module")
def hold(robot: RobotModel) -> StandHold:
    return StandHold(robot, KP, KD)


# --- balanced_vertical_forces --------------------------------------------------------------------------
def random_layout(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Four feet around a rectangle (perturbed) and a CoM inside their hull."""
    rng = np.random.default_rng(seed)
    corners = np.array([[0.37, 0.2], [0.37, -0.2], [-0.37, 0.2], [-0.37, -0.2]])
    feet = corners + rng.uniform(-0.05, 0.05, (4, 2)) + rng.uniform(-3.0, 3.0, 2)
    com = feet.mean(axis=0) + rng.uniform(-0.08, 0.08, 2)
    return feet, com


@pytest.mark.parametrize("seed", range(6))
def test_balanced_forces_carry_the_weight_with_zero_moment_about_the_com(seed: int) -> None:
    feet, com = random_layout(seed)
    weight = 851.2
    forces = balanced_vertical_forces(feet, com, weight)
    assert forces.shape == (4,)
    assert forces.sum() == pytest.approx(weight, rel=1e-12)
    moment = forces @ (feet - com)  # sum_i f_i (p_i - c): the horizontal moment arms of vertical forces
    np.testing.assert_allclose(moment, 0.0, atol=1e-9 * weight)
    assert np.all(forces > 0.0)  # CoM well inside the support polygon


@pytest.mark.parametrize("seed", range(3))
def test_balanced_forces_are_the_minimum_norm_solution(seed: int) -> None:
    feet, com = random_layout(seed)
    forces = balanced_vertical_forces(feet, com, 100.0)
    A = np.vstack([np.ones(4), (feet - com).T])
    null_space = np.linalg.svd(A)[2][-1]  # the one direction that changes no constraint
    np.testing.assert_allclose(A @ null_space, 0.0, atol=1e-12)
    assert forces @ null_space == pytest.approx(0.0, abs=1e-9)


def test_balanced_forces_for_a_centred_com_on_a_rectangle_are_equal() -> None:
    feet = np.array([[0.4, 0.25], [0.4, -0.25], [-0.4, 0.25], [-0.4, -0.25]]) + [1.0, -2.0]
    np.testing.assert_allclose(balanced_vertical_forces(feet, np.array([1.0, -2.0]), 400.0), 100.0)


def test_balanced_forces_shift_towards_the_com() -> None:
    feet = np.array([[0.4, 0.25], [0.4, -0.25], [-0.4, 0.25], [-0.4, -0.25]])
    forces = balanced_vertical_forces(feet, np.array([0.1, 0.05]), 400.0)
    assert forces[0] > forces[1] and forces[0] > forces[2] and forces[3] == forces.min()


# --- feed_forward vs an independent Pinocchio computation ---------------------------------------------
def independent_feed_forward(hold: StandHold, joint_positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(joint torques in canonical order, free-flyer residual wrench) from a model built in the test.

    Foot forces: the minimum-norm vertical forces carrying the weight with zero moment about the CoM
    (pseudo-inverse); torques: inverse dynamics at rest with those forces as external forces,
    tau = rnea(q, 0, 0, f_ext) = h - sum_i J_i^T F_i.
    """
    description = hold.model.description
    model = pin.buildModelFromUrdf(str(description.urdf_path), pin.JointModelFreeFlyer())
    data = model.createData()
    q = pin.neutral(model)
    q[2] = hold.base_height_m
    joints = [model.joints[model.getJointId(name)] for name in description.joint_names]
    for joint, angle in zip(joints, joint_positions, strict=True):
        q[joint.idx_q] = angle
    pin.framesForwardKinematics(model, data, q)
    com = pin.centerOfMass(model, data, q)
    frame_ids = [model.getFrameId(description.foot_frames[leg]) for leg in LEGS]
    feet = np.array([data.oMf[fid].translation for fid in frame_ids])
    weight = pin.computeTotalMass(model) * GRAVITY_M_S2
    A = np.vstack([np.ones(4), feet[:, 0] - com[0], feet[:, 1] - com[1]])
    f_z = np.linalg.pinv(A) @ np.array([weight, 0.0, 0.0])
    f_ext = [pin.Force.Zero() for _ in range(model.njoints)]
    for fid, p, fz in zip(frame_ids, feet, f_z, strict=True):
        force = np.array([0.0, 0.0, fz])
        joint_id = model.frames[fid].parentJoint
        world_force = pin.Force(force, np.cross(p, force))  # spatial force about the world origin
        f_ext[joint_id] += data.oMi[joint_id].actInv(world_force)
    tau = pin.rnea(model, data, q, np.zeros(model.nv), np.zeros(model.nv), f_ext)
    return np.array([tau[joint.idx_v] for joint in joints]), tau[:6]


def test_feed_forward_at_the_nominal_pose_matches_pinocchio(hold: StandHold) -> None:
    nominal = hold.model.description.nominal_joint_positions_rad
    expected, residual = independent_feed_forward(hold, nominal)
    np.testing.assert_allclose(hold.feed_forward(nominal), expected, rtol=1e-9, atol=1e-9)
    # The forces balance the whole robot: nothing is left for the (unactuated) free flyer.
    np.testing.assert_allclose(residual, 0.0, atol=1e-8 * hold.weight_n)


def test_feed_forward_at_the_nominal_pose_is_plausible(hold: StandHold) -> None:
    tau = hold.feed_forward(hold.model.description.nominal_joint_positions_rad)
    assert tau.shape == (12,)
    assert np.all(np.abs(tau) < 150.0)  # within HyQ's torque limits
    knees = tau[[2, 5, 8, 11]]
    assert np.all(np.abs(knees) > 20.0)  # the knees carry the weight
    # Front knees bend the other way from hind knees, so their torques have opposite signs.
    assert np.sign(knees[0]) == np.sign(knees[1]) == -np.sign(knees[2]) == -np.sign(knees[3])


def test_feed_forward_at_a_perturbed_pose_matches_pinocchio(hold: StandHold) -> None:
    q = hold.model.description.nominal_joint_positions_rad + np.linspace(-0.15, 0.15, 12)
    expected, residual = independent_feed_forward(hold, q)
    np.testing.assert_allclose(hold.feed_forward(q), expected, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(residual, 0.0, atol=1e-8 * hold.weight_n)


def test_weight_and_base_height_come_from_the_model(hold: StandHold, robot: RobotModel) -> None:
    assert hold.weight_n == pytest.approx(robot.total_mass_kg * 9.81, rel=1e-12)
    assert robot.total_mass_kg == pytest.approx(86.77, abs=0.01)
    assert hold.base_height_m == pytest.approx(robot.neutral_q()[2])


# --- command() -----------------------------------------------------------------------------------------
def test_command_fields_in_canonical_order(hold: StandHold) -> None:
    nominal = hold.model.description.nominal_joint_positions_rad
    q = nominal + 0.05
    command = hold.command(q)
    assert set(command) == {"effort", "position", "velocity", "kp", "kd"}
    np.testing.assert_array_equal(command["effort"], hold.feed_forward(q))
    np.testing.assert_array_equal(command["position"], nominal)
    np.testing.assert_array_equal(command["velocity"], np.zeros(12))
    np.testing.assert_array_equal(command["kp"], np.full(12, KP))
    np.testing.assert_array_equal(command["kd"], np.full(12, KD))
    command["position"][:] = 0.0  # the caller owns the arrays
    np.testing.assert_array_equal(hold.command(q)["position"], nominal)


@pytest.mark.parametrize("bad", [
    np.full(12, math.nan),
    np.r_[np.zeros(11), math.inf],
    np.zeros(11),
    np.zeros(13),
    np.zeros((1, 12)),
    np.zeros(0),
], ids=["nan", "inf", "11", "13", "2d", "empty"])
def test_command_rejects_bad_joint_positions(hold: StandHold, bad: np.ndarray) -> None:
    with pytest.raises(InputError, match=r"expected 12 finite joint positions"):
        hold.command(bad)


@pytest.mark.parametrize(("kp", "kd"), [(-1.0, 40.0), (1500.0, -0.1), (-5.0, -5.0)])
def test_negative_gains_are_rejected(robot: RobotModel, kp: float, kd: float) -> None:
    with pytest.raises(InputError, match=r"PD gains must be >= 0"):
        StandHold(robot, kp, kd)


def test_zero_gains_are_allowed(robot: RobotModel) -> None:
    command = StandHold(robot, 0.0, 0.0).command(robot.description.nominal_joint_positions_rad)
    np.testing.assert_array_equal(command["kp"], 0.0)
