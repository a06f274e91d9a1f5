#!/usr/bin/env python3
"""Time of one whole-body control cycle of tal's sWBC, side by side with TSID on the same HyQ states.

Run after ``source scripts/env.sh``:  ``python bench/bench_wbc.py [--quick] [--no-tsid] [--profile]``.
Prints markdown tables on stdout, progress on stderr, and writes ``bench/out/bench_wbc.json``.

1. A state set (``bench/out/wbc_states.npz``, seeded, so both sides solve the same inputs): two sequences of
   N HyQ states each, one with 4 stance legs, one in a trot (LF+RH stance, RF+LH swing with targets a few cm
   away). Every quantity is an Ornstein-Uhlenbeck random walk sampled at the 4 ms control period (correlation
   time 0.1 s), so consecutive states are as close as in a real loop: base pose near nominal (height +-1 cm,
   roll/pitch 0.03 rad, yaw 0.05 rad, 1 sigma), joints within 0.05 rad of the nominal pose, base and joint
   velocities (0.2 m/s, 0.2 rad/s, 1 rad/s), CoM targets 1 cm from the CoM, swing targets (3, 0, 5) cm
   +- 1 cm from the swing foot. q and v are in Pinocchio's convention.
2. Our side (this process): per state, ``model.update(q, v)`` + ``StandardWbc.solve(q, v, refs)`` (which maps
   the solution to joint torques) is the "cycle time"; the QP solve time OSQP reports, the iterations and the
   non-solved QPs (fallbacks) are recorded too. The states are solved in sequence with one controller per
   sequence, so OSQP warm-starts from the previous cycle as in the real loop. References are built before
   the clock starts (the motion generator's job), as they are on the TSID side.
3. TSID side (``bench/tsid_side.py`` in the separate venv of ``bench/setup_tsid_venv.sh``): the equivalent
   TSID problem; per state ``computeProblemData`` + ``SolverHQuadProgFast.solve`` + ``getActuatorForces``.
4. The two sides alternate (ours, TSID, ours, TSID: 2 rounds each) to share the machine's noise; the samples
   of the rounds are pooled. The first state of each sequence is left out of the statistics on both sides
   (OSQP's setup and factorisation happen there; it is reported as ``first_solve_ms``).

Goals (issue): median <= 0.4 ms and p99 <= 1.5 ms per cycle. This is a benchmark, never a pass/fail test.
With ``--profile`` (or when our median misses the goal) one extra pass runs under cProfile and the top
hotspots are printed and stored in the JSON.
"""

from __future__ import annotations

import argparse
import cProfile
import datetime as dt
import gc
import importlib.metadata
import json
import os
import pstats
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from common import OUT_DIR, ROOT, fmt, latency_stats, progress_for, requires_env, write_json  # bench/common.py
from machine import add_wait_quiet_option, cpu_snapshot, machine_info, machine_record, other_cores_busy, settle_machine

with requires_env("bench_wbc"):
    import osqp
    import pinocchio as pin

    from tal_control.wbc import StandardWbc, WbcReferences, WbcSettings
    from tal_control.wbc.swbc import QP_SOLVERS
    from tal_control.wbc.tasks import WbcGains
    from tal_core.legs import NUM_LEGS
    from tal_core.robot_description import find_example_robot_data_dir
    from tal_core.robot_model import RobotModel

STATES_PATH = OUT_DIR / "wbc_states.npz"
SETUP_SCRIPT = ROOT / "bench" / "setup_tsid_venv.sh"
TSID_SIDE = ROOT / "bench" / "tsid_side.py"
TSID_VENV = Path(os.environ.get("TAL_TSID_VENV", OUT_DIR / ".venv-tsid"))
TSID_PYTHON = TSID_VENV / "bin" / "python"

