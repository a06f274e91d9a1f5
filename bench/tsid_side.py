#!/usr/bin/env python3
"""TSID side of the WBC cycle benchmark: run with the TSID venv's python (bench/setup_tsid_venv.sh).

    bench/out/.venv-tsid/bin/python bench/tsid_side.py --states bench/out/wbc_states.npz [--round 1]

Reads the state set written by bench/bench_wbc.py (q, v in Pinocchio's convention, stance masks, swing and
CoM targets, and the problem's limits in Pinocchio's joint order), builds the TSID problem closest to tal's
sWBC and times, per state, ``formulation.computeProblemData(t, q, v)`` + ``solver.solve(hqp)`` +
``formulation.getActuatorForces(sol)`` (TSID's equivalent of ``model.update`` + ``StandardWbc.solve``).
Prints one JSON document on stdout (per stance count: cycle times [ms], failures, QP size); progress on
stderr.

The TSID problem (InverseDynamicsFormulationAccForce, variables [qdd (18), contact forces (3 per stance
foot)]; priority 0 = hard constraints, priority 1 = weighted cost). TSID's tasks are at the acceleration
level, so tal's force-level trunk gains are divided by the mass / the centroidal inertia (the thesis' gains,
"--gains thesis", the default), and the weights are tal's cost written in acceleration units and divided by
m^2 (tal weighs the centroidal force residual m * (a_com - a_com,d) with 1, the torque residual ~ I (dw - dw_d)
with 1, the swing slack with 1e4, the forces with 1e-5):
  * stance feet: ``ContactPoint`` (3D point contact on the foot frame, world-aligned, normal +z, friction
    pyramid with tal's mu 0.8, normal force within 10..1000 N as tal's sWBC), rigid (motion at priority 0,
    Kp = Kd = 0 like tal's K_st = D_st = 0), force regularisation weight 1e-5 / m^2;
  * CoM: ``TaskComEquality``, weight 1, Kp = K_x / m = 2000 / 86.8 = 23 1/s^2, Kd = D_x / m = 4.6 1/s;
  * trunk orientation: ``TaskSE3Equality`` on the base frame with only the angular part in the mask, weight
    (mean of diag(I) / m)^2 = 0.011, Kp = K_theta / I_ii = 1000 / (3.7, 11.3, 12.2) per axis (centroidal
    inertia of the nominal pose), Kd = D_theta / I_ii;
  * swing feet: ``TaskSE3Equality`` on each swing foot frame, linear part only, world-aligned, Kp = 2000,
    Kd = 20 (tal's K_sw, D_sw, already acceleration gains), weight 1e4 / m^2 = 1.33 (tal: an equality with a
    slack weighted 1e4);
  * posture: ``TaskJointPosture`` to the nominal pose, weight 1e-6, Kp = 10, Kd = 2 sqrt(10) (tal has only a
    1e-6 qdd regularisation; with 1e-3 the posture task fights the swing legs' ~300 rad/s^2 and TSID's
    trot solutions press 30% more on the ground than tal's; at 1e-6 the median total normal force matches
    tal's to 0.3%, and the time is the same);
  * torque limits: ``TaskActuationBounds`` +-150 N m (the URDF's, as tal's), priority 0;
  * joint position limits: ``TaskJointPosVelAccBounds`` with a 0.04 s horizon (tal's 10 periods: the same
    qdd bound 2/h^2 (q_lim - q - h qd); the task doubles the dt it is given, so it gets 0.02 s) and a
    1e4 rad/s^2 acceleration bound, priority 0; velocity and viability bounds off (tal has none);
  * solver: ``SolverHQuadProgFast`` (the default; dense active set, no warm start).
``--gains kp100`` uses Kp = 100, Kd = 20 for the CoM and the trunk and weights 1 (CoM, trunk) and 10 (swing)
instead, for the sensitivity of TSID's time to the gains.
One formulation per stance set (4 legs; LF+RH trot stance): the sequences never switch contacts.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import math
import pathlib
import sys
import time

import numpy as np

try:
    import pinocchio as pin
    import tsid
except ImportError as _exc:
    raise SystemExit(f"tsid_side: {_exc}; run it with the TSID venv's python (bench/setup_tsid_venv.sh)") from None

POSTURE_KP = 10.0
POSTURE_WEIGHT = 1e-6
MAX_JOINT_ACC = 1e4  # [rad/s^2] TaskJointPosVelAccBounds needs one; never active here
HQP_STATUS_OPTIMAL = 0
STATUS_NAMES = {
    -1: "unknown",
    0: "optimal",
    1: "infeasible",
    2: "unbounded",
    3: "max_iter_reached",
    4: "error",
}


def progress(message: str) -> None:
    print(f"[tsid_side {time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


def example_robot_data_dir() -> pathlib.Path:
    for entry in sys.path:
        candidate = pathlib.Path(entry or ".") / "cmeel.prefix" / "share" / "example-robot-data"
        if candidate.is_dir():
            return candidate
    raise SystemExit("tsid_side: example-robot-data not found on sys.path")


def kd(kp: float) -> float:
    return 2.0 * math.sqrt(kp)


def task_settings(meta: dict, gains: str) -> dict:
    """Gains (per axis) and weights of the TSID tasks, see the module docstring."""
    mass = float(meta["total_mass_kg"])
    inertia = np.asarray(meta["centroidal_inertia_diag_nominal"], dtype=float)
    if gains == "thesis":
        return {
            "com_kp": float(meta["com_kp_n_m"]) / mass * np.ones(3),
            "com_kd": float(meta["com_kd_n_s_m"]) / mass * np.ones(3),
            "trunk_kp": np.concatenate([np.zeros(3), float(meta["trunk_kp_nm_rad"]) / inertia]),
            "trunk_kd": np.concatenate([np.zeros(3), float(meta["trunk_kd_nm_s_rad"]) / inertia]),
            "com_weight": 1.0,
            "trunk_weight": float((inertia.mean() / mass) ** 2),
            "swing_weight": float(meta["slack_weight"]) / mass**2,
            "force_regularisation_weight": float(meta["force_regularisation"]) / mass**2,
        }
    return {
        "com_kp": 100.0 * np.ones(3),
        "com_kd": kd(100.0) * np.ones(3),
        "trunk_kp": 100.0 * np.ones(6),
        "trunk_kd": kd(100.0) * np.ones(6),
        "com_weight": 1.0,
        "trunk_weight": 1.0,
        "swing_weight": 10.0,
        "force_regularisation_weight": float(meta["force_regularisation"]),
    }


class TsidWbc:
    """The TSID problem for one stance set."""

    def __init__(self, robot: tsid.RobotWrapper, meta: dict, stance: np.ndarray, gains: str = "thesis") -> None:
        self.robot = robot
        cfg = task_settings(meta, gains)
        self.stance = stance
        foot_frames = [str(f) for f in meta["foot_frames"]]
        self.formulation = tsid.InverseDynamicsFormulationAccForce("tsid", robot, False)
        f = self.formulation
        q0 = np.zeros(robot.nq)
        q0[6] = 1.0
        f.computeProblemData(0.0, q0, np.zeros(robot.nv))

        self.contacts = {}
        for leg, frame in enumerate(foot_frames):
            if not stance[leg]:
                continue
            contact = tsid.ContactPoint(
                f"contact_{frame}",
                robot,
                frame,
                np.array([0.0, 0.0, 1.0]),
                float(meta["friction_coefficient"]),
                float(meta["min_normal_force_n"]),
                float(meta["max_normal_force_n"]),
            )
            contact.useLocalFrame(False)
            contact.setKp(np.zeros(3))
            contact.setKd(np.zeros(3))
            f.addRigidContact(contact, cfg["force_regularisation_weight"], 1.0, 0)
            self.contacts[leg] = contact

        self.com_task = tsid.TaskComEquality("com", robot)
        self.com_task.setKp(cfg["com_kp"])
        self.com_task.setKd(cfg["com_kd"])
        f.addMotionTask(self.com_task, cfg["com_weight"], 1, 0.0)
        self.com_ref = tsid.TrajectorySample(3)

        self.trunk_task = tsid.TaskSE3Equality("trunk", robot, str(meta["base_frame"]))
        self.trunk_task.setKp(cfg["trunk_kp"])
        self.trunk_task.setKd(cfg["trunk_kd"])
        self.trunk_task.setMask(np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0]))
        f.addMotionTask(self.trunk_task, cfg["trunk_weight"], 1, 0.0)
        self.trunk_ref = tsid.TrajectorySample(12, 6)

        self.swing_tasks = {}
        for leg, frame in enumerate(foot_frames):
            if stance[leg]:
                continue
            task = tsid.TaskSE3Equality(f"swing_{frame}", robot, frame)
            task.setKp(float(meta["swing_kp"]) * np.ones(6))
            task.setKd(float(meta["swing_kd"]) * np.ones(6))
            task.setMask(np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]))
            task.useLocalFrame(False)
            f.addMotionTask(task, cfg["swing_weight"], 1, 0.0)
            self.swing_tasks[leg] = (task, tsid.TrajectorySample(12, 6))

        posture = tsid.TaskJointPosture("posture", robot)
        posture.setKp(POSTURE_KP * np.ones(robot.na))
        posture.setKd(kd(POSTURE_KP) * np.ones(robot.na))
        posture_ref = tsid.TrajectorySample(robot.na)
        posture_ref.value(np.asarray(meta["nominal_joints_pin_order"], dtype=float))
        posture_ref.derivative(np.zeros(robot.na))
        posture_ref.second_derivative(np.zeros(robot.na))
        posture.setReference(posture_ref)
        f.addMotionTask(posture, POSTURE_WEIGHT, 1, 0.0)
        self.posture = posture

        torque = tsid.TaskActuationBounds("torque_limits", robot)
        tau_max = np.asarray(meta["torque_max_pin_order"], dtype=float)
        torque.setBounds(-tau_max, tau_max)
        f.addActuationTask(torque, 1.0, 0, 0.0)
        self.torque = torque

        # The task's constructor stores 2 * dt as its horizon (tsid source: m_dt(2*dt)): half of tal's horizon.
        joint_bounds = tsid.TaskJointPosVelAccBounds(
            "joint_bounds", robot, 0.5 * float(meta["joint_limit_horizon_s"]), False
        )
        joint_bounds.setPositionBounds(
            np.asarray(meta["position_lower_pin_order"], dtype=float),
            np.asarray(meta["position_upper_pin_order"], dtype=float),
        )
        joint_bounds.setVelocityBounds(np.asarray(meta["velocity_limit_pin_order"], dtype=float))
        joint_bounds.setAccelerationBounds(MAX_JOINT_ACC * np.ones(robot.na))
        joint_bounds.setImposeBounds(True, False, False, True)
        f.addMotionTask(joint_bounds, 1.0, 0, 0.0)
        self.joint_bounds = joint_bounds

        self.solver = tsid.SolverHQuadProgFast("qp")
        self.solver.resize(f.nVar, f.nEq, f.nIn)
        self.qp_size = (int(f.nVar), int(f.nEq), int(f.nIn))
        self.settings = {
            key: (value.tolist() if isinstance(value, np.ndarray) else value) for key, value in cfg.items()
        }

    def set_references(self, states: dict, i: int) -> None:
        """Per-state references (outside the timed section, as tal builds WbcReferences before its clock)."""
        self.com_ref.value(states["com_target"][i])
        self.com_ref.derivative(np.zeros(3))
        self.com_ref.second_derivative(np.zeros(3))
        self.com_task.setReference(self.com_ref)
        x, y, z, w = states["base_quat_des_xyzw"][i]
        trunk = pin.SE3(pin.Quaternion(w, x, y, z).toRotationMatrix(), states["q"][i][:3].copy())
        self.trunk_ref.value(trunk)
        self.trunk_ref.derivative(np.zeros(6))
        self.trunk_ref.second_derivative(np.zeros(6))
        self.trunk_task.setReference(self.trunk_ref)
        for leg, contact in self.contacts.items():
            contact.setReference(pin.SE3(np.eye(3), states["foot_positions"][i][leg].copy()))
        for leg, (task, sample) in self.swing_tasks.items():
            sample.value(pin.SE3(np.eye(3), states["foot_targets"][i][leg].copy()))
            sample.derivative(np.zeros(6))
            sample.second_derivative(np.zeros(6))
            task.setReference(sample)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--states", required=True, type=pathlib.Path)
    parser.add_argument("--round", type=int, default=1, help="round number (recorded only)")
    parser.add_argument(
        "--gains",
        choices=("thesis", "kp100"),
        default="thesis",
        help="task gains and weights (see the module docstring)",
    )
    args = parser.parse_args()

    data = np.load(args.states)
    states = {key: data[key] for key in data.files}
    meta = {key: (value.item() if value.ndim == 0 else value) for key, value in states.items()}
    urdf = example_robot_data_dir() / str(meta["urdf_relpath"])
    robot = tsid.RobotWrapper(str(urdf), [str(example_robot_data_dir())], pin.JointModelFreeFlyer(), False)
    model = robot.model()
    names = [model.names[j] for j in range(2, model.njoints)]
    expected = [str(n) for n in meta["joint_names_pin_order"]]
    if names != expected or robot.nq != states["q"].shape[1] or robot.nv != states["v"].shape[1]:
        raise SystemExit(f"tsid_side: model mismatch: joints {names} vs {expected}, nq {robot.nq}, nv {robot.nv}")
    dt = float(meta["control_period_s"])

    groups = {}
    problem = {}
    for group in sorted({int(g) for g in states["group"]}, reverse=True):
        idx = np.flatnonzero(states["group"] == group)
        stance = states["stance"][idx[0]].astype(bool)
        wbc = TsidWbc(robot, meta, stance, args.gains)
        f, solver = wbc.formulation, wbc.solver
        n = len(idx)
        cycle = np.empty(n)
        status = np.empty(n, dtype=int)
        fz = np.full(n, np.nan)
        tau_norm = np.full(n, np.nan)
        clock = time.perf_counter
        for k, i in enumerate(idx):
            wbc.set_references(states, i)
            q, v = states["q"][i], states["v"][i]
            t = k * dt
            t0 = clock()
            hqp = f.computeProblemData(t, q, v)
            sol = solver.solve(hqp)
            tau = f.getActuatorForces(sol)
            t1 = clock()
            cycle[k] = t1 - t0
            status[k] = sol.status
            if sol.status == HQP_STATUS_OPTIMAL:
                forces = f.getContactForces(sol)
                fz[k] = float(np.sum(forces[2::3]))
                tau_norm[k] = float(np.linalg.norm(tau))
        ok = status == HQP_STATUS_OPTIMAL
        groups[str(group)] = {
            "cycle_ms": (1e3 * cycle[1:]).tolist(),
            "first_solve_ms": 1e3 * cycle[0],
            "states": n,
            "failures": int(np.sum(~ok)),
            "status_counts": {STATUS_NAMES.get(int(s), str(s)): int(np.sum(status == s)) for s in np.unique(status)},
            "qp_size": wbc.qp_size,
            "median_ms": float(np.median(1e3 * cycle[1:])),
            "p99_ms": float(np.percentile(1e3 * cycle[1:], 99)),
            "median_total_fz_n": float(np.median(fz[ok])) if ok.any() else None,
            "median_tau_norm_nm": float(np.median(tau_norm[ok])) if ok.any() else None,
        }
        problem[str(group)] = {
            "stance": stance.tolist(),
            "nVar": wbc.qp_size[0],
            "nEq": wbc.qp_size[1],
            "nIn": wbc.qp_size[2],
        }
        progress(
            f"round {args.round}, {group} stance legs: median {groups[str(group)]['median_ms']:.3f} ms, "
            f"p99 {groups[str(group)]['p99_ms']:.3f} ms, failures {groups[str(group)]['failures']}/{n}"
        )

    problem["settings"] = {
        "gains": args.gains,
        **wbc.settings,
        "solver": "SolverHQuadProgFast",
        "swing_kp": float(meta["swing_kp"]),
        "swing_kd": float(meta["swing_kd"]),
        "posture_kp": POSTURE_KP,
        "posture_weight": POSTURE_WEIGHT,
        "friction_coefficient": float(meta["friction_coefficient"]),
        "normal_force_n": [float(meta["min_normal_force_n"]), float(meta["max_normal_force_n"])],
        "joint_bounds_dt_s": float(meta["joint_limit_horizon_s"]),
        "max_joint_acc": MAX_JOINT_ACC,
    }
    versions = {
        "tsid": importlib.metadata.version("tsid"),
        "pinocchio": pin.__version__,
        "numpy": np.__version__,
    }
    json.dump({"round": args.round, "versions": versions, "problem": problem, "groups": groups}, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
