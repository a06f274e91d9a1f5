#!/usr/bin/env python3
"""Time of the whole VPA update (4 legs, receding horizon N_h = 2) on HyQ: exact evaluation and CNN.

Run after ``source scripts/env.sh``:  ``python bench/bench_vpa.py [--quick] [--scenes N] [--rounds R]``.
Prints a markdown table on stdout, progress on stderr, and writes ``bench/out/bench_vpa.json`` (git-ignored).

Inputs: ``--scenes`` seeded whole-robot scenes (``tal_lab.vital.vpa_scenes``: flat, bars, gaps,
stairs, rocks ahead of the robot; a 141 x 141 map of 0.02 m cells; forward twist 0.1-0.4 m/s, so the
two horizon stages have different maps: 8 leg maps per update), trot gait, cost C_int, L-BFGS-B.
One ``PoseAdapter.update`` call is timed per scene (time.perf_counter; the call includes the extraction
of the 8 leg maps, the pose evaluation, the RBF fit and the optimiser), after one warm-up call. Every
scene starts from the previous scene's pose (as in a running node). ``--rounds`` alternating rounds
of the two modes are pooled. torch runs on one thread. The JSON also holds the time split (evaluation
vs optimisation) and how many cores other processes kept busy per round.

Thesis figures (Python, i7 quad-core): exact VPA 720 ms +- 68 ms, CNN 180 ms +- 60 ms.
Goals of the issue: exact <= 50 ms, CNN <= 20 ms. A benchmark, never a pass/fail test.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter

import numpy as np
from common import VITAL_STATS, latency_stats, progress_for, requires_env, write_json  # bench/common.py
from machine import add_wait_quiet_option, cpu_snapshot, machine_info, other_cores_busy, settle_machine

with requires_env("bench_vpa"):
    import torch
    from tal_lab.vital.vpa_dataset import TROT_GAIT
    from tal_lab.vital.vpa_scenes import vpa_scenes

    from tal_core.robot_model import RobotModel
    from tal_perception.fec import FootholdEvaluator
    from tal_perception.vpa import PoseAdapter
    from tal_perception.vpa_cnn import CnnNsfModel

THESIS_MS = {"exact": 720.0, "cnn": 180.0}
GOAL_MS = {"exact": 50.0, "cnn": 20.0}
DEFAULT_SCENES, QUICK_SCENES = 40, 10
DEFAULT_SEED = 20240602


progress = progress_for("bench_vpa")


def run(adapter: PoseAdapter, scenes: list) -> dict[str, object]:
    adapter.reset()
    first = scenes[0]
    adapter.update(first.grid, first.base_position, 0.0, first.twist, TROT_GAIT)  # warm-up
    total, evaluation, optimisation, statuses = [], [], [], Counter()
    for scene in scenes:
        start = time.perf_counter()
        result = adapter.update(scene.grid, scene.base_position, 0.0, scene.twist, TROT_GAIT)
        total.append((time.perf_counter() - start) * 1e3)
        evaluation.append(result.diagnostics.evaluation_s * 1e3)
        optimisation.append(result.diagnostics.optimisation_s * 1e3)
        statuses[result.status.value] += 1
    return {"ms": total, "evaluation_ms": evaluation, "optimisation_ms": optimisation, "status": dict(statuses)}


def report(summary: dict) -> str:
    lines = [
        "| VPA update (4 legs, N_h = 2) | median [ms] | p99 [ms] | round medians [ms] | evaluation median [ms] "
        "| optimiser median [ms] | thesis mean [ms] | goal [ms] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for mode, row in summary.items():
        lines.append(
            f"| {mode} | {row['stats']['median']:.1f} | {row['stats']['p99']:.1f} | "
            f"{min(row['round_medians_ms']):.1f}-{max(row['round_medians_ms']):.1f} | "
            f"{np.median(row['evaluation_ms']):.1f} | {np.median(row['optimisation_ms']):.1f} | "
            f"{THESIS_MS[mode]:.0f} | {GOAL_MS[mode]:.0f} |"
        )
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_SCENES} scenes instead of {DEFAULT_SCENES}")
    parser.add_argument("--scenes", type=int, default=None)
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    parser.add_argument("--rounds", type=int, default=2, help="alternating rounds of both modes, pooled")
    add_wait_quiet_option(parser)
    args = parser.parse_args()
    n = args.scenes or (QUICK_SCENES if args.quick else DEFAULT_SCENES)
    if n < 2 or args.rounds < 1:
        parser.error("need --scenes >= 2 and --rounds >= 1")
    torch.set_num_threads(1)
    load_at_start = settle_machine(args.wait_quiet, progress)
    model = RobotModel.from_name("hyq")
    evaluator = FootholdEvaluator(model)
    adapters = {
        "exact": PoseAdapter(model, evaluator=evaluator),
        "cnn": PoseAdapter(model, evaluator=evaluator, nsf_model=CnnNsfModel.load()),
    }
    scenes = list(vpa_scenes(args.seed, n, model.nominal_base_height_m))
    progress(f"{n} scenes (seed {args.seed}), 8 leg maps per update")
    pooled: dict[str, dict] = {}
    others_busy = []
    for r in range(1, args.rounds + 1):
        for mode, adapter in adapters.items():
            progress(f"round {r}/{args.rounds}: {mode}")
            start = cpu_snapshot()
            result = run(adapter, scenes)
            others_busy.append(other_cores_busy(start, cpu_snapshot()))
            entry = pooled.setdefault(mode, {"ms": [], "evaluation_ms": [], "optimisation_ms": [],
                                             "round_medians_ms": [], "status": result["status"]})  # fmt: skip
            for key in ("ms", "evaluation_ms", "optimisation_ms"):
                entry[key].extend(result[key])
            entry["round_medians_ms"].append(float(np.median(result["ms"])))
    for row in pooled.values():
        row["stats"] = latency_stats(row["ms"], VITAL_STATS)
    busy = [b for b in others_busy if b is not None]
    progress(f"other processes kept {np.mean(busy):.2f} cores busy on average" if busy else "CPU use unknown")
    print(report(pooled))
    document = {
        "benchmark": "bench_vpa",
        "machine": machine_info(),
        "load_average_at_start": load_at_start,
        "other_processes_cores_busy": others_busy,
        "rounds": args.rounds,
        "inputs": {"scenes": n, "seed": args.seed, "kinds": dict(Counter(s.kind for s in scenes))},
        "thesis_mean_ms": THESIS_MS,
        "goal_ms": GOAL_MS,
        "results": {mode: {k: v for k, v in row.items() if not k.endswith("ms") or k == "round_medians_ms"}
                    for mode, row in pooled.items()},  # fmt: skip
        "samples_ms": {mode: {k: row[k] for k in ("ms", "evaluation_ms", "optimisation_ms")}
                       for mode, row in pooled.items()},  # fmt: skip
    }
    write_json("bench_vpa", document, log=progress)
    return 0


if __name__ == "__main__":
    sys.exit(main())