GOAL_MEDIAN_MS = 0.4
GOAL_P99_MS = 1.5
CONTROL_PERIOD_S = 0.004
CORRELATION_TIME_S = 0.1
TROT_STANCE = (True, False, False, True)  # LF + RH stance, RF + LH swing
GROUPS = (4, 2)  # stance legs per sequence
DEFAULT_STATES = 500  # per sequence
QUICK_STATES = 100
DEFAULT_SEED = 20240531
UP = np.tile([0.0, 0.0, 1.0], (NUM_LEGS, 1))


progress = progress_for("bench_wbc")


# -- 1. the state set ------------------------------------------------------------------------------------
def _ou(rng: np.random.Generator, n: int, sigma) -> np.ndarray:
    """(n, len(sigma)) Ornstein-Uhlenbeck samples at the control period, stationary std ``sigma``."""
    sigma = np.atleast_1d(np.asarray(sigma, dtype=float))
    a = np.exp(-CONTROL_PERIOD_S / CORRELATION_TIME_S)
    x = np.empty((n, sigma.size))
    x[0] = sigma * rng.standard_normal(sigma.size)
    step = np.sqrt(1.0 - a * a) * sigma
    for k in range(1, n):
        x[k] = a * x[k - 1] + step * rng.standard_normal(sigma.size)
    return x


def _quat_xyzw(rotation: np.ndarray) -> np.ndarray:
    return np.asarray(pin.Quaternion(rotation).coeffs())  # Pinocchio's coeffs() order is (x, y, z, w)


def generate_states(model: RobotModel, n: int, seed: int) -> dict[str, np.ndarray]:
    """Two seeded sequences of n states (4 stance legs, then the trot) with their references."""
    rng = np.random.default_rng(seed)
    nominal = np.asarray(model.description.nominal_joint_positions_rad, dtype=float)
    out: dict[str, list] = {
        key: []
        for key in (
            "q",
            "v",
            "stance",
            "group",
            "foot_positions",
            "foot_targets",
            "com_target",
            "base_quat_des_xyzw",
        )
    }
    for group in GROUPS:
        stance = np.ones(NUM_LEGS, dtype=bool) if group == 4 else np.array(TROT_STANCE)
        base_xy = _ou(rng, n, [0.02, 0.02])
        base_z = model.nominal_base_height_m + _ou(rng, n, [0.01])[:, 0]
        rpy = _ou(rng, n, [0.03, 0.03, 0.05])
        joints = nominal + _ou(rng, n, np.full(12, 0.05))
        lin_vel = _ou(rng, n, [0.2, 0.1, 0.05]) + ([0.3, 0.0, 0.0] if group == 2 else 0.0)
        ang_vel = _ou(rng, n, [0.2, 0.2, 0.2])
        joint_vel = _ou(rng, n, np.full(12, 1.0))
        com_offset = _ou(rng, n, [0.01, 0.01, 0.01])
        swing_offset = np.array([0.03, 0.0, 0.05]) + _ou(rng, n, np.full(12, 0.01)).reshape(n, NUM_LEGS, 3)
        for k in range(n):
            rotation = pin.rpy.rpyToMatrix(*rpy[k])
            quat = _quat_xyzw(rotation)
            q = model.make_q([*base_xy[k], base_z[k]], quat, joints[k])
            v = model.make_v(lin_vel[k], ang_vel[k], joint_vel[k], quat)
            model.update(q, v)
            feet = model.foot_positions().copy()
            targets = np.where(stance[:, None], feet, feet + swing_offset[k])
            out["q"].append(q)
            out["v"].append(v)
            out["stance"].append(stance)
            out["group"].append(group)
            out["foot_positions"].append(feet)
            out["foot_targets"].append(targets)
            out["com_target"].append(model.com() + com_offset[k])
            out["base_quat_des_xyzw"].append(_quat_xyzw(pin.rpy.rpyToMatrix(0.0, 0.0, rpy[k, 2])))
    return {key: np.array(value) for key, value in out.items()}


