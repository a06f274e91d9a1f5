#!/usr/bin/env python3
"""Time of one state-estimator tick (``StateEstimator.update``) for the rigid and the terrain-aware leg odometry.

Run after ``source scripts/env.sh``:  ``python bench/bench_estimator.py [--quick] [--wait-quiet S]``.
Prints a markdown table on stdout, progress on stderr, and writes ``bench/out/bench_estimator.json``.

Inputs (no simulator; generated before the clock starts): HyQ standing in its nominal pose with every joint
moving sinusoidally (0.05 rad, 1.5 Hz, a phase per joint), the IMU tick input a specific force of (0, 0, 9.81)
m/s^2 and an angular rate of zero plus white noise (the mean of 3 samples of 0.05 m/s^2 and 0.002 rad/s), and
joint torques that hold the robot's weight (``RobotModel.leg_torques_for_foot_force``), shifted between the
diagonal pairs at the trot frequency (every foot keeps 0.5-1.5 of a quarter of the weight, all in contact).
Ticks every 3 ms (333 Hz); ``--warmup`` ticks (default 200) after ``initialise_standing`` are not timed.

1. Whole tick: ``update`` timed call by call, rigid and terrain_aware (impedance K 2400 N/m, D 400 N s/m on
   every leg from ``legs_from_impedance_arrays``) in alternating rounds (rigid, terrain_aware, rigid, ...), so
   both share the machine's noise; samples pooled over the rounds.
2. Parts: one more pass per mode with the parts wrapped in timers (which adds a little to each): the attitude
   update (NLO + XKF), the leg odometry update, ``RobotModel.foot_dynamics`` (inside the leg odometry; with
   the mass matrix when terrain aware) and the KF predict + update; "rest" is the tick minus the attitude,
   leg odometry and KF (input checks, IMU lever arm, the motion-compensated gravity
   direction, building the estimate).

The budget is the 3 ms estimator period. A benchmark, never a pass/fail test.
"""

from __future__ import annotations

import argparse
import datetime as dt
import gc
import os
import sys
import time
from collections.abc import Callable

import numpy as np
from common import ESTIMATOR_STATS, fmt, latency_stats, progress_for, requires_env, write_json  # bench/common.py
from machine import add_wait_quiet_option, cpu_snapshot, machine_info, machine_record, other_cores_busy, settle_machine

with requires_env("bench_estimator"):
    from tal_core.legs import LEGS, NUM_LEGS
    from tal_core.robot_model import RobotModel
    from tal_estimation.leg_odometry import LegImpedance, LegOdometrySettings
    from tal_estimation.state_estimator import StateEstimator, StateEstimatorSettings, legs_from_impedance_arrays

PERIOD_S = 0.003  # 333 Hz: the budget of one tick
MODES = ("rigid", "terrain_aware")
STIFFNESS_N_PER_M, DAMPING_NS_PER_M = 2400.0, 400.0
JOINT_AMPLITUDE_RAD, JOINT_FREQUENCY_HZ, TROT_FREQUENCY_HZ = 0.05, 1.5, 1.8
ACCEL_NOISE_M_S2, GYRO_NOISE_RAD_S, IMU_SAMPLES_PER_TICK = 0.05, 0.002, 3
DIAGONAL = np.array([1.0, -1.0, -1.0, 1.0])  # LF + RH against RF + LH
PARTS = ("attitude", "leg_odometry", "foot_dynamics", "kalman_filter")
DEFAULT_TICKS, QUICK_TICKS, DEFAULT_WARMUP, DEFAULT_SEED = 3000, 300, 200, 20240531


progress = progress_for("bench_estimator")


def stats(samples_ms: list[float] | np.ndarray) -> dict:
    """Median, p90, p99, max and mean [ms], and the median's and p99's share of the 3 ms budget [%]."""
    return latency_stats(samples_ms, ESTIMATOR_STATS, budget_ms=1e3 * PERIOD_S)


