"""The passive whole-body controller (sWBC) of the thesis, solved with OSQP or DAQP (dense active set).

    min  || W_com(F) - W_com,d ||_Q^2 + ||u||_R^2 + alpha ||eta||^2        u = [qdd, F, eta]
    s.t. M_u qdd + h_u = J_st,u^T F                     (floating-base dynamics, 6 rows)
         J_st qdd + dJ_st v = a_st                      (stance feet; a_st = stance-task impedance)
         -eta <= J_sw qdd + dJ_sw v - a_sw,d <= eta     (swing task with one slack per direction)
         friction pyramid inscribed in the cone about the terrain normal, F_min <= n.F <= F_max(load)
         tau_min(q) <= M_a qdd + h_j - J_st,j^T F <= tau_max(q)
         qdd_j within the bounds that reach the end stop at zero velocity in 10 control periods
    tau* = M_a qdd* + h_j - J_st,j^T F*

W_com is the centroidal wrench of the contact forces about the CoM (world frame): (sum F_i,
sum (p_i - c) x F_i), which equals J_st,com^T F of the thesis' CoM coordinates; the dynamics rows use
Pinocchio's base coordinates (first 6 rows of M qdd + h = S^T tau + J^T F), an equivalent constraint.

Solvers (``WbcSettings.qp_solver``): "osqp" (default; ADMM, sparse, warm-started) stops at its tolerance;
"daqp", a dual active-set solver for small dense QPs, returns the exact optimum in 4x less time than OSQP's
update and solve. The QP's cost barely penalises forces that cancel between stance legs (regularisation
1e-5), so OSQP's stopping point at eps 1e-4 leaves the joint torques 25-35 N m (median, bench states) from
the optimum. OSQP stays the default because HyQ walks the stairs better with it: ViTAL's stairs at 0.2-0.5
m/s from 3 starts each, 9 of 12 with OSQP (3 leg collisions), 6 of 12 with DAQP, 9 of 12 with DAQP and
force_rate_regularisation 0.1 (12 leg collisions).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import daqp
import numpy as np
import osqp
import pinocchio as pin

from tal_core.errors import InputError
from tal_core.legs import NUM_LEGS
from tal_core.robot_model import RobotModel

from .qp_layout import FRICTION_ROWS_PER_LEG, INF, FixedPatternMatrix, QpLayout
from .tasks import (
    WbcGains,
    WbcReferences,
    centroidal_wrench_map,
    desired_com_wrench,
    swing_accelerations,
    tangent_basis,
)

GRAVITY = np.array([0.0, 0.0, -9.81])


def joint_acceleration_bounds(q: np.ndarray, qd: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                              horizon_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(qdd_min, qdd_max) [rad/s^2]: the accelerations that reach each end stop (lower, upper [rad]) at zero
    velocity within ``horizon_s`` [s] from (q [rad], qd [rad/s]) (thesis eq.)."""
    qdd_max = 2.0 / horizon_s**2 * (upper - q - horizon_s * qd)
    qdd_min = 2.0 / horizon_s**2 * (lower - q - horizon_s * qd)
    # Beyond a limit the two bounds cross: keep the one that brings the joint back.
    return np.minimum(qdd_min, qdd_max), qdd_max


QP_SOLVERS = ("daqp", "osqp")
DAQP_EQUALITY = 5   # DAQP's sense flags: active + immutable (an equality row)
DAQP_SOFT = 8       # a row DAQP may violate (penalised) when the QP is infeasible otherwise
DAQP_SOLVED = {1: "solved", 2: "solved (soft constraints relaxed)"}


@dataclass(frozen=True)
class QpInfo:
    """What a solve reports, whichever solver ran: status text, its code (1 solved), iterations, time [s]."""

    status: str
    status_val: int
    iter: int
    solve_time: float