def problem_metadata(model: RobotModel, settings: WbcSettings, gains: WbcGains) -> dict[str, np.ndarray]:
    """What the TSID side needs to build the equivalent problem, in Pinocchio's joint order."""
    desc = model.description
    to_pin = model.canonical_joint_v_indices() - 6  # canonical joint k -> Pinocchio joint index
    pin_order = np.argsort(to_pin)  # Pinocchio joint index -> canonical joint k

    def in_pin_order(values) -> np.ndarray:
        return np.asarray(values, dtype=float)[pin_order]

    nominal = np.asarray(desc.nominal_joint_positions_rad, dtype=float)
    tau_min, tau_max = desc.torque_limits(nominal)
    urdf_rel = Path(desc.urdf_path).resolve().relative_to(find_example_robot_data_dir().resolve())
    return {
        "urdf_relpath": np.array(str(urdf_rel)),
        "base_frame": np.array(desc.base_frame),
        "foot_frames": np.array(list(desc.foot_frames)),
        "joint_names_pin_order": np.array([desc.joint_names[k] for k in pin_order]),
        "nominal_joints_pin_order": in_pin_order(nominal),
        "position_lower_pin_order": in_pin_order(desc.position_lower_rad),
        "position_upper_pin_order": in_pin_order(desc.position_upper_rad),
        "velocity_limit_pin_order": in_pin_order(desc.velocity_limit_rad_s),
        "torque_max_pin_order": in_pin_order(tau_max),
        "friction_coefficient": np.array(settings.friction_coefficient),
        "min_normal_force_n": np.array(settings.min_normal_force_n),
        "max_normal_force_n": np.array(settings.max_normal_force_n),
        "joint_limit_horizon_s": np.array(settings.joint_limit_horizon_periods * settings.control_period_s),
        "control_period_s": np.array(settings.control_period_s),
        "force_regularisation": np.array(settings.force_regularisation),
        "slack_weight": np.array(settings.slack_weight),
        "swing_kp": np.array(gains.K_sw),
        "swing_kd": np.array(gains.D_sw),
        "com_kp_n_m": np.array(gains.K_x),
        "com_kd_n_s_m": np.array(gains.D_x),
        "trunk_kp_nm_rad": np.array(gains.K_theta),
        "trunk_kd_nm_s_rad": np.array(gains.D_theta),
        "total_mass_kg": np.array(model.total_mass_kg),
        "centroidal_inertia_diag_nominal": np.diag(_centroidal_inertia(model)),
    }


def _centroidal_inertia(model: RobotModel) -> np.ndarray:
    """(3, 3) rotational inertia about the CoM [kg m^2] in the nominal standing pose."""
    q, v = model.neutral_q(), np.zeros(model.nv)
    pin.ccrba(model.model, model.data, q, v)
    return np.array(model.data.Ig.inertia)


def references(states: dict[str, np.ndarray], i: int) -> WbcReferences:
    z = np.zeros(3)
    zeros = np.zeros((NUM_LEGS, 3))
    x, y, zq, w = states["base_quat_des_xyzw"][i]
    return WbcReferences(
        com_position=states["com_target"][i],
        com_velocity=z,
        com_acceleration=z,
        world_R_base=pin.Quaternion(w, x, y, zq).toRotationMatrix(),
        angular_velocity=z,
        angular_acceleration=z,
        foot_position=states["foot_targets"][i],
        foot_velocity=zeros,
        foot_acceleration=zeros,
        stance=states["stance"][i],
        load_factor=np.ones(NUM_LEGS),
        touchdown_position=states["foot_positions"][i],
        normals=UP,
    )


