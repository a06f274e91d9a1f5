#!/usr/bin/env python3
"""Time of the STANCE parts: the TCE update for 4 legs and one c3WBC cycle, next to the sWBC cycle.

Run after ``source scripts/env.sh``:  ``python bench/bench_stance.py [--quick]``.
Prints markdown tables on stdout and writes ``bench/out/bench_stance.json``.

1. TCE update (``TerrainComplianceEstimator.update``): 4 stance legs, windows full (250 samples), one new
   sample per leg and a refit of all four; and, separately, ``contact_states`` (the model update, h, the
   feet's kinematics and the per-leg force from the actuated dynamics) on the same robot states.
2. c3WBC vs sWBC: ``model.update`` + ``StandardWbc.solve`` on bench_wbc's seeded state set (4-leg stance
   and trot sequences), compliant references with T1's stiffness (3500 N/m) and 400 N s/m. Rounds alternate
   rigid, compliant, rigid, compliant so both share the machine's noise; the ratio is the figure to trust.

Goals (issue): TCE update <= 0.1 ms median, c3WBC cycle <= 0.6 ms median. A benchmark, not a test.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import time

import numpy as np
from bench_wbc import GROUPS, generate_states, references  # bench/ is on sys.path
from common import latency_stats, progress_for, requires_env, write_json  # bench/common.py
from machine import machine_info

with requires_env("bench_stance"):
    from tal_control.wbc import StandardWbc, WbcSettings
    from tal_control.wbc.tasks import WbcGains
    from tal_core.legs import NUM_LEGS
    from tal_core.robot_model import RobotModel
    from tal_estimation.tce import ContactSample, TceSettings, TerrainComplianceEstimator

GOALS_MS = {"tce_update_median": 0.1, "c3wbc_cycle_median": 0.6}  # the goals (docstring)
T1_STIFFNESS, DAMPING = 3500.0, 400.0


progress = progress_for("bench_stance")


def bench_tce_update(n: int, seed: int = 0) -> dict:
    """Median time of TerrainComplianceEstimator.update with 4 stance legs and full windows."""
    model = RobotModel.from_name("hyq")
    tce = TerrainComplianceEstimator(model, TceSettings())
    rng = np.random.default_rng(seed)
    up = np.array([0.0, 0.0, 1.0])

    def samples(i: int) -> list[ContactSample]:
        p = 0.06 + 0.01 * np.sin(0.05 * i + np.arange(NUM_LEGS)) + rng.normal(0, 1e-4, NUM_LEGS)
        rate = 0.5 * np.cos(0.05 * i + np.arange(NUM_LEGS))
        return [ContactSample(True, np.array([0.0, 0.0, T1_STIFFNESS * p[k] + DAMPING * rate[k]]), up,
                              float(p[k]), float(rate[k])) for k in range(NUM_LEGS)]

    for i in range(tce.settings.window):   # fill the windows first
        tce.update(samples(i))
    batch = [samples(i) for i in range(n)]
    times = np.empty(n)
    gc.collect()
    for i, s in enumerate(batch):
        t0 = time.perf_counter()
        tce.update(s)
        times[i] = time.perf_counter() - t0
    k = [e.stiffness_n_per_m for e in tce.estimates]
    return {"update_ms": latency_stats((1e3 * times).tolist()), "final_estimates_n_per_m": k}


def bench_contact_states(states: dict, n: int) -> dict:
    model = RobotModel.from_name("hyq")
    tce = TerrainComplianceEstimator(model, TceSettings())
    rng = np.random.default_rng(1)
    qs, vs = states["q"][:n], states["v"][:n]
    taus = rng.normal(0.0, 30.0, (len(qs), 12))
    times = np.empty(len(qs))
    for i, (q, v, tau) in enumerate(zip(qs, vs, taus)):
        t0 = time.perf_counter()
        tce.contact_states(q, v, tau, height=lambda x, y: 0.0)
        times[i] = time.perf_counter() - t0
    return {"contact_states_ms": latency_stats((1e3 * times).tolist())}


def wbc_round(model: RobotModel, states: dict, compliant: bool) -> dict[str, list[float]]:
    settings = WbcSettings(contact_model="compliant" if compliant else "rigid")
    out: dict[str, list[float]] = {}
    for group in GROUPS:
        idx = np.flatnonzero(states["group"] == group)
        refs = [references(states, i) for i in idx]
        if compliant:
            refs = [dataclasses.replace(r, stiffness_normal=np.full(NUM_LEGS, T1_STIFFNESS),
                                        damping_normal=np.full(NUM_LEGS, DAMPING)) for r in refs]
        wbc = StandardWbc(model, WbcGains(), settings)
        cycle, fallbacks = np.empty(len(idx)), 0
        gc.collect()
        for k, i in enumerate(idx):
            t0 = time.perf_counter()
            model.update(states["q"][i], states["v"][i])
            solution = wbc.solve(states["q"][i], states["v"][i], refs[k])
            cycle[k] = time.perf_counter() - t0
            fallbacks += int(solution.fallback)
        out[str(group)] = (1e3 * cycle[1:]).tolist()   # first solve: OSQP setup
        out[f"{group}_fallbacks"] = [float(fallbacks)]
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    n = 300 if args.quick else 2000
    model = RobotModel.from_name("hyq")
    progress("TCE update")
    tce = bench_tce_update(n)
    states = generate_states(model, 200 if args.quick else 1000, seed=7)
    progress("TCE contact states")
    contact = bench_contact_states(states, n)
    pooled: dict[str, dict[str, list[float]]] = {"rigid": {}, "compliant": {}}
    for round_index in range(2):
        for kind in ("rigid", "compliant"):
            progress(f"WBC round {round_index + 1}/2: {kind}")
            for key, values in wbc_round(model, states, kind == "compliant").items():
                pooled[kind].setdefault(key, []).extend(values)
    wbc = {kind: {str(g): latency_stats(pooled[kind][str(g)]) | {"fallbacks": int(sum(pooled[kind][f"{g}_fallbacks"]))}
                  for g in GROUPS} for kind in pooled}
    summary = {"benchmark": "bench_stance", "machine": machine_info(), "settings": {"quick": args.quick},
               "goals_ms": GOALS_MS, "tce": tce, "contact_states": contact, "wbc": wbc}
    write_json("bench_stance", summary, indent=2)
    u, c = tce["update_ms"], contact["contact_states_ms"]
    lines = ["| part | median [ms] | p99 [ms] | goal (median) |", "|---|---|---|---|",
             f"| TCE update, 4 legs, full windows | {u['median']:.3f} | {u['p99']:.3f} | 0.1 ms |",
             f"| TCE contact states (model, h, feet, forces) | {c['median']:.3f} | {c['p99']:.3f} | - |"]
    for g in GROUPS:
        r, k = wbc["rigid"][str(g)], wbc["compliant"][str(g)]
        lines.append(f"| sWBC cycle, {g} stance legs | {r['median']:.3f} | {r['p99']:.3f} | - |")
        lines.append(f"| c3WBC cycle, {g} stance legs | {k['median']:.3f} | {k['p99']:.3f} | 0.6 ms |")
        lines.append(f"| c3WBC / sWBC median, {g} stance legs | {k['median'] / r['median']:.2f}x | | |")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