def generate_inputs(model: RobotModel, n: int, seed: int) -> dict[str, np.ndarray]:
    """n ticks of (t, specific force, angular rate, q, qd, tau) as described in the module docstring."""
    rng = np.random.default_rng(seed)
    t = PERIOD_S * np.arange(1, n + 1)
    nominal = np.asarray(model.description.nominal_joint_positions_rad, dtype=float)
    phase = rng.uniform(0.0, 2.0 * np.pi, nominal.size)
    w = 2.0 * np.pi * JOINT_FREQUENCY_HZ
    q = nominal + JOINT_AMPLITUDE_RAD * np.sin(w * t[:, None] + phase)
    qd = JOINT_AMPLITUDE_RAD * w * np.cos(w * t[:, None] + phase)
    scale = 1.0 / np.sqrt(IMU_SAMPLES_PER_TICK)  # the tick's input is the mean of the IMU samples
    f = np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, ACCEL_NOISE_M_S2 * scale, (n, 3))
    gyro = rng.normal(0.0, GYRO_NOISE_RAD_S * scale, (n, 3))
    share = 1.0 + 0.5 * np.sin(2.0 * np.pi * TROT_FREQUENCY_HZ * t)[:, None] * DIAGONAL  # (n, 4), mean 1
    weight = model.total_mass_kg * 9.81 / NUM_LEGS
    tau = np.empty((n, nominal.size))
    for k in range(n):
        model.update(
            model.make_q([0.0, 0.0, model.nominal_base_height_m], [0.0, 0.0, 0.0, 1.0], q[k]),
            model.make_v(np.zeros(3), np.zeros(3), qd[k], [0.0, 0.0, 0.0, 1.0]),
        )
        for leg in LEGS:
            tau[k, 3 * leg : 3 * leg + 3] = model.leg_torques_for_foot_force(leg, [0.0, 0.0, weight * share[k, leg]])
    return {"t": t, "f": f, "gyro": gyro, "q": q, "qd": qd, "tau": tau}


def _estimator(model: RobotModel, mode: str, inputs: dict[str, np.ndarray]) -> StateEstimator:
    settings = StateEstimatorSettings(period_s=PERIOD_S, leg_odometry=LegOdometrySettings(mode=mode))
    estimator = StateEstimator(model, settings)
    estimator.initialise_standing(0.0, inputs["q"][0])
    return estimator


def _tick(estimator: StateEstimator, inputs: dict[str, np.ndarray], k: int, impedance: LegImpedance | None):
    return estimator.update(
        inputs["t"][k],
        inputs["f"][k],
        inputs["gyro"][k],
        inputs["q"][k],
        inputs["qd"][k],
        inputs["tau"][k],
        impedance=impedance,
    )


def run_mode(
    model: RobotModel, mode: str, inputs: dict[str, np.ndarray], warmup: int, impedance: LegImpedance | None
) -> dict:
    """update() per tick [ms] after the warm-up ticks, plus what the last estimate says (sanity)."""
    estimator = _estimator(model, mode, inputs)
    for k in range(warmup):
        _tick(estimator, inputs, k, impedance)
    n = len(inputs["t"]) - warmup
    times = np.empty(n)
    gc.collect()
    for i in range(n):
        t0 = time.perf_counter()
        estimate = _tick(estimator, inputs, warmup + i, impedance)
        times[i] = time.perf_counter() - t0
    legs = estimate.legs
    return {
        "update_ms": (1e3 * times).tolist(),
        "contact_legs": int(np.sum(legs.in_contact)),
        "weight_sum": float(legs.weight_sum),
        "speed_m_s": float(np.linalg.norm(estimate.linear_velocity)),
        "max_penetration_mm": float(1e3 * np.max(legs.penetration)),
    }


