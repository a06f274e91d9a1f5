#!/usr/bin/env python3
"""Time of the exact VFA (foothold evaluation g) per leg on HyQ, on seeded random terrains.

Run after ``source scripts/env.sh``:  ``python bench/bench_vfa.py [--quick] [--samples N] [--seed S]``.
Prints a markdown table on stdout, progress on stderr, and writes ``bench/out/bench_vfa.json`` (git-ignored).

Inputs (seeded, the same for every leg): ``--samples`` terrains from ``tal_lab.vital.terrain_samples``
cycling through flat, bars, gaps, stairs and rocks, each a 65 x 65 map of 0.02 m cells around the
nominal foothold at a random heading, with a random hip height (nominal +-0.05 m above the terrain's
base height), a random base twist (vx in [0, 0.5] m/s, vy +-0.1 m/s, yaw rate +-0.3 rad/s) and a random
time left in a trot swing (1.5 Hz, duty factor 0.6, 0.1 m step height).

Per call we time (time.perf_counter, one call at a time, after one warm-up call per leg), in ``--rounds``
alternating rounds of the two modes whose samples are pooled (the table also shows the spread of the
per-round medians; the JSON records how many cores other processes kept busy in each round):

* ``vfa``: ``FootholdSelector.select`` as the VFA node calls it: patch extraction, FEC preparation and
  the lazy search for the safe candidate closest to the nominal (the exact g of the thesis);
* ``vfa_full``: the same with ``lazy=False``: all four criteria on all 33 x 33 candidates, erosion,
  then the argmin (what a CNN label or the VPA's count needs).

Thesis figure: exact VFA 7.5 ms +- 1 ms per leg (Python, i7 quad-core); goal of issue 6: <= 1 ms.
This is a benchmark, never a pass/fail test.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter

import numpy as np
from common import VITAL_STATS, latency_stats, progress_for, requires_env, write_json  # bench/common.py
from machine import add_wait_quiet_option, cpu_snapshot, machine_info, other_cores_busy, settle_machine

with requires_env("bench_vfa"):
    from tal_lab.vital.terrain_samples import terrain_samples

    from tal_core.heightmap import HeightMapGrid
    from tal_core.legs import LEGS
    from tal_core.robot_model import RobotModel
    from tal_perception.fec import FootholdEvaluator
    from tal_perception.fec_settings import GaitTiming
    from tal_perception.vfa import FootholdSelector

THESIS_MEAN_MS = 7.5
GOAL_MS = 1.0
MAP_CELLS = 65
DEFAULT_SAMPLES = 200
QUICK_SAMPLES = 40
DEFAULT_SEED = 20240601


progress = progress_for("bench_vfa")


def make_cases(model: RobotModel, n: int, seed: int) -> list[dict]:
    """The seeded inputs shared by every leg."""
    rng = np.random.default_rng(seed)
    cases = []
    for sample in terrain_samples(seed, n, cells=MAP_CELLS):
        base = float(sample.parameters["base_height_m"])
        grid = HeightMapGrid(center_xy=(0.0, 0.0), yaw=sample.yaw, resolution_m=0.02, heights=sample.heights)
        twist = np.array([rng.uniform(0.0, 0.5), rng.uniform(-0.1, 0.1), 0.0, 0.0, 0.0, rng.uniform(-0.3, 0.3)])
        swing_s = 0.4 / 1.5
        gait = GaitTiming(1.5, 0.6, float(rng.uniform(0.0, swing_s)), 0.1)
        hip = model.nominal_base_height_m + base + float(rng.uniform(-0.05, 0.05))
        cases.append({"kind": sample.kind, "grid": grid, "nominal": np.array([0.0, 0.0, base]),
                      "twist": twist, "gait": gait, "hip": hip})  # fmt: skip
    return cases


def run(selector: FootholdSelector, cases: list[dict], lazy: bool) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for leg in LEGS:
        times, statuses, adapted = [], Counter(), 0
        first = cases[0]
        selector.select(leg, first["nominal"], first["grid"], hip_height_m=first["hip"], twist=first["twist"],
                        gait=first["gait"], lazy=lazy)  # fmt: skip  # warm-up
        for case in cases:
            start = time.perf_counter()
            result = selector.select(
                leg, case["nominal"], case["grid"], hip_height_m=case["hip"], twist=case["twist"],
                gait=case["gait"], yaw=case["grid"].yaw, lazy=lazy,
            )  # fmt: skip
            times.append((time.perf_counter() - start) * 1e3)
            statuses[result.status.value] += 1
            adapted += int(result.adapted)
        out[leg.name] = {"ms": times, "status": dict(statuses), "adapted": adapted}
    return out


def report(summary: dict) -> str:
    lines = [
        "| leg | exact VFA median [ms] | p99 [ms] | round medians [ms] | full FEC + argmin median [ms] | p99 [ms] "
        "| adapted | no safe |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for leg in LEGS:
        lazy, full = summary["vfa"][leg.name], summary["vfa_full"][leg.name]
        n_rounds = len(lazy["round_medians_ms"])
        lines.append(
            f"| {leg.name} | {lazy['stats']['median']:.3f} | {lazy['stats']['p99']:.3f} | "
            f"{min(lazy['round_medians_ms']):.2f}-{max(lazy['round_medians_ms']):.2f} | "
            f"{full['stats']['median']:.3f} | {full['stats']['p99']:.3f} | "
            f"{lazy['adapted']}/{lazy['stats']['n'] // n_rounds} | "
            f"{lazy['status'].get('no_safe_candidate', 0)} |"
        )
    lines.append(f"\nThesis: exact VFA {THESIS_MEAN_MS} ms +- 1 ms per leg (mean); goal <= {GOAL_MS} ms.")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_SAMPLES} terrains instead of {DEFAULT_SAMPLES}")
    parser.add_argument("--samples", type=int, default=None, help="number of terrains (per leg)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds of both modes, pooled (default 3)")
    add_wait_quiet_option(parser)
    args = parser.parse_args()
    n = args.samples or (QUICK_SAMPLES if args.quick else DEFAULT_SAMPLES)
    if n < 5 or args.rounds < 1:
        parser.error("need --samples >= 5 and --rounds >= 1")
    load_at_start = settle_machine(args.wait_quiet, progress)
    model = RobotModel.from_name("hyq")
    selector = FootholdSelector(FootholdEvaluator(model))
    progress(f"{n} terrains (seed {args.seed}), {MAP_CELLS} x {MAP_CELLS} maps, 4 legs")
    cases = make_cases(model, n, args.seed)
    pooled: dict[str, dict[str, dict]] = {"vfa": {}, "vfa_full": {}}
    round_medians: dict[str, dict[str, list[float]]] = {"vfa": {}, "vfa_full": {}}
    others_busy = []
    for r in range(1, args.rounds + 1):
        for key, lazy in (("vfa", True), ("vfa_full", False)):
            progress(f"round {r}/{args.rounds}: {key}")
            start = cpu_snapshot()
            result = run(selector, cases, lazy)
            others_busy.append(other_cores_busy(start, cpu_snapshot()))
            for leg, value in result.items():
                entry = pooled[key].setdefault(leg, {"ms": [], "status": value["status"], "adapted": value["adapted"]})
                entry["ms"].extend(value["ms"])
                round_medians[key].setdefault(leg, []).append(float(np.median(value["ms"])))
    summary = {key: {leg: {**r, "stats": latency_stats(r["ms"], VITAL_STATS),
                           "round_medians_ms": round_medians[key][leg]}
                     for leg, r in value.items()} for key, value in pooled.items()}  # fmt: skip
    busy = [b for b in others_busy if b is not None]
    progress(f"other processes kept {np.mean(busy):.2f} cores busy on average" if busy else "CPU use unknown")
    print(report(summary))
    document = {
        "benchmark": "bench_vfa",
        "machine": machine_info(),
        "load_average_at_start": load_at_start,
        "settings": {k: v for k, v in vars(selector.evaluator.settings).items()},
        "other_processes_cores_busy": others_busy,
        "rounds": args.rounds,
        "inputs": {
            "samples": n,
            "seed": args.seed,
            "map_cells": MAP_CELLS,
            "kinds": dict(Counter(c["kind"] for c in cases)),
        },  # fmt: skip
        "thesis_mean_ms": THESIS_MEAN_MS,
        "goal_ms": GOAL_MS,
        "results": {
            key: {leg: {k: v for k, v in r.items() if k != "ms"} for leg, r in value.items()}
            for key, value in summary.items()
        },  # fmt: skip
        "samples_ms": {key: {leg: r["ms"] for leg, r in value.items()} for key, value in summary.items()},
    }
    write_json("bench_vfa", document, log=progress)
    return 0


if __name__ == "__main__":
    sys.exit(main())