@dataclass(frozen=True)
class WbcSettings:
    """QP weights and limits. Units: forces [N], accelerations [m/s^2, rad/s^2]."""

    wrench_weights: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0)   # Q: Fx Fy Fz Tx Ty Tz
    qdd_regularisation: float = 1e-6
    force_regularisation: float = 1e-5
    # w ||F - F_prev||^2: contact forces kept near the previous cycle's (0: off). With DAQP's exact optimum the
    # joint torques jumped more from tick to tick than with OSQP's warm-started stopping point (trot 0.5 m/s,
    # p99 of the largest step 59.7 against 28.7 N m); w = 0.1 brought it to 25.1 N m.
    force_rate_regularisation: float = 0.0
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
    qp_solver: str = "osqp"            # "osqp" (ADMM, to eps_abs/rel) or "daqp" (dense active set, exact optimum)
    # 1e-4 is ample for forces of hundreds of newtons and cuts OSQP's iterations on two-leg stances
    # from ~300 to ~25 (measured on HyQ trot states).
    eps_abs: float = 1e-4
    eps_rel: float = 1e-4
    # c3WBC (contact_model "compliant"): desired penetrations eps become decision variables with
    # F = K eps + D deps/dt and J_st qdd + dJ_st v = -d2eps/dt2 (finite differences over the last cycles).
    contact_model: str = "rigid"
    penetration_regularisation: float = 1.0          # weight on ||eps||^2 (eps in m; wrench error in N)
    default_stiffness_n_per_m: float = 2e6           # used when the references carry no impedance
    default_damping_ns_per_m: float = 400.0
    # Normal penetration of the last two cycles: "desired" (the thesis: the QP's own previous solutions) or
    # "measured" (the foot's sinking since its touchdown sample and its normal velocity). With "desired" the
    # model integrates open loop and drifts from the real sinking wherever the terrain model is off (a fresh
    # TCE estimate, damping-dominated touchdowns); "measured" keeps F = K eps + D deps/dt anchored to it.
    penetration_history: str = "desired"
    # c3WBC load ramps: T = 4.6 / sqrt(k / m_e) (thesis) is 0.51 s on T1 with two legs in stance, longer than
    # a whole trot stance (0.4 s): the load factor then never reaches 1, the stance legs' force bound falls
    # from mid-stance and HyQ dropped onto T1 within 1.1 s (measured). The ramp is capped at this fraction of
    # the gait's stance duration (the thesis' crawl on T1: 0.41 s of 1.6 s, under the cap).
    max_load_ramp_stance_fraction: float = 0.25

    @property
    def joint_limit_horizon_s(self) -> float:
        """[s] horizon of the joint-limit acceleration bounds."""
        return self.joint_limit_horizon_periods * self.control_period_s

    def __post_init__(self) -> None:
        if self.contact_model not in ("rigid", "compliant"):
            raise InputError(f"contact_model must be 'rigid' or 'compliant', got {self.contact_model!r}")
        if self.qp_solver not in QP_SOLVERS:
            raise InputError(f"qp_solver must be one of {QP_SOLVERS}, got {self.qp_solver!r}")
        if self.penetration_history not in ("desired", "measured"):
            raise InputError(f"penetration_history must be 'desired' or 'measured', got {self.penetration_history!r}")
        if not 0.0 < self.max_load_ramp_stance_fraction <= 0.5:
            raise InputError(f"max_load_ramp_stance_fraction must be in (0, 0.5], "
                             f"got {self.max_load_ramp_stance_fraction!r}")


# WbcSettings read at every solve (the others shape the QP's layout and static blocks)
RUNTIME_SETTINGS = frozenset({"friction_coefficient", "min_normal_force_n", "max_normal_force_n"})


