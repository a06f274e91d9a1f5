"""Closed-form leg IK against Pinocchio's forward kinematics."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from tal_core.legs import LEGS, Leg
from tal_core.robot_model import RobotModel
from tal_perception import leg_kinematics
from tal_perception.errors import LegKinematicsError, PerceptionInputError
from tal_perception.leg_kinematics import LegKinematics


@pytest.fixture(scope="module")
def model() -> RobotModel:
    return RobotModel.from_name("hyq")


@pytest.fixture(scope="module")
def kinematics(model: RobotModel) -> LegKinematics:
    return LegKinematics(model)


def pinocchio_points(model: RobotModel, leg: Leg, joints: np.ndarray) -> tuple[np.ndarray, ...]:
    """Foot centres, KFE and HFE origins (N, 3), base frame, from Pinocchio with the base at the origin."""
    description = model.description
    data = model.model.createData()
    hfe_id = model.model.getJointId(description.leg_joint_names(leg)[1])
    knee_id = model.model.getJointId(description.leg_joint_names(leg)[2])
    foot_id = model.model.getFrameId(description.foot_frames[leg])
    feet, knees, hfes = [], [], []
    for q_leg in joints:
        q_all = np.array(description.nominal_joint_positions_rad, dtype=float)
        q_all[description.leg_joint_slice(leg)] = q_leg
        pin.framesForwardKinematics(model.model, data, model.make_q([0, 0, 0], [0, 0, 0, 1], q_all))
        feet.append(data.oMf[foot_id].translation.copy())
        knees.append(data.oMi[knee_id].translation.copy())
        hfes.append(data.oMi[hfe_id].translation.copy())
    return np.array(feet), np.array(knees), np.array(hfes)


@pytest.mark.parametrize("leg", LEGS, ids=lambda leg: leg.name)
def test_forward_matches_pinocchio(model: RobotModel, kinematics: LegKinematics, leg: Leg) -> None:
    g = kinematics.geometry[leg]
    joints = np.random.default_rng(int(leg)).uniform(g.lower_rad, g.upper_rad, (50, 3))
    feet, knees, hfes = pinocchio_points(model, leg, joints)
    hfe, knee, foot = kinematics.forward(leg, joints)
    np.testing.assert_allclose(foot, feet, atol=1e-9)
    np.testing.assert_allclose(knee, knees, atol=1e-9)
    np.testing.assert_allclose(hfe, hfes, atol=1e-9)


@pytest.mark.parametrize("leg", LEGS, ids=lambda leg: leg.name)
def test_inverse_recovers_pinocchio_configurations(model: RobotModel, kinematics: LegKinematics, leg: Leg) -> None:
    g = kinematics.geometry[leg]
    joints = np.random.default_rng(10 + int(leg)).uniform(g.lower_rad, g.upper_rad, (200, 3))
    feet, knees, hfes = pinocchio_points(model, leg, joints)
    ik = kinematics.inverse(leg, feet)
    assert ik.reachable.all()
    # Whatever branch IK picks, it reaches the target.
    np.testing.assert_allclose(kinematics.forward(leg, ik.joints)[2], feet, atol=1e-9)
    # Within the joint limits HyQ's legs have one branch only: the sampled joints come back exactly.
    assert ik.within_limits.mean() > 0.95
    np.testing.assert_allclose(ik.joints[ik.within_limits], joints[ik.within_limits], atol=1e-9)
    np.testing.assert_allclose(ik.knee[ik.within_limits], knees[ik.within_limits], atol=1e-9)
    np.testing.assert_allclose(ik.hfe[ik.within_limits], hfes[ik.within_limits], atol=1e-9)


def test_nominal_pose_is_feasible_and_far_targets_are_not(model: RobotModel, kinematics: LegKinematics) -> None:
    for leg in LEGS:
        nominal = np.asarray(model.description.nominal_joint_positions_rad)[model.description.leg_joint_slice(leg)]
        foot = kinematics.forward(leg, nominal[None])[2]
        hip = kinematics.geometry[leg].haa_origin
        targets = np.vstack([foot, hip + [0.0, 0.0, -2.0], [np.nan, 0.0, 0.0]])
        ik = kinematics.inverse(leg, targets)
        assert ik.feasible.tolist() == [True, False, False]
        np.testing.assert_allclose(ik.joints[0], nominal, atol=1e-9)
        assert np.isnan(ik.joints[1:]).all()


def test_margins_shrink_the_workspace(model: RobotModel) -> None:
    plain, strict = LegKinematics(model), LegKinematics(model, reach_margin_m=0.05, limit_margin_rad=0.1)
    g = plain.geometry[Leg.LF]
    joints = np.random.default_rng(3).uniform(g.lower_rad, g.upper_rad, (300, 3))
    feet = plain.forward(Leg.LF, joints)[2]
    loose, tight = plain.inverse(Leg.LF, feet).feasible, strict.inverse(Leg.LF, feet).feasible
    assert tight.sum() < loose.sum()
    assert not (tight & ~loose).any()


@pytest.mark.parametrize("leg", LEGS, ids=lambda leg: leg.name)
def test_within_limits_xyz_gives_the_inverse_numbers_of_the_feasible_targets(
    model: RobotModel, kinematics: LegKinematics, leg: Leg
) -> None:
    """The VPA's lean IK: same limit check and bit-identical joint origins as ``inverse_xyz``, for the
    targets within the limits only (a mix of feasible, out-of-limit, unreachable and NaN targets)."""
    rng = np.random.default_rng(4)
    hip = kinematics.geometry[leg].haa_origin
    targets = hip + rng.uniform([-0.5, -0.4, -0.9], [0.5, 0.4, 0.1], (2000, 3))
    targets[::97] = np.nan
    x, y, z = targets.T
    full = kinematics.inverse_xyz(leg, x, y, z)
    within, origins = kinematics.within_limits_xyz(leg, x, y, z)
    np.testing.assert_array_equal(within, full.within_limits)
    assert 0 < within.sum() < within.size
    for axis in range(3):
        np.testing.assert_array_equal(origins.knee(axis), full.knee_xyz[axis][within])
        np.testing.assert_array_equal(origins.hfe(axis), full.hfe_xyz[axis][within])
    some = np.array([0, 3, 5])
    np.testing.assert_array_equal(origins.knee(2, some), full.knee_xyz[2][within][some])
    # Per-cell x, y shared by several targets (the VPA's hip heights): the same numbers again.
    cells = rng.integers(0, 300, x.size)
    x_cells, y_cells = x[:300].copy(), y[:300].copy()
    x, y = x_cells[cells], y_cells[cells]
    full = kinematics.inverse_xyz(leg, x, y, z)
    within, origins = kinematics.within_limits_xyz(leg, x_cells, y_cells, z, cells=cells)
    np.testing.assert_array_equal(within, full.within_limits)
    assert 0 < within.sum() < within.size
    for axis in range(3):
        np.testing.assert_array_equal(origins.knee(axis), full.knee_xyz[axis][within])
        np.testing.assert_array_equal(origins.hfe(axis), full.hfe_xyz[axis][within])


@pytest.mark.parametrize("leg", list(LEGS))
def test_the_in_place_solver_gives_the_bits_of_the_plain_formulas(kinematics: LegKinematics, leg: Leg) -> None:
    """``_solve`` (reused output arrays) against ``_solve_reference`` (plain expressions): every cosine, sine
    and flag bit for bit, on targets in and out of reach, at the HAA origin, NaN and infinite."""
    rng = np.random.default_rng(8)
    constants = kinematics._constants[leg]
    hip = kinematics.geometry[leg].haa_origin
    targets = hip + rng.uniform([-0.9, -0.9, -1.2], [0.9, 0.9, 0.3], (20000, 3))
    targets[:10] = hip
    targets[10:20, 0], targets[20:30, 1], targets[30:40, 2] = np.nan, np.inf, -np.inf
    frame = leg_kinematics._haa_frame(constants, *targets.T)
    fast, plain = leg_kinematics._solve(constants, *frame), leg_kinematics._solve_reference(constants, *frame)
    np.testing.assert_array_equal(fast.reachable, plain.reachable)
    np.testing.assert_array_equal(fast.within, plain.within)
    assert 0 < fast.within.sum() < fast.within.size
    for ours, theirs in zip(fast.cosines + fast.sines, plain.cosines + plain.sines):
        np.testing.assert_array_equal(ours.view(np.int64), theirs.view(np.int64))


def test_bad_input_is_rejected(model: RobotModel, kinematics: LegKinematics) -> None:
    with pytest.raises(PerceptionInputError, match=r"leg LF: foot positions must have shape \(N, 3\), got \(3,\)"):
        kinematics.inverse(Leg.LF, np.zeros(3))
    with pytest.raises(PerceptionInputError, match=r"leg RH: joints must have shape \(N, 3\), got \(2, 2\)"):
        kinematics.forward(Leg.RH, np.zeros((2, 2)))
    with pytest.raises(LegKinematicsError, match=r"reach_margin_m must be a finite value >= 0 \[m\], got -0.1"):
        LegKinematics(model, reach_margin_m=-0.1)
    with pytest.raises(LegKinematicsError, match=r"limit_margin_rad must be a finite value >= 0 \[rad\], got nan"):
        LegKinematics(model, limit_margin_rad=float("nan"))