# -- 2. our side -------------------------------------------------------------------------------------------
def run_ours(
    model: RobotModel, states: dict[str, np.ndarray], settings: WbcSettings, gains: WbcGains
) -> dict[str, dict]:
    """One round: every sequence in order with a fresh controller (OSQP warm-starts along the sequence)."""
    result: dict[str, dict] = {}
    for group in GROUPS:
        idx = np.flatnonzero(states["group"] == group)
        refs = [references(states, i) for i in idx]
        qs, vs = states["q"][idx], states["v"][idx]
        wbc = StandardWbc(model, gains, settings)
        n = len(idx)
        cycle = np.empty(n)
        update = np.empty(n)
        qp_solve = np.empty(n)
        iterations = np.empty(n, dtype=int)
        status = []
        fz = np.empty(n)
        tau_norm = np.empty(n)
        gc.collect()
        clock = time.perf_counter
        for k in range(n):
            q, v, r = qs[k], vs[k], refs[k]
            t0 = clock()
            model.update(q, v)
            t1 = clock()
            solution = wbc.solve(q, v, r)
            t2 = clock()
            cycle[k] = t2 - t0
            update[k] = t1 - t0
            qp_solve[k] = solution.solve_time_s
            iterations[k] = solution.iterations
            status.append(solution.status)
            fz[k] = float(np.sum(solution.forces[:, 2]))
            tau_norm[k] = float(np.linalg.norm(solution.tau))
        solved = np.array([s != "fallback" for s in status])
        body = slice(1, None)  # the first solve sets OSQP up: out of the statistics
        result[str(group)] = {
            "cycle_ms": (1e3 * cycle[body]).tolist(),
            "update_ms": (1e3 * update[body]).tolist(),
            "wbc_solve_ms": (1e3 * (cycle - update)[body]).tolist(),
            "qp_solve_ms": (1e3 * qp_solve[body][solved[body]]).tolist(),
            "iterations": iterations[body][solved[body]].tolist(),
            "first_solve_ms": 1e3 * cycle[0],
            "states": n,
            "not_solved": int(np.sum(~solved)),
            "status_counts": {s: status.count(s) for s in sorted(set(status))},
            "median_total_fz_n": float(np.median(fz[solved])) if solved.any() else None,
            "median_tau_norm_nm": float(np.median(tau_norm[solved])) if solved.any() else None,
        }
    return result


def profile_ours(
    model: RobotModel, states: dict[str, np.ndarray], settings: WbcSettings, gains: WbcGains, top: int = 15
) -> dict:
    """One pass over both sequences under cProfile: self-time hotspots and tal functions' cumulative time."""
    prepared = []
    for group in GROUPS:
        idx = np.flatnonzero(states["group"] == group)
        prepared.append(
            (
                StandardWbc(model, gains, settings),
                states["q"][idx],
                states["v"][idx],
                [references(states, i) for i in idx],
            )
        )
    profiler = cProfile.Profile()
    cycles = 0
    profiler.enable()
    for wbc, qs, vs, refs in prepared:
        for q, v, r in zip(qs, vs, refs, strict=True):
            model.update(q, v)
            wbc.solve(q, v, r)
            cycles += 1
    profiler.disable()
    stats = pstats.Stats(profiler).stats  # (file, line, function) -> (cc, nc, tottime, cumtime, callers)
    total = sum(entry[2] for entry in stats.values())

    def name(key) -> str:
        file, line, function = key
        if file == "~":
            return function  # a C function or method
        path = Path(file).resolve()  # the colcon build tree links back to the sources
        for base in (ROOT, *(Path(p) for p in sys.path if p)):
            try:
                return f"{path.relative_to(base)}:{function}"
            except ValueError:
                continue
        return f"{path.name}:{function}"

    def row(key, value, column) -> dict:
        return {
            "function": name(key),
            "calls_per_cycle": value[1] / cycles,
            "us_per_cycle": 1e6 * value[column] / cycles,
            "share": value[column] / total,
        }

    self_time = sorted(stats.items(), key=lambda item: item[1][2], reverse=True)[:top]
    tal_cumulative = sorted(
        ((key, value) for key, value in stats.items() if "tal_control" in key[0] or "tal_core" in key[0]),
        key=lambda item: item[1][3],
        reverse=True,
    )[:top]
    return {
        "cycles": cycles,
        "profiled_us_per_cycle": 1e6 * total / cycles,
        "note": "cProfile inflates Python-level overhead relative to C calls; shares, not absolute times",
        "self_time": [row(key, value, 2) for key, value in self_time],
        "tal_cumulative": [row(key, value, 3) for key, value in tal_cumulative],
    }


