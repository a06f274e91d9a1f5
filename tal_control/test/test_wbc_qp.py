"""sWBC QP on HyQ: physical consistency, constraints honoured, fixed sparsity, fallback on failure."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from tal_control.wbc import StandardWbc, WbcReferences, WbcSettings
from tal_control.wbc.qp_layout import FixedPatternMatrix
from tal_core.errors import InputError
from tal_core.legs import Leg
from tal_core.robot_model import RobotModel

UP = np.tile([0.0, 0.0, 1.0], (4, 1))


@pytest.fixture(scope="module")
def model() -> RobotModel:
    return RobotModel.from_name("hyq")


def standing_state(model: RobotModel, base_offset=(0.0, 0.0, 0.0), joint_velocity=None):
    q = model.neutral_q()
    q[:3] += np.asarray(base_offset)
    v = np.zeros(model.nv)
    if joint_velocity is not None:
        v[6:] = joint_velocity
    model.update(q, v)
    return q, v


def references(model: RobotModel, stance=(True, True, True, True), com_offset=(0.0, 0.0, 0.0),
               foot_targets=None) -> WbcReferences:
    feet = model.foot_positions().copy()
    z = np.zeros(3)
    return WbcReferences(
        com_position=model.com() + np.asarray(com_offset), com_velocity=z, com_acceleration=z,
        world_R_base=np.eye(3), angular_velocity=z, angular_acceleration=z,
        foot_position=feet if foot_targets is None else foot_targets, foot_velocity=np.zeros((4, 3)),
        foot_acceleration=np.zeros((4, 3)), stance=np.array(stance), load_factor=np.ones(4),
        touchdown_position=feet, normals=UP)


def full_dynamics_residual(model: RobotModel, q, v, solution) -> np.ndarray:
    """M qdd + h - S^T tau - J^T F over all nv rows (tau mapped back to Pinocchio's joint order)."""
    tau_v = np.zeros(model.nv)
    tau_v[model.canonical_joint_v_indices()] = solution.tau
    residual = model.mass_matrix() @ solution.qdd + model.nonlinear_effects() - tau_v
    for leg in Leg:
        residual -= model.foot_jacobian(leg).T @ solution.forces[leg]
    return residual


def test_standing_is_physically_consistent_and_carries_the_weight(model) -> None:
    q, v = standing_state(model)
    wbc = StandardWbc(model)
    solution = wbc.solve(q, v, references(model))
    assert solution.status_val == 1 and not solution.fallback
    assert np.sum(solution.forces[:, 2]) == pytest.approx(model.total_mass_kg * 9.81, rel=1e-3)
    assert np.abs(full_dynamics_residual(model, q, v, solution)).max() < 1e-2
    # Rigid stance: the stance feet do not accelerate.
    for leg in Leg:
        foot_acc = model.foot_jacobian(leg) @ solution.qdd + model.foot_djdq(leg)
        assert np.linalg.norm(foot_acc) < 1e-3


def test_com_error_produces_a_restoring_wrench(model) -> None:
    q, v = standing_state(model)
    solution = StandardWbc(model).solve(q, v, references(model, com_offset=(0.05, 0.0, 0.0)))
    # K_x = 2000 N/m on 5 cm: 100 N forward on the CoM from the feet's tangential forces.
    assert np.sum(solution.forces[:, 0]) == pytest.approx(100.0, rel=0.02)


def test_friction_pyramid_holds_with_a_low_coefficient(model) -> None:
    q, v = standing_state(model)
    wbc = StandardWbc(model, settings=WbcSettings(friction_coefficient=0.05))
    solution = wbc.solve(q, v, references(model, com_offset=(0.2, 0.0, 0.0)))
    f = solution.forces
    # OSQP stops at eps 1e-4 (relative to forces of ~200 N): violations stay below 0.05 N.
    assert np.all(np.abs(f[:, 0]) <= 0.05 * f[:, 2] + 0.05)
    assert np.all(np.abs(f[:, 1]) <= 0.05 * f[:, 2] + 0.05)


def test_swing_leg_has_no_force_and_tracks_its_target(model) -> None:
    q, v = standing_state(model)
    refs = references(model, stance=(False, True, True, True))
    target = refs.foot_position.copy()
    target[Leg.LF] += [0.0, 0.0, 0.01]
    refs = references(model, stance=(False, True, True, True), foot_targets=target)
    solution = StandardWbc(model).solve(q, v, refs)
    assert not solution.fallback
    assert np.allclose(solution.forces[Leg.LF], 0.0, atol=1e-3)
    foot_acc = model.foot_jacobian(Leg.LF) @ solution.qdd + model.foot_djdq(Leg.LF)
    assert foot_acc[2] == pytest.approx(2000.0 * 0.01, rel=1e-2)   # K_sw * 1 cm
    assert solution.slack_norm < 0.05   # only the solver tolerance: nothing conflicts


def test_torque_limit_is_respected_and_load_moves_to_other_joints(model) -> None:
    q, v = standing_state(model)
    free = StandardWbc(model).solve(q, v, references(model))
    kfe = model.description.joint_names.index("lf_kfe_joint")
    assert abs(free.tau[kfe]) > 30.0
    limited = StandardWbc(model, settings=WbcSettings(torque_limit_overrides_nm=(("lf_kfe_joint", 26.0),)))
    solution = limited.solve(q, v, references(model))
    assert not solution.fallback
    assert abs(solution.tau[kfe]) <= 26.0 + 1e-2
    assert np.sum(solution.forces[:, 2]) == pytest.approx(model.total_mass_kg * 9.81, rel=1e-3)


def test_joint_limit_engages_the_swing_slack(model) -> None:
    # LH HFE 0.22 rad from its lower limit, moving towards it at 8 rad/s: the acceleration bound must
    # brake the joint, which conflicts with a swing task that asks the foot to keep its velocity.
    names = model.description.joint_names
    hfe = names.index("lh_hfe_joint")
    to_v = model.canonical_joint_v_indices()
    q = model.neutral_q()
    q[to_v[hfe] + 1] = model.description.position_lower_rad[hfe] + 0.22
    v = np.zeros(model.nv)
    v[to_v[hfe]] = -8.0
    model.update(q, v)
    refs = references(model, stance=(True, True, False, True))
    foot_velocity = model.foot_velocities()
    refs = WbcReferences(**{**refs.__dict__, "foot_velocity": foot_velocity})
    solution = StandardWbc(model).solve(q, v, refs)
    assert not solution.fallback
    dt = 10 * 0.004
    qdd_min = 2.0 / dt**2 * (model.description.position_lower_rad[hfe] - q[to_v[hfe] + 1] - dt * v[to_v[hfe]])
    assert solution.qdd[to_v[hfe]] >= qdd_min - 1e-2        # the joint is braked as required
    assert solution.slack_norm > 1.0                        # and the swing task gives way
    assert np.abs(solution.slacks[Leg.LH]).max() > 1.0


def test_invalid_references_are_rejected(model) -> None:
    standing_state(model)
    refs = references(model)
    with pytest.raises(InputError, match="com_position"):
        WbcReferences(**{**refs.__dict__, "com_position": np.array([np.nan, 0.0, 0.0])})
    normals = refs.normals.copy()
    normals[2, 1] = np.inf
    with pytest.raises(InputError, match="'normals' has NaN or inf"):
        WbcReferences(**{**refs.__dict__, "normals": normals})
    with pytest.raises(InputError, match="stance"):
        WbcReferences(**{**refs.__dict__, "stance": np.ones(3, dtype=bool)})
    with pytest.raises(InputError, match="unknown joint"):
        StandardWbc(model, settings=WbcSettings(torque_limit_overrides_nm=(("no_joint", 1.0),)))


def test_infeasible_problem_falls_back_without_raising(model) -> None:
    """Every joint limited to 0.1 N m: the stance cannot be held. OSQP (200 iterations) finds neither the QP nor
    its relaxed retry and the fallback decays the last torques; DAQP finds the relaxed retry's exact optimum
    (stance given up, torques within their limits). Both count it as a fallback; neither raises."""
    q, v = standing_state(model)
    names = model.description.joint_names
    limits = tuple((n, 0.1) for n in names)
    osqp_wbc = StandardWbc(model, settings=WbcSettings(qp_solver="osqp", torque_limit_overrides_nm=limits,
                                                       max_iterations=200))
    solution = osqp_wbc.solve(q, v, references(model))
    assert solution.fallback and solution.status == "fallback"
    assert osqp_wbc.failed_solves == 1
    assert np.all(np.isfinite(solution.tau))
    daqp_wbc = StandardWbc(model, settings=WbcSettings(qp_solver="daqp", torque_limit_overrides_nm=limits))
    solution = daqp_wbc.solve(q, v, references(model))
    assert solution.fallback and solution.status.startswith("relaxed stance")
    assert daqp_wbc.failed_solves == 1
    assert np.all(np.abs(solution.tau) <= 0.1 + 1e-6)


def test_daqp_reaches_the_optimum_osqp_approaches(model) -> None:
    """DAQP returns the QP's optimum: OSQP at a tight tolerance lands on the same joint torques and forces."""
    q, v = standing_state(model)
    refs = references(model, stance=(True, False, False, True))
    exact = StandardWbc(model, settings=WbcSettings(qp_solver="daqp")).solve(q, v, refs)
    tight = StandardWbc(model, settings=WbcSettings(qp_solver="osqp", eps_abs=1e-9, eps_rel=1e-9,
                                                    max_iterations=100000)).solve(q, v, refs)
    assert not exact.fallback and exact.status == "solved"
    assert np.allclose(exact.tau, tight.tau, atol=0.5)
    assert np.allclose(exact.forces, tight.forces, atol=0.5)


def test_force_rate_regularisation_keeps_the_forces_near_the_last_ones(model) -> None:
    """w ||F - F_prev||^2: after a solve on four feet, the same state with the wrench reference moved sideways
    gives forces closer to the previous ones with the term than without it."""
    q, v = standing_state(model)
    refs = references(model)
    moved = WbcReferences(**{**refs.__dict__, "com_position": refs.com_position + np.array([0.0, 0.05, 0.0])})
    changes = []
    for w in (0.0, 1.0):
        wbc = StandardWbc(model, settings=WbcSettings(qp_solver="daqp", force_rate_regularisation=w))
        first = wbc.solve(q, v, refs)
        second = wbc.solve(q, v, moved)
        changes.append(float(np.abs(second.forces - first.forces).max()))
    assert changes[1] < 0.9 * changes[0]


def test_unknown_qp_solver_is_rejected() -> None:
    with pytest.raises(InputError, match="qp_solver"):
        WbcSettings(qp_solver="quadprog")


def test_fixed_pattern_matrix_keeps_explicit_zeros() -> None:
    mask = np.array([[True, False, True], [False, True, True]])
    pattern = FixedPatternMatrix(mask)
    dense = np.array([[1.0, 9.0, 0.0], [0.0, 2.0, 3.0]])
    values = pattern.values_from(dense)
    assert len(values) == mask.sum()
    np.testing.assert_allclose(pattern.with_values(values).toarray(), dense * mask)


def test_orientation_error_sign(model) -> None:
    from tal_control.wbc.tasks import orientation_error
    desired = pin.rpy.rpyToMatrix(0.1, 0.0, 0.0)
    np.testing.assert_allclose(orientation_error(desired, np.eye(3)), [0.1, 0.0, 0.0], atol=1e-12)


def test_compliant_wbc_keeps_forces_consistent_with_the_contact_model(model) -> None:
    """c3WBC: F = K eps + D (eps - eps_prev)/dt and J qdd + dJ v = -(eps - 2 eps_prev + eps_prev2)/dt^2."""
    q, v = standing_state(model)
    settings = WbcSettings(contact_model="compliant")
    wbc = StandardWbc(model, settings=settings)
    refs = references(model)
    k, d, dt = 3500.0, 400.0, settings.control_period_s
    refs = WbcReferences(**{**refs.__dict__, "stiffness_normal": np.full(4, k), "damping_normal": np.full(4, d)})
    history = [np.zeros((4, 3)), np.zeros((4, 3))]
    for _ in range(3):
        solution = wbc.solve(q, v, refs)
        assert not solution.fallback
        eps = solution.extras["penetration"]
        for leg in Leg:
            model_force = k * eps[leg] + d * (eps[leg] - history[-1][leg]) / dt
            np.testing.assert_allclose(solution.forces[leg], model_force, atol=0.5)
            foot_acc = model.foot_jacobian(leg) @ solution.qdd + model.foot_djdq(leg)
            eps_dd = (eps[leg] - 2 * history[-1][leg] + history[-2][leg]) / dt**2
            np.testing.assert_allclose(foot_acc, -eps_dd, atol=0.5)
        assert np.all(eps[:, 2] >= -1e-6)            # normal penetration is never negative
        history.append(eps.copy())
    assert np.sum(solution.forces[:, 2]) > 0.0


def test_unknown_contact_model_is_rejected() -> None:
    with pytest.raises(InputError, match="contact_model"):
        WbcSettings(contact_model="squishy")


def test_run_time_settings_take_effect_at_the_next_solve_and_fixed_ones_are_refused(model) -> None:
    q, v = standing_state(model)
    refs = references(model, com_offset=(0.2, 0.0, 0.0))
    wbc = StandardWbc(model)
    wide = wbc.solve(q, v, refs).forces
    assert np.any(np.abs(wide[:, 0]) > 0.1 * wide[:, 2] + 0.05)       # mu 0.8 lets the feet push harder
    wbc.update_settings(friction_coefficient=0.05, max_normal_force_n=300.0)
    f = wbc.solve(q, v, refs).forces                                    # the cached pyramids are rebuilt
    assert np.all(np.abs(f[:, 0]) <= 0.05 * f[:, 2] + 0.05)
    assert np.all(f[:, 2] <= 300.0 + 0.05)
    with pytest.raises(InputError, match="contact_model"):
        wbc.update_settings(contact_model="compliant")
    with pytest.raises(InputError, match="min <= max"):
        wbc.update_settings(min_normal_force_n=400.0)
    assert wbc.settings.min_normal_force_n == 10.0 and wbc.settings.friction_coefficient == 0.05