@dataclass
class WbcSolution:
    """Result of one control cycle."""

    tau: np.ndarray               # (nj,) [N m] joint torques, canonical order
    qdd: np.ndarray               # (nv,) generalised accelerations (Pinocchio convention)
    forces: np.ndarray            # (4, 3) [N] ground reaction forces on the feet, world frame
    slacks: np.ndarray            # (4, 3) [m/s^2] swing-task slacks
    desired_wrench: np.ndarray    # (6,) [N, N m] world frame, about the CoM
    delivered_wrench: np.ndarray  # (6,) [N, N m] the same wrench of ``forces`` (what the QP delivered)
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
        self.compliant = self.settings.contact_model == "compliant"
        self.layout = QpLayout(nv=model.nv, nj=model.nv - 6, leg_joint_v_indices=legs, compliant=self.compliant)
        # Desired penetrations of the previous two cycles (world frame, per leg) for the finite differences.
        self._eps_prev = np.zeros((NUM_LEGS, 3))
        self._eps_prev2 = np.zeros((NUM_LEGS, 3))
        self._eps_offset = np.zeros((NUM_LEGS, 3))   # 2 eps_{k-1} - eps_{k-2} of the stance legs [m]
        self._was_stance = np.zeros(NUM_LEGS, dtype=bool)
        self.joint_v = model.canonical_joint_v_indices()          # canonical joint k -> v index
        pin_model = model.model
        self._joint_q = np.array([pin_model.joints[pin_model.getJointId(name)].idx_q
                                  for name in model.description.joint_names])
        self.A_pattern = FixedPatternMatrix(self.layout.constraint_mask())
        self.P_pattern = FixedPatternMatrix(self.layout.cost_mask(), upper_triangular=True)
        self._prepare_static_blocks()
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

    def update_settings(self, **changes: float) -> None:
        """Change settings read at every solve (``RUNTIME_SETTINGS``) from the next one on. InputError for
        another setting (fixed by the QP's layout and static blocks) or an invalid value."""
        fixed = sorted(set(changes) - RUNTIME_SETTINGS)
        if fixed:
            raise InputError(f"WBC settings {fixed} are fixed at construction; at run time only "
                             f"{sorted(RUNTIME_SETTINGS)} change")
        settings = replace(self.settings, **{name: float(value) for name, value in changes.items()})
        if not (np.isfinite(settings.friction_coefficient) and settings.friction_coefficient > 0.0):
            raise InputError(f"friction_coefficient must be > 0, got {settings.friction_coefficient!r}")
        if not 0.0 <= settings.min_normal_force_n <= settings.max_normal_force_n < INF:
            raise InputError(f"normal force bounds must satisfy 0 <= min <= max, got min "
                             f"{settings.min_normal_force_n!r} N, max {settings.max_normal_force_n!r} N")
        self.settings = settings
        self._friction_key = None  # the pyramids are rebuilt with the new coefficient

    # ------------------------------------------------------------------------------------------------
    def solve(self, q: np.ndarray, v: np.ndarray, refs: WbcReferences) -> WbcSolution:
        """Solve the QP for the model state (q, v) (already passed to ``model.update``) and references."""
        start = time.perf_counter()
        A, lower, upper = self._constraints(q, v, refs)
        P, q_cost, wrench_d = self._cost(q, v, refs)
        solution = self._run_qp(P, q_cost, A, lower, upper)
        relaxed = False
        if solution is None:
            # Conflicting hard constraints (e.g. a torque limit the rigid stance cannot respect): re-solve
            # with the stance conditions softened by the same penalised slacks as the swing task.
            self.failed_solves += 1
            relaxed = True
            solution = self._run_qp(P, q_cost, A, *self._relax_stance(lower, upper, refs), relaxed=True)
        lay = self.layout
        if solution is None:
            result = self._fallback(wrench_d)
        else:
            x, info = solution
            qdd = x[lay.qdd]
            forces = x[lay.force].reshape(NUM_LEGS, 3)
            tau_v = self._torques(qdd, forces)
            if self.compliant:
                # The QP's variable is the penetration acceleration u = d2eps/dt2 [m/s^2] (scaled like qdd):
                # eps_k = dt^2 u + 2 eps_{k-1} - eps_{k-2}.
                dt2 = self.settings.control_period_s ** 2
                eps = np.where(refs.stance[:, None],
                               dt2 * x[lay.penetration].reshape(NUM_LEGS, 3) + self._eps_offset, 0.0)
                self._eps_prev2, self._eps_prev = self._eps_prev, eps
            result = WbcSolution(tau=tau_v, qdd=qdd, forces=forces, slacks=x[lay.slack].reshape(NUM_LEGS, 3),
                                 desired_wrench=wrench_d, delivered_wrench=self._wrench_map @ forces.ravel(),
                                 status=info.status, status_val=int(info.status_val),
                                 iterations=int(info.iter), solve_time_s=float(info.solve_time),
                                 fallback=relaxed)
            if relaxed:
                result.status = f"relaxed stance ({info.status})"
            if self.compliant:
                result.extras["penetration"] = self._eps_prev.copy()
            self._last = result
        result.cycle_time_s = time.perf_counter() - start
        return result

    # ------------------------------------------------------------------------------------------------
    def _torques(self, qdd: np.ndarray, forces: np.ndarray) -> np.ndarray:
        m = self.model
        tau_v = m.mass_matrix()[6:] @ qdd + m.nonlinear_effects()[6:] - m.foot_jacobians()[:, 6:].T @ forces.ravel()
        return tau_v[self.joint_v - 6]

    def _relax_stance(self, lower: np.ndarray, upper: np.ndarray, refs: WbcReferences):
        """Bounds with the stance rows turned into slack-bounded rows like the swing task's."""
        lower, upper = lower.copy(), upper.copy()
        stance3 = np.repeat(refs.stance, 3)
        sl = self._slices
        low_rows = sl["task_low_rows"].start + self._task_row_index[stance3]
        high_rows = sl["task_high_rows"].start + self._task_row_index[stance3]
        lower[high_rows] = lower[low_rows]        # J qdd + eta >= target
        lower[low_rows] = -INF                    # J qdd - eta <= target
        upper[sl["slack_rows"].start + self._task_row_index[stance3]] = INF
        return lower, upper

    def _fallback(self, wrench_d: np.ndarray) -> WbcSolution:
        """Even the relaxed QP failed: decay the previous solution (never raise out of the control loop)."""
        last = self._last
        nj = self.layout.nj
        if last is None:
            tau = np.zeros(nj)
            qdd = np.zeros(self.layout.nv)
            forces = np.zeros((NUM_LEGS, 3))
        else:
            tau, qdd, forces = 0.9 * last.tau, last.qdd, last.forces
        result = WbcSolution(tau=tau, qdd=qdd, forces=forces, slacks=np.zeros((NUM_LEGS, 3)),
                             desired_wrench=wrench_d, delivered_wrench=self._wrench_map @ forces.ravel(),
                             status="fallback", status_val=-1, iterations=0,
                             solve_time_s=0.0, fallback=True)
        self._last = result
        return result

    def _run_qp(self, P, q_cost, A, lower, upper, relaxed: bool = False) -> tuple[np.ndarray, QpInfo] | None:
        """(x, info) of the QP, or None (non-finite data, infeasible, or not solved within the limits).
        relaxed: the retry after a failed solve (DAQP: the joint-limit rows may then give way too)."""
        if not (np.all(np.isfinite(P)) and np.all(np.isfinite(A)) and np.all(np.isfinite(q_cost))
                and not np.any(np.isnan(lower)) and not np.any(np.isnan(upper))):
            return None
        if self.settings.qp_solver == "daqp":
            return self._run_daqp(P, q_cost, A, lower, upper, relaxed)
        return self._run_osqp(P, q_cost, A, lower, upper)

    def _run_daqp(self, P, q_cost, A, lower, upper, relaxed: bool) -> tuple[np.ndarray, QpInfo] | None:
        # Rows with equal bounds are equalities (the dynamics, the stance tasks, pinned forces and slacks);
        # bounds at +-INF (1e30, DAQP's infinity too) are absent.
        sense = np.where(lower == upper, DAQP_EQUALITY, 0).astype(np.int32)
        if relaxed:
            # In the retry the joint-limit acceleration bounds (stop at the end stop within a horizon) may give
            # way too: a joint at or past its stop asks for accelerations the stance feet cannot give (HyQ's
            # neutral pose, knees at +-1.6 rad, left even the relaxed QP infeasible). OSQP returned an
            # inaccurate point there; DAQP reports the infeasibility.
            sense[self._slices["joint_acc_rows"]] = DAQP_SOFT
        x, _, flag, info = daqp.solve(P, q_cost, A, upper, lower, sense, iter_limit=self.settings.max_iterations)
        if flag not in DAQP_SOLVED or not np.all(np.isfinite(x)):
            return None
        return x, QpInfo(DAQP_SOLVED[flag], 1, int(info["iterations"]),
                         float(info["solve_time"]) + float(info["setup_time"]))

    def _run_osqp(self, P, q_cost, A, lower, upper) -> tuple[np.ndarray, QpInfo] | None:
        P_values = self.P_pattern.values_from(P)
        A_values = self.A_pattern.values_from(A)
        s = self.settings
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
        info = result.info
        return result.x, QpInfo(str(info.status), int(info.status_val), int(info.iter), float(info.solve_time))

    # ------------------------------------------------------------------------------------------------
    def _prepare_static_blocks(self) -> None:
        """Preallocate the dense QP matrices and fill the entries that never change."""
        lay = self.layout
        self._slices = {name: getattr(lay, name) for name in (
            "qdd", "force", "slack", "dynamics_rows", "task_low_rows", "task_high_rows", "friction_rows",
            "torque_rows", "joint_acc_rows", "slack_rows")}
        sl = self._slices
        self._A = np.zeros((lay.n_rows, lay.n_vars))
        A = self._A
        eye_f = np.eye(lay.n_force)
        A[sl["task_low_rows"], sl["slack"]] = -eye_f
        A[sl["task_high_rows"], sl["slack"]] = eye_f
        A[sl["slack_rows"], sl["slack"]] = eye_f
        A[sl["joint_acc_rows"], 6:lay.nv] = np.eye(lay.nj)
        self._P = np.zeros((lay.n_vars, lay.n_vars))
        s = self.settings
        self._P_static = np.zeros((lay.n_vars, lay.n_vars))
        self._P_static[sl["qdd"], sl["qdd"]] = s.qdd_regularisation * np.eye(lay.nv)
        self._P_static[sl["force"], sl["force"]] = s.force_regularisation * eye_f
        self._P_static[sl["slack"], sl["slack"]] = s.slack_weight * eye_f
        if self.compliant:
            # Variable u = d2eps/dt2: eps = dt^2 u + offset, so the weight on ||eps||^2 is weight * dt^4 on ||u||^2.
            self._P_static[lay.penetration, lay.penetration] = (s.penetration_regularisation
                                                                * s.control_period_s**4 * eye_f)
            self._model_rows = lay.compliant_rows.start + np.arange(lay.n_force)
            self._eps_bound_rows = lay.compliant_rows.start + lay.n_force + np.arange(lay.n_force)
            A[self._model_rows, sl["force"]] = eye_f
            three = np.arange(3)
            legs3 = 3 * np.arange(NUM_LEGS)[:, None] + three            # (4, 3) a leg's three rows / columns
            rows = (self._model_rows[legs3], self._eps_bound_rows[legs3], sl["task_low_rows"].start + legs3,
                    sl["task_high_rows"].start + legs3)
            cols = lay.penetration.start + legs3
            blocks = np.concatenate([r[:, :, None] * lay.n_vars + cols[:, None, :]
                                     for r in (rows[1], rows[0], rows[2], rows[3])])   # frame, model, task low, high
            self._compliant_index = (rows, blocks)
            self._frames_key: bytes | None = None
        self._Q = np.diag(s.wrench_weights)
        self._friction_key: bytes | None = None
        # Rows of the torque/joint blocks in Pinocchio's joint order that hold each canonical joint.
        self._rows_of_canonical = self.joint_v - 6
        self._task_row_index = np.arange(lay.n_force)

    def _cost(self, q: np.ndarray, v: np.ndarray, refs: WbcReferences):
        m, lay, s, sl = self.model, self.layout, self.settings, self._slices
        com = m.com()
        inertia = self._centroidal_rotational_inertia(q, v)
        wrench_d = desired_com_wrench(m.total_mass_kg, inertia, com, m.com_velocity(),
                                      self._base_rotation(q), self._base_angular_velocity_world(q, v),
                                      refs, self.gains)
        # Centroidal wrench of the contact forces: W = A_F F, A_F = [I ...; skew(p_i - c) ...] (6 x 12).
        A_F = centroidal_wrench_map(m.foot_positions() - self.description.foot_radius_m * refs.normals, com)
        self._wrench_map = A_F  # the delivered wrench of this cycle's forces is A_F F
        P = self._P
        P[:] = self._P_static
        P[sl["force"], sl["force"]] += A_F.T @ self._Q @ A_F
        if s.torque_regularisation is not None:
            r_tau = np.zeros(lay.nv - 6)
            r_tau[self.joint_v - 6] = np.asarray(s.torque_regularisation, dtype=float)
            J_joints = m.foot_jacobians()[:, 6:]
            P[sl["force"], sl["force"]] += J_joints @ np.diag(r_tau) @ J_joints.T
        q_cost = np.zeros(lay.n_vars)
        q_cost[sl["force"]] = -A_F.T @ self._Q @ wrench_d
        w_rate = s.force_rate_regularisation
        if w_rate > 0.0 and self._last is not None:
            P[sl["force"], sl["force"]] += w_rate * np.eye(lay.n_force)
            q_cost[sl["force"]] -= w_rate * self._last.forces.ravel()
        if self.compliant:
            # w ||eps||^2 with eps = dt^2 u + offset: the linear term w dt^2 offset on u.
            dt = self.settings.control_period_s
            q_cost[self.layout.penetration] = (self.settings.penetration_regularisation * dt**2
                                               * self._eps_offset.ravel())
        return P, q_cost, wrench_d

    def _constraints(self, q: np.ndarray, v: np.ndarray, refs: WbcReferences):
        m, lay, s, sl = self.model, self.layout, self.settings, self._slices
        A = self._A
        lower = np.full(lay.n_rows, -INF)
        upper = np.full(lay.n_rows, INF)
        M, h = m.mass_matrix(), m.nonlinear_effects()
        J = m.foot_jacobians()                     # (12, nv), legs stacked
        djdq = m.foot_djdqs().reshape(-1)          # (12,)
        stance3 = np.repeat(refs.stance, 3)        # per task row
        # Floating-base dynamics: M_u qdd - J_u^T F = -h_u
        A[sl["dynamics_rows"], sl["qdd"]] = M[:6]
        A[sl["dynamics_rows"], sl["force"]] = -J[:, :6].T
        lower[sl["dynamics_rows"]] = upper[sl["dynamics_rows"]] = -h[:6]
        # Stance and swing tasks at the acceleration level (stance rows: equalities, slacks pinned to 0).
        target = swing_accelerations(m.foot_positions(), m.foot_velocities(), refs, self.gains).reshape(-1) - djdq
        A[sl["task_low_rows"], sl["qdd"]] = J
        A[sl["task_high_rows"], sl["qdd"]] = J
        low_rows = sl["task_low_rows"].start + self._task_row_index
        high_rows = sl["task_high_rows"].start + self._task_row_index
        upper[low_rows] = target                                   # J qdd - eta <= target
        lower[low_rows] = np.where(stance3, target, -INF)          # stance: equality
        lower[high_rows] = np.where(stance3, -INF, target)         # swing: J qdd + eta >= target
        slack_rows = sl["slack_rows"].start + self._task_row_index
        lower[slack_rows] = 0.0
        upper[slack_rows] = np.where(stance3, 0.0, INF)
        # Friction pyramids (rebuilt only when the normals change) and normal force bounds.
        self._fill_friction_rows(refs.normals)
        normal_rows = sl["friction_rows"].start + FRICTION_ROWS_PER_LEG * np.arange(NUM_LEGS) + 4
        pyramid_rows = (sl["friction_rows"].start + FRICTION_ROWS_PER_LEG * np.arange(NUM_LEGS)[:, None]
                        + np.arange(4)).reshape(-1)
        upper[pyramid_rows] = 0.0
        f_max = s.min_normal_force_n + refs.load_factor * (s.max_normal_force_n - s.min_normal_force_n)
        f_min = np.minimum(s.min_normal_force_n * refs.load_factor, f_max)
        lower[normal_rows] = np.where(refs.stance, f_min, 0.0)
        upper[normal_rows] = np.where(refs.stance, f_max, 0.0)
        # Torque limits from the actuated dynamics (rows in Pinocchio's joint order).
        q_joints = self._canonical_joint_positions(q)
        tau_min, tau_max = self._torque_limits(q_joints)
        A[sl["torque_rows"], sl["qdd"]] = M[6:]
        A[sl["torque_rows"], sl["force"]] = -J[:, 6:].T
        torque_rows = sl["torque_rows"].start + self._rows_of_canonical
        lower[torque_rows] = tau_min - h[6:][self._rows_of_canonical]
        upper[torque_rows] = tau_max - h[6:][self._rows_of_canonical]
        # Joint kinematic limits as acceleration bounds.
        qdd_min, qdd_max = self._joint_acceleration_bounds(q_joints, v[self.joint_v])
        joint_rows = sl["joint_acc_rows"].start + self._rows_of_canonical
        lower[joint_rows] = qdd_min
        upper[joint_rows] = qdd_max
        if self.compliant:
            self._compliant_rows(refs, target, lower, upper)
        return A, lower, upper

    def _compliant_rows(self, refs: WbcReferences, target: np.ndarray, lower: np.ndarray,
                        upper: np.ndarray) -> None:
        """c3-stance task: F = K eps + D deps, J qdd + dJ v = -d2eps, n.eps >= 0 (thesis' c3WBC)."""
        s = self.settings
        A = self._A
        dt = s.control_period_s
        touchdown = refs.stance & ~self._was_stance
        velocities = self.model.foot_velocities()
        normals = refs.normals / np.linalg.norm(refs.normals, axis=1, keepdims=True)
        for leg in np.flatnonzero(touchdown):
            # A fresh contact starts undeformed but with the foot's measured normal velocity (eps_dot = -n.v):
            # starting from rest would make the model demand a force the moving foot does not produce.
            n = normals[leg]
            self._eps_prev[leg] = 0.0
            self._eps_prev2[leg] = float(n @ velocities[leg]) * n * dt   # eps_{k-2} = eps_{k-1} - eps_dot dt
        self._was_stance = refs.stance.copy()
        if s.penetration_history == "measured":
            feet = self.model.foot_positions()
            for leg in np.flatnonzero(refs.stance):
                n = normals[leg]
                sink = float(n @ (refs.touchdown_position[leg] - feet[leg]))   # [m] along -n since touchdown
                rate = -float(n @ velocities[leg])                             # [m/s]
                for history, value in ((self._eps_prev, sink), (self._eps_prev2, sink - rate * dt)):
                    history[leg] += (value - float(n @ history[leg])) * n       # replace the normal part
        self._eps_offset = np.where(refs.stance[:, None], 2.0 * self._eps_prev - self._eps_prev2, 0.0)
        def per_leg(value: np.ndarray | None, default: float | np.ndarray) -> np.ndarray:
            return np.broadcast_to(default, (NUM_LEGS,)) if value is None else value

        k_n = per_leg(refs.stiffness_normal, s.default_stiffness_n_per_m)
        k_t = per_leg(refs.stiffness_tangential, k_n)
        d_n = per_leg(refs.damping_normal, s.default_damping_ns_per_m)
        d_t = per_leg(refs.damping_tangential, d_n)
        # All four legs at once: contact frames R (rows n, t1, t2), K = R^T diag(k_n, k_t, k_t) R, D alike.
        R = self._contact_frames(normals)
        K = np.einsum("lki,lk,lkj->lij", R, np.column_stack([k_n, k_t, k_t]), R)
        D = np.einsum("lki,lk,lkj->lij", R, np.column_stack([d_n, d_t, d_t]), R)
        stance = refs.stance
        (model_rows, bound_rows, task_low, _), blocks = self._compliant_index
        # The blocks of A, each leg's 3 x 3 at its rows and penetration columns (flat indices into A):
        # contact frame rows; F = K eps_k + D (eps_k - eps_{k-1})/dt with eps_k = dt^2 u + offset (u: the
        # variable), swing legs 0; J qdd + u = -dJ v (the foot follows the penetration; replaces the rigid
        # stance row), low and high task rows alike.
        KD = K + D / dt
        eye = np.where(stance[:, None, None], np.eye(3), 0.0)
        np.put(A, blocks, np.concatenate([R, np.where(stance[:, None, None], -KD * dt**2, 0.0), eye, eye]))
        offset = self._eps_offset
        m = self.model
        g = self.gains
        stance_acc = g.K_st * (refs.touchdown_position - m.foot_positions()) - g.D_st * velocities
        model_rhs = np.einsum("lij,lj->li", KD, offset) - np.einsum("lij,lj->li", D, self._eps_prev) / dt
        task_rhs = target.reshape(NUM_LEGS, 3) - stance_acc
        legs = np.flatnonzero(stance)
        lower[model_rows[legs]] = upper[model_rows[legs]] = model_rhs[legs]   # swing: unbounded (-INF, INF),
        lower[task_low[legs]] = upper[task_low[legs]] = task_rhs[legs]        # F pinned by the friction rows
        # stance: normal penetration >= 0, n.u >= -n.offset / dt^2; swing: u = 0
        bound_low = np.zeros((NUM_LEGS, 3))
        bound_low[legs] = -INF
        bound_low[legs, 0] = -np.einsum("lj,lj->l", normals[legs], offset[legs]) / dt**2
        lower[bound_rows] = bound_low
        upper[bound_rows] = np.where(stance[:, None], INF, 0.0)

    def _contact_frames(self, normals: np.ndarray) -> np.ndarray:
        """(4, 3, 3) rows n, t1, t2 of each leg's contact frame (world), kept while the normals stay."""
        key = normals.tobytes()
        if key != self._frames_key:
            self._frames_key = key
            frames = np.empty((NUM_LEGS, 3, 3))
            for leg in range(NUM_LEGS):
                t1, t2 = tangent_basis(normals[leg])
                frames[leg] = (normals[leg], t1, t2)
            self._frames = frames
        return self._frames

    def _fill_friction_rows(self, normals: np.ndarray) -> None:
        key = normals.tobytes()
        if key == self._friction_key:
            return
        self._friction_key = key
        # Square pyramid inscribed in the cone: each tangential component within mu/sqrt(2) of the normal
        # one, so that also diagonal forces stay inside the true friction cone.
        mu = self.settings.friction_coefficient / np.sqrt(2.0)
        lay = self.layout
        for leg in range(NUM_LEGS):
            n = normals[leg] / np.linalg.norm(normals[leg])
            t1, t2 = tangent_basis(n)
            rows = slice(lay.friction_rows.start + FRICTION_ROWS_PER_LEG * leg,
                         lay.friction_rows.start + FRICTION_ROWS_PER_LEG * (leg + 1))
            self._A[rows, lay.leg_cols(lay.force, leg)] = np.vstack(
                [t1 - mu * n, -t1 - mu * n, t2 - mu * n, -t2 - mu * n, n])

    def _torque_limits(self, q_joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Robot torque limits [N m] at q, tightened by the settings' overrides (e.g. a damaged joint)."""
        tau_min, tau_max = self.description.torque_limits(q_joints)
        for index, limit in self._overrides:
            tau_max[index] = min(tau_max[index], limit)
            tau_min[index] = max(tau_min[index], -limit)
        return tau_min, tau_max

    def _joint_acceleration_bounds(self, q_joints: np.ndarray, qd_joints: np.ndarray):
        """Accelerations that reach each end stop at zero velocity within the horizon (thesis eq.)."""
        return joint_acceleration_bounds(q_joints, qd_joints, self.position_lower, self.position_upper,
                                         self.settings.joint_limit_horizon_s)

    # -- state helpers ---------------------------------------------------------------------------------
    def _canonical_joint_positions(self, q: np.ndarray) -> np.ndarray:
        return q[self._joint_q]

    @staticmethod
    def _base_rotation(q: np.ndarray) -> np.ndarray:
        return pin.Quaternion(q[6], q[3], q[4], q[5]).toRotationMatrix()

    def _base_angular_velocity_world(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        return self._base_rotation(q) @ v[3:6]

    def _centroidal_rotational_inertia(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        pin.ccrba(self.model.model, self.model.data, q, v)
        return np.array(self.model.data.Ig.inertia)