# -- 3. the TSID side -----------------------------------------------------------------------------------------
def ensure_tsid_venv() -> str | None:
    """None when the TSID venv is usable, else why not (setup_tsid_venv.sh is a fast no-op when ready)."""
    progress(f"TSID venv: bash {SETUP_SCRIPT.relative_to(ROOT)}")
    done = subprocess.run(["bash", str(SETUP_SCRIPT)], capture_output=True, text=True)
    if done.stderr:
        sys.stderr.write(done.stderr)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        return f"{SETUP_SCRIPT.name} failed (exit {done.returncode}): {last}"
    if not TSID_PYTHON.exists():
        return f"{TSID_PYTHON} missing after {SETUP_SCRIPT.name}"
    return None


def run_tsid(round_index: int) -> dict:
    done = subprocess.run(
        [str(TSID_PYTHON), str(TSID_SIDE), "--states", str(STATES_PATH), "--round", str(round_index)],
        capture_output=True,
        text=True,
    )
    if done.stderr:
        sys.stderr.write(done.stderr)
    if done.returncode != 0:
        raise RuntimeError(f"tsid_side.py exited {done.returncode}")
    return json.loads(done.stdout)


# -- 4. statistics and report ------------------------------------------------------------------------------
def pool(rounds: list[dict], group: str, key: str) -> list[float]:
    return [value for r in rounds for value in r[group][key]]