def run_parts(
    model: RobotModel, mode: str, inputs: dict[str, np.ndarray], warmup: int, impedance: LegImpedance | None
) -> dict[str, list[float]]:
    """Per tick [ms]: the whole update and its parts, with the parts wrapped in timers."""
    estimator = _estimator(model, mode, inputs)
    spent = dict.fromkeys(PARTS, 0.0)

    def timed(part: str, function: Callable) -> Callable:
        def wrapper(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                spent[part] += time.perf_counter() - t0

        return wrapper

    # instance attributes shadow the methods; the model is the one the leg odometry calls
    estimator.attitude.update = timed("attitude", estimator.attitude.update)
    estimator.legs.update = timed("leg_odometry", estimator.legs.update)
    model.foot_dynamics = timed("foot_dynamics", model.foot_dynamics)
    estimator.kf.predict = timed("kalman_filter", estimator.kf.predict)
    estimator.kf.update = timed("kalman_filter", estimator.kf.update)
    out: dict[str, list[float]] = {key: [] for key in ("update", *PARTS, "rest")}
    try:
        for k in range(len(inputs["t"])):
            for part in PARTS:
                spent[part] = 0.0
            t0 = time.perf_counter()
            _tick(estimator, inputs, k, impedance)
            total = time.perf_counter() - t0
            if k < warmup:
                continue
            out["update"].append(1e3 * total)
            for part in PARTS:
                out[part].append(1e3 * spent[part])
            out["rest"].append(1e3 * (total - spent["attitude"] - spent["leg_odometry"] - spent["kalman_filter"]))
    finally:
        del model.foot_dynamics  # back to the class's method
    return out


def report(summary: dict) -> str:
    lines = [
        "| mode | part | median [ms] | p90 [ms] | p99 [ms] | max [ms] | median / p99 share of 3 ms [%] |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    labels = {
        "update": "**whole tick** (update)",
        "parts_update": "whole tick in the parts pass (with the timers)",
        "attitude": "attitude (NLO + XKF)",
        "leg_odometry": "leg odometry",
        "foot_dynamics": "RobotModel.foot_dynamics (in leg odometry)",
        "kalman_filter": "KF predict + update",
        "rest": "rest (input checks, lever arm, motion-compensated gravity, estimate)",
    }
    for mode in MODES:
        parts = summary[mode]["parts"]
        rows = [("update", summary[mode]["update"]), ("parts_update", parts["update"])]
        rows += [(p, parts[p]) for p in (*PARTS, "rest")]
        for key, s in rows:
            lines.append(
                f"| {mode} | {labels[key]} | {fmt(s['median'])} | {fmt(s['p90'])} | {fmt(s['p99'])} | "
                f"{fmt(s['max'])} | {fmt(s['median_budget_pct'], 1)} / {fmt(s['p99_budget_pct'], 1)} |"
            )
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_TICKS} timed ticks per round")
    parser.add_argument("--ticks", type=int, default=None, help=f"timed ticks per round (default {DEFAULT_TICKS})")
    parser.add_argument("--warmup", type=int, default=DEFAULT_WARMUP, help="untimed ticks first")
    parser.add_argument("--rounds", type=int, default=2, help="alternating rounds per mode (default 2)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    add_wait_quiet_option(parser)
    args = parser.parse_args()
    n = args.ticks or (QUICK_TICKS if args.quick else DEFAULT_TICKS)
    if n < 10 or args.rounds < 1 or args.warmup < 1:
        parser.error("need --ticks >= 10, --rounds >= 1 and --warmup >= 1")

    load_at_start = settle_machine(args.wait_quiet, progress)
    cpu_at_start = cpu_snapshot()
    model = RobotModel.from_name("hyq")
    progress(f"generating {args.warmup} + {n} ticks of inputs (seed {args.seed})")
    inputs = generate_inputs(RobotModel.from_name("hyq"), args.warmup + n, args.seed)
    impedances = {
        "rigid": None,
        "terrain_aware": legs_from_impedance_arrays(
            np.full(NUM_LEGS, STIFFNESS_N_PER_M), np.full(NUM_LEGS, DAMPING_NS_PER_M), np.ones(NUM_LEGS, bool)
        ),
    }
    rounds: dict[str, list[dict]] = {mode: [] for mode in MODES}
    for r in range(1, args.rounds + 1):
        for mode in MODES:
            progress(f"round {r}/{args.rounds}: {mode}")
            rounds[mode].append(run_mode(model, mode, inputs, args.warmup, impedances[mode]))
    parts = {}
    for mode in MODES:
        progress(f"parts pass: {mode}")
        parts[mode] = run_parts(model, mode, inputs, args.warmup, impedances[mode])
    other_load = other_cores_busy(cpu_at_start, cpu_snapshot())

    summary = {
        mode: {
            "update": stats([x for r in rounds[mode] for x in r["update_ms"]]),
            "round_medians_ms": [float(np.median(r["update_ms"])) for r in rounds[mode]],
            "parts": {key: stats(values) for key, values in parts[mode].items()},
            "last_estimate": {k: v for k, v in rounds[mode][-1].items() if k != "update_ms"},
        }
        for mode in MODES
    }
    ratio = summary["terrain_aware"]["update"]["median"] / summary["rigid"]["update"]["median"]
    table = report(summary)
    now = dt.datetime.now().astimezone()
    print(f"## State estimator tick ({now:%Y-%m-%d %H:%M %Z}, {machine_info()['cpu_model']}, {os.cpu_count()} cores)\n")
    print(
        f"HyQ, {n} ticks per round after {args.warmup} warm-up ticks, {args.rounds} alternating rounds per mode; "
        f"parts from one more pass per mode with timers around them. terrain_aware / rigid median: {ratio:.2f}x; "
        f"other processes kept {fmt(other_load, 2)} cores busy on average during the run.\n"
    )
    print(table)

    document = {
        "benchmark": "bench_estimator",
        "date": now.isoformat(timespec="seconds"),
        "machine": machine_record(load_at_start, other_load),
        "budget_ms": 1e3 * PERIOD_S,
        "ticks_per_round": n,
        "warmup_ticks": args.warmup,
        "rounds": args.rounds,
        "seed": args.seed,
        "impedance": {"stiffness_n_per_m": STIFFNESS_N_PER_M, "damping_ns_per_m": DAMPING_NS_PER_M},
        "summary": summary,
        "terrain_aware_over_rigid_median": ratio,
        "table_markdown": table,
        "raw": {mode: {"update_ms": [r["update_ms"] for r in rounds[mode]], "parts_ms": parts[mode]} for mode in MODES},
    }
    write_json("bench_estimator", document, log=progress)
    return 0


if __name__ == "__main__":
    sys.exit(main())
