"""The passive whole-body controller (sWBC) of the thesis, solved with OSQP.

    min  || W_com(F) - W_com,d ||_Q^2 + ||u||_R^2 + alpha ||eta||^2        u = [qdd, F, eta]
    s.t. M_u qdd + h_u = J_st,u^T F                     (floating-base dynamics, 6 rows)
         J_st qdd + dJ_st v = a_st                      (stance feet; a_st = stance-task impedance)
         -eta <= J_sw qdd + dJ_sw v - a_sw,d <= eta     (swing task with one slack per direction)
         friction pyramid about the terrain normal, F_min <= n.F <= F_max(load factor)
         tau_min(q) <= M_a qdd + h_j - J_st,j^T F <= tau_max(q)
         qdd_j within the bounds that reach the end stop at zero velocity in 10 control periods
    tau* = M_a qdd* + h_j - J_st,j^T F*

W_com is the centroidal wrench of the contact forces about the CoM (world frame): (sum F_i,
sum (p_i - c) x F_i), which equals J_st,com^T F of the thesis' CoM coordinates; the dynamics rows use
Pinocchio's base coordinates (first 6 rows of M qdd + h = S^T tau + J^T F), an equivalent constraint.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import osqp
import pinocchio as pin

from tal_core.errors import InputError
from tal_core.legs import NUM_LEGS
from tal_core.robot_model import RobotModel

from .qp_layout import FRICTION_ROWS_PER_LEG, INF, FixedPatternMatrix, QpLayout
from .tasks import WbcGains, WbcReferences, desired_com_wrench, skew, swing_accelerations, tangent_basis

GRAVITY = np.array([0.0, 0.0, -9.81])


@dataclass(frozen=True)
class WbcSettings:
    """QP weights and limits. Units: forces [N], accelerations [m/s^2, rad/s^2]."""

    wrench_weights: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0)   # Q: Fx Fy Fz Tx Ty Tz
    qdd_regularisation: float = 1e-6
    force_regularisation: float = 1e-5
    torque_regularisation: tuple[float, ...] | None = None   # R_tau per joint: R_FF = J_j R_tau J_j^T
    slack_weight: float = 1e4          # alpha, high: slacks only where the swing task must give way
    friction_coefficient: float = 0.8
    min_normal_force_n: float = 10.0
    max_normal_force_n: float = 1000.0
    torque_limit_overrides_nm: tuple[tuple[str, float], ...] = ()   # (joint name, max |tau|) pairs
    position_limit_overrides_rad: tuple[tuple[str, float, float], ...] = ()  # (joint, lower, upper)
    joint_limit_horizon_periods: int = 10
    control_period_s: float = 0.004
    max_iterations: int = 4000
    eps_abs: float = 1e-5
    eps_rel: float = 1e-5


@dataclass
class WbcSolution:
    """Result of one control cycle."""

    tau: np.ndarray               # (nj,) [N m] joint torques, canonical order
    qdd: np.ndarray               # (nv,) generalised accelerations (Pinocchio convention)
    forces: np.ndarray            # (4, 3) [N] ground reaction forces on the feet, world frame
    slacks: np.ndarray            # (4, 3) [m/s^2] swing-task slacks
    desired_wrench: np.ndarray    # (6,) [N, N m] world frame, about the CoM
    status: str
    status_val: int
    iterations: int
    solve_time_s: float
    cycle_time_s: float = 0.0
    fallback: bool = False
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def slack_norm(self) -> float:
        return float(np.linalg.norm(self.slacks))


class StandardWbc:
    """sWBC: one ``solve`` per control cycle on a RobotModel already updated with the current (q, v)."""

    SOLVED = (1, 2)  # OSQP_SOLVED, OSQP_SOLVED_INACCURATE

    def __init__(self, model: RobotModel, gains: WbcGains | None = None,
                 settings: WbcSettings | None = None) -> None:
        self.model = model
        self.gains = gains or WbcGains()
        self.settings = settings or WbcSettings()
        legs = tuple(tuple(int(i) for i in model.leg_joint_v_indices(leg)) for leg in range(NUM_LEGS))
        self.layout = QpLayout(nv=model.nv, nj=model.nv - 6, leg_joint_v_indices=legs)
        self.joint_v = model.canonical_joint_v_indices()          # canonical joint k -> v index
        self.A_pattern = FixedPatternMatrix(self.layout.constraint_mask())
        self.P_pattern = FixedPatternMatrix(self.layout.cost_mask(), upper_triangular=True)
        self._solver: osqp.OSQP | None = None
        self._last: WbcSolution | None = None
        self.failed_solves = 0
        self.description = model.description
        names = self.description.joint_names
        unknown = [name for name, _ in self.settings.torque_limit_overrides_nm if name not in names]
        if unknown:
            raise InputError(f"torque limit override for unknown joint(s) {unknown}")
        self._overrides = [(names.index(name), float(limit))
                           for name, limit in self.settings.torque_limit_overrides_nm]
        unknown = [o[0] for o in self.settings.position_limit_overrides_rad if o[0] not in names]
        if unknown:
            raise InputError(f"position limit override for unknown joint(s) {unknown}")
        self.position_lower = self.description.position_lower_rad.copy()
        self.position_upper = self.description.position_upper_rad.copy()
        for name, low, high in self.settings.position_limit_overrides_rad:
            if not low < high:
                raise InputError(f"position limit override for {name}: lower {low} must be < upper {high}")
            self.position_lower[names.index(name)] = low
            self.position_upper[names.index(name)] = high

    # ------------------------------------------------------------------------------------------------
    def solve(self, q: np.ndarray, v: np.ndarray, refs: WbcReferences) -> WbcSolution:
        """Solve the QP for the model state (q, v) (already passed to ``model.update``) and references."""
        start = time.perf_counter()
        A, lower, upper = self._constraints(q, v, refs)
        P, q_cost, wrench_d = self._cost(q, v, refs)
        solution = self._run_osqp(P, q_cost, A, lower, upper)
        lay = self.layout
        if solution is None:
            result = self._fallback(wrench_d)
        else:
            x, info = solution
            qdd = x[lay.qdd]
            forces = x[lay.force].reshape(NUM_LEGS, 3)
            tau_v = self._torques(qdd, forces)
            result = WbcSolution(tau=tau_v, qdd=qdd, forces=forces, slacks=x[lay.slack].reshape(NUM_LEGS, 3),
                                 desired_wrench=wrench_d, status=info.status, status_val=int(info.status_val),
                                 iterations=int(info.iter), solve_time_s=float(info.solve_time))
            self._last = result
        result.cycle_time_s = time.perf_counter() - start
        return result

    # ------------------------------------------------------------------------------------------------
    def _torques(self, qdd: np.ndarray, forces: np.ndarray) -> np.ndarray:
        m = self.model
        tau_v = m.mass_matrix()[6:] @ qdd + m.nonlinear_effects()[6:]
        for leg in range(NUM_LEGS):
            tau_v -= m.foot_jacobian(leg)[:, 6:].T @ forces[leg]
        return tau_v[self.joint_v - 6]

    def _fallback(self, wrench_d: np.ndarray) -> WbcSolution:
        """QP not solved: decay the previous solution (never raise out of the control loop)."""
        self.failed_solves += 1
        last = self._last
        nj = self.layout.nj
        if last is None:
            tau = np.zeros(nj)
            qdd = np.zeros(self.layout.nv)
            forces = np.zeros((NUM_LEGS, 3))
        else:
            tau, qdd, forces = 0.9 * last.tau, last.qdd, last.forces
        result = WbcSolution(tau=tau, qdd=qdd, forces=forces, slacks=np.zeros((NUM_LEGS, 3)),
                             desired_wrench=wrench_d, status="fallback", status_val=-1, iterations=0,
                             solve_time_s=0.0, fallback=True)
        self._last = result
        return result

    def _run_osqp(self, P, q_cost, A, lower, upper):
        P_values = self.P_pattern.values_from(P)
        A_values = self.A_pattern.values_from(A)
        s = self.settings
        if not (np.all(np.isfinite(P_values)) and np.all(np.isfinite(A_values)) and np.all(np.isfinite(q_cost))
                and not np.any(np.isnan(lower)) and not np.any(np.isnan(upper))):
            return None
        if self._solver is None:
            self._solver = osqp.OSQP()
            self._solver.setup(self.P_pattern.with_values(P_values), q_cost,
                               self.A_pattern.with_values(A_values), lower, upper, verbose=False,
                               warm_starting=True, polishing=False, max_iter=s.max_iterations,
                               eps_abs=s.eps_abs, eps_rel=s.eps_rel, adaptive_rho=True)
        else:
            self._solver.update(Px=P_values, q=q_cost, Ax=A_values, l=lower, u=upper)
        try:
            result = self._solver.solve(raise_error=False)
        except ValueError:
            return None
        if result.info.status_val not in self.SOLVED or not np.all(np.isfinite(result.x)):
            return None
        return result.x, result.info

    # ------------------------------------------------------------------------------------------------
    def _cost(self, q: np.ndarray, v: np.ndarray, refs: WbcReferences):
        m, lay, s = self.model, self.layout, self.settings
        com = m.com()
        inertia = self._centroidal_rotational_inertia(q, v)
        wrench_d = desired_com_wrench(m.total_mass_kg, inertia, com, m.com_velocity(),
                                      self._base_rotation(q), self._base_angular_velocity_world(q, v),
                                      refs, self.gains)
        G = np.zeros((6, lay.n_vars))
        contact_points = m.foot_positions() - self.description.foot_radius_m * refs.normals
        for leg in range(NUM_LEGS):
            cols = lay.leg_cols(lay.force, leg)
            G[0:3, cols] = np.eye(3)
            G[3:6, cols] = skew(contact_points[leg] - com)
        Q = np.diag(s.wrench_weights)
        P = G.T @ Q @ G
        P[lay.qdd, lay.qdd] += s.qdd_regularisation * np.eye(lay.nv)
        P[lay.force, lay.force] += s.force_regularisation * np.eye(lay.n_force)
        if s.torque_regularisation is not None:
            r_tau = np.zeros(lay.nv - 6)
            r_tau[self.joint_v - 6] = np.asarray(s.torque_regularisation, dtype=float)
            J_joints = m.foot_jacobians()[:, 6:]
            P[lay.force, lay.force] += J_joints @ np.diag(r_tau) @ J_joints.T
        P[lay.slack, lay.slack] += s.slack_weight * np.eye(lay.n_force)
        q_cost = -G.T @ Q @ wrench_d
        return P, q_cost, wrench_d

    def _constraints(self, q: np.ndarray, v: np.ndarray, refs: WbcReferences):
        m, lay, s = self.model, self.layout, self.settings
        A = np.zeros((lay.n_rows, lay.n_vars))
        lower = np.full(lay.n_rows, -INF)
        upper = np.full(lay.n_rows, INF)
        M, h = m.mass_matrix(), m.nonlinear_effects()
        jacobians = [m.foot_jacobian(leg) for leg in range(NUM_LEGS)]
        djdq = m.foot_djdqs()
        # Floating-base dynamics: M_u qdd - J_u^T F = -h_u
        A[lay.dynamics_rows, lay.qdd] = M[:6]
        for leg in range(NUM_LEGS):
            A[lay.dynamics_rows, lay.leg_cols(lay.force, leg)] = -jacobians[leg][:, :6].T
        lower[lay.dynamics_rows] = upper[lay.dynamics_rows] = -h[:6]
        # Stance and swing tasks at the acceleration level.
        task_acc = swing_accelerations(m.foot_positions(), m.foot_velocities(), refs, self.gains)
        for leg in range(NUM_LEGS):
            low = slice(lay.task_low_rows.start + 3 * leg, lay.task_low_rows.start + 3 * leg + 3)
            high = slice(lay.task_high_rows.start + 3 * leg, lay.task_high_rows.start + 3 * leg + 3)
            target = task_acc[leg] - djdq[leg]
            A[low, lay.qdd] = jacobians[leg]
            A[high, lay.qdd] = jacobians[leg]
            A[low, lay.leg_cols(lay.slack, leg)] = -np.eye(3)
            A[high, lay.leg_cols(lay.slack, leg)] = np.eye(3)
            slack_rows = slice(lay.slack_rows.start + 3 * leg, lay.slack_rows.start + 3 * leg + 3)
            A[slack_rows, lay.leg_cols(lay.slack, leg)] = np.eye(3)
            lower[slack_rows] = 0.0
            if refs.stance[leg]:
                lower[low] = upper[low] = target      # slack pinned to zero below: an equality
                upper[slack_rows] = 0.0
            else:
                upper[low] = target                   # J qdd - eta <= target
                lower[high] = target                  # J qdd + eta >= target
        # Friction pyramids and normal force bounds.
        mu = s.friction_coefficient
        for leg in range(NUM_LEGS):
            n = refs.normals[leg] / np.linalg.norm(refs.normals[leg])
            t1, t2 = tangent_basis(n)
            rows = slice(lay.friction_rows.start + FRICTION_ROWS_PER_LEG * leg,
                         lay.friction_rows.start + FRICTION_ROWS_PER_LEG * (leg + 1))
            A[rows, lay.leg_cols(lay.force, leg)] = np.vstack([t1 - mu * n, -t1 - mu * n, t2 - mu * n,
                                                                 -t2 - mu * n, n])
            upper[rows.start:rows.start + 4] = 0.0
            if refs.stance[leg]:
                f_max = s.min_normal_force_n + refs.load_factor[leg] * (s.max_normal_force_n - s.min_normal_force_n)
                lower[rows.stop - 1] = min(s.min_normal_force_n * refs.load_factor[leg], f_max)
                upper[rows.stop - 1] = f_max
            else:
                lower[rows.stop - 1] = upper[rows.stop - 1] = 0.0
        # Torque limits from the actuated dynamics (rows in Pinocchio's joint order).
        q_joints = self._canonical_joint_positions(q)
        tau_min, tau_max = self._torque_limits(q_joints)
        A[lay.torque_rows, lay.qdd] = M[6:]
        for leg in range(NUM_LEGS):
            A[lay.torque_rows, lay.leg_cols(lay.force, leg)] = -jacobians[leg][:, 6:].T
        rows_of_canonical = self.joint_v - 6
        lower[lay.torque_rows.start + rows_of_canonical] = tau_min - h[6:][rows_of_canonical]
        upper[lay.torque_rows.start + rows_of_canonical] = tau_max - h[6:][rows_of_canonical]
        # Joint kinematic limits as acceleration bounds.
        A[lay.joint_acc_rows, 6:lay.nv] = np.eye(lay.nj)
        qdd_min, qdd_max = self._joint_acceleration_bounds(q_joints, v[self.joint_v])
        lower[lay.joint_acc_rows.start + rows_of_canonical] = qdd_min
        upper[lay.joint_acc_rows.start + rows_of_canonical] = qdd_max
        return A, lower, upper

    def _torque_limits(self, q_joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Robot torque limits [N m] at q, tightened by the settings' overrides (e.g. a damaged joint)."""
        tau_min, tau_max = self.description.torque_limits(q_joints)
        for index, limit in self._overrides:
            tau_max[index] = min(tau_max[index], limit)
            tau_min[index] = max(tau_min[index], -limit)
        return tau_min, tau_max

    def _joint_acceleration_bounds(self, q_joints: np.ndarray, qd_joints: np.ndarray):
        """Accelerations that reach each end stop at zero velocity within the horizon (thesis eq.)."""
        dt = self.settings.joint_limit_horizon_periods * self.settings.control_period_s
        qdd_max = 2.0 / dt**2 * (self.position_upper - q_joints - dt * qd_joints)
        qdd_min = 2.0 / dt**2 * (self.position_lower - q_joints - dt * qd_joints)
        # Beyond a limit the two bounds cross: keep the one that brings the joint back.
        qdd_min = np.minimum(qdd_min, qdd_max)
        return qdd_min, qdd_max

    # -- state helpers ---------------------------------------------------------------------------------
    def _canonical_joint_positions(self, q: np.ndarray) -> np.ndarray:
        return self.model.split_q(q)[2]

    @staticmethod
    def _base_rotation(q: np.ndarray) -> np.ndarray:
        return pin.Quaternion(q[6], q[3], q[4], q[5]).toRotationMatrix()

    def _base_angular_velocity_world(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        return self._base_rotation(q) @ v[3:6]

    def _centroidal_rotational_inertia(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        pin.ccrba(self.model.model, self.model.data, q, v)
        return np.array(self.model.data.Ig.inertia)