def report(summary: dict) -> str:
    lines = [
        "| controller | stance legs | median [ms] | p99 [ms] | ratio to TSID (median) |",
        "| --- | --- | --- | --- | --- |",
    ]
    solver = str(summary.get("qp_solver", "osqp")).upper()
    for side, label in (("ours", f"tal sWBC ({solver})"), ("tsid", "TSID 1.7.1 (HQuadProgFast)")):
        for group in map(str, GROUPS):
            s = summary[side].get(group) if summary.get(side) else None
            t = summary["tsid"].get(group) if summary.get("tsid") else None
            if s is None:
                lines.append(f"| {label} | {group} | n/a | n/a | n/a |")
                continue
            ratio = s["cycle"]["median"] / t["cycle"]["median"] if t and t["cycle"]["median"] else None
            lines.append(
                f"| {label} | {group} | {fmt(s['cycle']['median'])} | {fmt(s['cycle']['p99'])} | {fmt(ratio, 2)} |"
            )
    lines += [
        "",
        f"Goals: median <= {GOAL_MEDIAN_MS} ms, p99 <= {GOAL_P99_MS} ms (tal sWBC cycle).",
        "",
        "| tal sWBC, stance legs | model.update median [ms] | wbc.solve median [ms] | QP solve median / "
        "p99 [ms] | QP iterations median / p99 / max | not solved | first solve [ms] | median sum Fz [N] | "
        "median norm(tau) [N m] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for group in map(str, GROUPS):
        s = summary["ours"][group]
        it = s["iterations"]
        lines.append(
            f"| {group} | {fmt(s['update']['median'])} | {fmt(s['wbc_solve']['median'])} | "
            f"{fmt(s['qp_solve']['median'])} / {fmt(s['qp_solve']['p99'])} | "
            f"{fmt(it['median'], 0)} / {fmt(it['p99'], 0)} / {fmt(it['max'], 0)} | "
            f"{s['not_solved']} of {s['states']} | {fmt(s['first_solve_ms'])} | {fmt(s['median_total_fz_n'], 1)} | "
            f"{fmt(s['median_tau_norm_nm'], 1)} |"
        )
    if summary.get("tsid"):
        lines += [
            "",
            "| TSID, stance legs | not solved (status != 0) | QP size (vars, eq, ineq) | first solve [ms] | "
            "median sum Fz [N] | median norm(tau) [N m] |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for group in map(str, GROUPS):
            t = summary["tsid"][group]
            lines.append(
                f"| {group} | {t['failures']} of {t['states']} | {tuple(t['qp_size'])} | {fmt(t['first_solve_ms'])} | "
                f"{fmt(t['median_total_fz_n'], 1)} | {fmt(t['median_tau_norm_nm'], 1)} |"
            )
    return "\n".join(lines)


def profile_report(profile: dict, top: int = 12) -> str:
    lines = [
        f"cProfile, {profile['cycles']} cycles, {profile['profiled_us_per_cycle']:.0f} us/cycle under the "
        f"profiler (inflated; read the shares)",
        "",
        "| self time: function | calls/cycle | us/cycle | share |",
        "| --- | --- | --- | --- |",
    ]
    lines += [
        f"| {r['function']} | {r['calls_per_cycle']:.1f} | {r['us_per_cycle']:.1f} | {100 * r['share']:.1f}% |"
        for r in profile["self_time"][:top]
    ]
    lines += [
        "",
        "| cumulative: tal function | calls/cycle | us/cycle | share |",
        "| --- | --- | --- | --- |",
    ]
    lines += [
        f"| {r['function']} | {r['calls_per_cycle']:.1f} | {r['us_per_cycle']:.1f} | {100 * r['share']:.1f}% |"
        for r in profile["tal_cumulative"][:top]
    ]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_STATES} states per sequence")
    parser.add_argument(
        "--states",
        type=int,
        default=None,
        help=f"states per sequence (default {DEFAULT_STATES}, --quick {QUICK_STATES})",
    )
    parser.add_argument("--rounds", type=int, default=2, help="alternating rounds per side (default 2)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    parser.add_argument("--no-tsid", action="store_true", help="our side only (no TSID venv needed)")
    parser.add_argument("--qp-solver", choices=QP_SOLVERS, default=WbcSettings().qp_solver,
                        help="our QP solver (default: WbcSettings'; another one writes bench_wbc_<solver>.json)")
    add_wait_quiet_option(parser)
    parser.add_argument(
        "--profile",
        action="store_true",
        help="always run the cProfile pass (it runs anyway when the median misses the goal)",
    )
    args = parser.parse_args()
    n = args.states or (QUICK_STATES if args.quick else DEFAULT_STATES)
    if n < 10 or args.rounds < 1:
        parser.error("need --states >= 10 and --rounds >= 1")

    OUT_DIR.mkdir(parents=True, exist_ok=True)
    load_at_start = settle_machine(args.wait_quiet, progress)
    cpu_at_start = cpu_snapshot()
    model = RobotModel.from_name("hyq")
    settings, gains = WbcSettings(qp_solver=args.qp_solver), WbcGains()
    progress(f"generating 2 x {n} states (seed {args.seed}) -> {STATES_PATH.relative_to(ROOT)}")
    states = generate_states(model, n, args.seed)
    np.savez(STATES_PATH, seed=np.array(args.seed), **states, **problem_metadata(model, settings, gains))

    tsid_error = None
    if args.no_tsid:
        tsid_error = "skipped (--no-tsid)"
        progress("TSID side skipped (--no-tsid)")
    else:
        tsid_error = ensure_tsid_venv()
        if tsid_error:
            progress(f"TSID side skipped: {tsid_error}")

    ours_rounds: list[dict] = []
    tsid_rounds: list[dict] = []
    for r in range(1, args.rounds + 1):
        progress(f"round {r}/{args.rounds}: tal sWBC")
        ours_rounds.append(run_ours(model, states, settings, gains))
        if tsid_error is None:
            progress(f"round {r}/{args.rounds}: TSID")
            try:
                tsid_rounds.append(run_tsid(r))
            except (RuntimeError, json.JSONDecodeError) as error:
                tsid_error = f"tsid_side.py failed: {error}"
                progress(f"TSID side stopped: {tsid_error}")
                tsid_rounds = []

    summary: dict = {"ours": {}, "tsid": {}, "qp_solver": args.qp_solver}
    for group in map(str, GROUPS):
        summary["ours"][group] = {
            "cycle": latency_stats(pool(ours_rounds, group, "cycle_ms")),
            "update": latency_stats(pool(ours_rounds, group, "update_ms")),
            "wbc_solve": latency_stats(pool(ours_rounds, group, "wbc_solve_ms")),
            "qp_solve": latency_stats(pool(ours_rounds, group, "qp_solve_ms")),
            "iterations": latency_stats([float(i) for i in pool(ours_rounds, group, "iterations")]),
            "states": sum(r[group]["states"] for r in ours_rounds),
            "not_solved": sum(r[group]["not_solved"] for r in ours_rounds),
            "first_solve_ms": float(np.median([r[group]["first_solve_ms"] for r in ours_rounds])),
            "round_medians_ms": [latency_stats(r[group]["cycle_ms"])["median"] for r in ours_rounds],
            "median_total_fz_n": ours_rounds[-1][group]["median_total_fz_n"],
            "median_tau_norm_nm": ours_rounds[-1][group]["median_tau_norm_nm"],
            "status_counts": ours_rounds[-1][group]["status_counts"],
        }
        if tsid_rounds:
            groups = [t["groups"][group] for t in tsid_rounds]
            summary["tsid"][group] = {
                "cycle": latency_stats([x for g in groups for x in g["cycle_ms"]]),
                "states": sum(g["states"] for g in groups),
                "failures": sum(g["failures"] for g in groups),
                "first_solve_ms": float(np.median([g["first_solve_ms"] for g in groups])),
                "round_medians_ms": [latency_stats(g["cycle_ms"])["median"] for g in groups],
                "qp_size": groups[-1]["qp_size"],
                "median_total_fz_n": groups[-1]["median_total_fz_n"],
                "median_tau_norm_nm": groups[-1]["median_tau_norm_nm"],
                "status_counts": groups[-1]["status_counts"],
            }
    if not tsid_rounds:
        summary["tsid"] = None

    table = report(summary)
    worst_median = max(summary["ours"][g]["cycle"]["median"] for g in map(str, GROUPS))
    profile = None
    if args.profile or worst_median > GOAL_MEDIAN_MS:
        progress("cProfile pass over both sequences (timings above were taken without the profiler)")
        profile = profile_ours(model, states, settings, gains)

    other_load = other_cores_busy(cpu_at_start, cpu_snapshot())
    now = dt.datetime.now().astimezone()
    print(f"## WBC cycle vs TSID ({now:%Y-%m-%d %H:%M %Z}, {machine_info()['cpu_model']}, {os.cpu_count()} cores)\n")
    print(
        f"{n} states per sequence, {args.rounds} alternating rounds per side, first state of each sequence left out; "
        f"other processes kept {fmt(other_load, 2)} cores busy on average during the run.\n"
    )
    print(table)
    if tsid_error:
        print(f"\nTSID side: {tsid_error}")
    if profile:
        print()
        print(profile_report(profile))

    document = {
        "benchmark": "bench_wbc",
        "date": now.isoformat(timespec="seconds"),
        "machine": machine_record(load_at_start, other_load),
        "versions": {
            "numpy": np.__version__,
            "osqp": getattr(osqp, "__version__", "?"),
            "daqp": importlib.metadata.version("daqp"),
            "pinocchio": pin.__version__,
            "tsid": tsid_rounds[0]["versions"] if tsid_rounds else None,
        },
        "qp_solver": args.qp_solver,
        "states_per_sequence": n,
        "rounds": args.rounds,
        "seed": args.seed,
        "states_file": str(STATES_PATH.relative_to(ROOT)),
        "goals_ms": {"median": GOAL_MEDIAN_MS, "p99": GOAL_P99_MS},
        "summary": summary,
        "tsid_error": tsid_error,
        "tsid_problem": tsid_rounds[0]["problem"] if tsid_rounds else None,
        "profile": profile,
        "table_markdown": table,
        "raw": {"ours": ours_rounds, "tsid": [t["groups"] for t in tsid_rounds]},
    }
    default_solver = args.qp_solver == WbcSettings().qp_solver
    write_json("bench_wbc" if default_solver else f"bench_wbc_{args.qp_solver}", document, log=progress)
    return 0


if __name__ == "__main__":
    sys.exit(main())
