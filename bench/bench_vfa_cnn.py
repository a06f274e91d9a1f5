#!/usr/bin/env python3
"""Time of the CNN-approximated VFA (g_hat) per leg on HyQ, on the seeded terrains of bench_vfa.

Run after ``source scripts/env.sh``:  ``python bench/bench_vfa_cnn.py [--quick] [--samples N] [--seed S]``.
Prints a markdown table on stdout, progress on stderr, and writes ``bench/out/bench_vfa_cnn.json`` (``--json``).
To time another commit's selector with this script (before / after, back to back): ``git worktree add
<worktree> <commit>`` and ``PYTHONPATH=<worktree>/tal_perception:$PYTHONPATH python bench/bench_vfa_cnn.py --json
...``; the JSON's ``tal_perception`` says which code was timed.

Inputs: the same cases as ``bench_vfa.py`` (``make_cases``: 65 x 65 maps of 0.02 m around the nominal
foothold at random headings, random hip height, twist and time left in a trot swing). The committed
weights (``tal_perception/models/vfa_cnn.pt``) on one CPU thread, with each network runtime of ``--backends``
(default both, interleaved in one session: ``onnxruntime``, the selector's default, = ``vfa_cnn_ort``;
``torch`` = ``torch.inference_mode`` with the fast path, ``vfa_cnn_fast``'s traced, frozen rearrangement,
or with ``--plain`` the module's own forward). The first backend's figures are the JSON's ``results``
(what ``bench/report.py`` reads); a last table compares the backends' medians and p99 with ratios.
Per call we time (time.perf_counter, after a warm-up call), in ``--rounds`` alternating rounds pooled:

* ``cnn``: ``CnnFootholdSelector.select`` for one leg, no verification (patch extraction, encoding, one
  forward pass, the argmax and the result);
* ``cnn_4legs``: ``select_legs`` for the four legs on one map (one batched forward pass); the time per
  leg is the call's time / 4;
* ``cnn_2legs``: ``select_legs`` for a trot's diagonal pair (LF, RH) on one map, the call the ``vfa`` node's
  planner makes when both legs of the swinging pair are decided in the same tick; per leg = call / 2;
* ``cnn_verified``: ``select`` with the verification the node uses (the exact FEC on the chosen candidate,
  the exact lazy search if it is unsafe); the table counts how often it fell back.

Thesis figure: CNN VFA 3.5 ms +- 1 ms per leg (mean); goal <= 0.5 ms. A benchmark, never a test.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from bench_vfa import make_cases
from common import OUT_DIR, VITAL_STATS, latency_stats, progress_for, requires_env, write_json  # bench/common.py
from machine import add_wait_quiet_option, cpu_snapshot, machine_info, other_cores_busy, settle_machine

with requires_env("bench_vfa_cnn"):
    import torch

    import tal_perception
    from tal_core.legs import LEGS
    from tal_core.robot_model import RobotModel
    from tal_perception.fec import FootholdEvaluator
    from tal_perception.vfa_cnn import DEFAULT_WEIGHTS, CnnFootholdSelector, FootholdRequest, load_model

JSON_PATH = OUT_DIR / "bench_vfa_cnn.json"
THESIS_MEAN_MS = 3.5
GOAL_MS = 0.5
DEFAULT_SAMPLES = 200
QUICK_SAMPLES = 40
DEFAULT_SEED = 20240601  # bench_vfa's seed: the same inputs as the exact VFA's bench
MODES = ("cnn", "cnn_4legs", "cnn_2legs", "cnn_verified")
BATCHES = {"cnn_4legs": LEGS, "cnn_2legs": (LEGS[0], LEGS[3])}  # all legs; a trot's diagonal pair (LF, RH)


progress = progress_for("bench_vfa_cnn")


def _kwargs(case: dict) -> dict:
    return {"hip_height_m": case["hip"], "twist": case["twist"], "gait": case["gait"], "yaw": case["grid"].yaw}


def run_single(selector: CnnFootholdSelector, cases: list[dict], verify: bool) -> dict[str, dict]:
    """One ``select`` call per leg and case; times [ms] per leg."""
    selector.verify = verify
    out: dict[str, dict] = {}
    for leg in LEGS:
        first = cases[0]
        selector.select(leg, first["nominal"], first["grid"], **_kwargs(first))  # warm-up
        before = selector.counters.rejected
        times, adapted = [], 0
        for case in cases:
            start = time.perf_counter()
            result = selector.select(leg, case["nominal"], case["grid"], **_kwargs(case))
            times.append((time.perf_counter() - start) * 1e3)
            adapted += int(result.adapted)
        out[leg.name] = {"ms": times, "adapted": adapted, "fallbacks": selector.counters.rejected - before}
    return out


def run_batch(selector: CnnFootholdSelector, cases: list[dict], legs: tuple = LEGS) -> dict[str, dict]:
    """One ``select_legs`` call for ``legs`` per case; times [ms] per call and per leg."""
    selector.verify = False

    def requests(case: dict) -> list[FootholdRequest]:
        return [FootholdRequest(leg, case["nominal"], case["hip"], case["twist"], case["gait"]) for leg in legs]

    selector.select_legs(requests(cases[0]), cases[0]["grid"], yaw=cases[0]["grid"].yaw)  # warm-up
    times = []
    for case in cases:
        batch = requests(case)
        start = time.perf_counter()
        selector.select_legs(batch, case["grid"], yaw=case["grid"].yaw)
        times.append((time.perf_counter() - start) * 1e3)
    return {f"{len(legs)}legs": {"ms": times, "ms_per_leg": [t / len(legs) for t in times]}}


def report(summary: dict, n: int, path: str) -> str:
    lines = [
        "| leg | CNN median [ms] | p99 [ms] | CNN + verification median [ms] | p99 [ms] | fallbacks to exact |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for leg in LEGS:
        cnn, ver = summary["cnn"][leg.name], summary["cnn_verified"][leg.name]
        lines.append(
            f"| {leg.name} | {cnn['stats']['median']:.3f} | {cnn['stats']['p99']:.3f} | "
            f"{ver['stats']['median']:.3f} | {ver['stats']['p99']:.3f} | {ver['fallbacks']}/{ver['stats']['n']} |"
        )
    lines.append("")
    for mode, legs in BATCHES.items():
        batch = summary[mode][f"{len(legs)}legs"]
        lines.append(
            f"{len(legs)}-leg batch (`select_legs`, {'+'.join(leg.name for leg in legs)}): median "
            f"{batch['stats']['median']:.3f} ms per call (p99 {batch['stats']['p99']:.3f}), i.e. "
            f"{batch['per_leg_stats']['median']:.3f} ms per leg (p99 {batch['per_leg_stats']['p99']:.3f})."
        )
    lines.append(f"{n} terrains; network: {path}.")
    lines.append(f"Thesis: CNN VFA {THESIS_MEAN_MS} ms +- 1 ms per leg (mean); goal <= {GOAL_MS} ms.")
    return "\n".join(lines)


def headline(summary: dict) -> dict[str, dict[str, float]]:
    """Median and p99 [ms] of the figures the comparison lists: the 4-leg and the 2-leg batch per leg, one
    leg per call (all legs pooled) and the verified call (all legs pooled)."""
    single = [t for r in summary["cnn"].values() for t in r["ms"]]
    verified = [t for r in summary["cnn_verified"].values() for t in r["ms"]]
    batch = summary["cnn_4legs"]["4legs"]["ms_per_leg"]
    pair = summary["cnn_2legs"]["2legs"]["ms_per_leg"]
    samples = {"4legs_per_leg": batch, "2legs_per_leg": pair, "one_leg": single, "verified": verified}
    return {key: {k: latency_stats(x, VITAL_STATS)[k] for k in ("median", "p99")} for key, x in samples.items()}


def comparison(headlines: dict[str, dict[str, dict[str, float]]], labels: dict[str, str]) -> str:
    """Markdown table of the backends' headline figures, with each one's ratio to the first backend."""
    names = list(headlines)
    base = names[0]
    lines = [
        "| network | 4-leg batch, per leg: median (p99) [ms] | 2-leg batch, per leg: median (p99) [ms] | "
        "one leg per call: median (p99) [ms] | verified one leg: median (p99) [ms] |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name in names:
        cells = []
        for key in ("4legs_per_leg", "2legs_per_leg", "one_leg", "verified"):
            value = headlines[name][key]
            ratio = value["median"] / headlines[base][key]["median"]
            cells.append(f"{value['median']:.3f} ({value['p99']:.3f})" + ("" if name == base else f", x{ratio:.2f}"))
        lines.append(f"| {labels[name]} | " + " | ".join(cells) + " |")
    lines.append(f"(ratios: median / the {labels[base]} median, same session, rounds interleaved)")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_SAMPLES} terrains instead of {DEFAULT_SAMPLES}")
    parser.add_argument("--samples", type=int, default=None, help="number of terrains (per leg)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds of the modes, pooled (default 3)")
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument(
        "--backends", default="onnxruntime,torch",
        help="comma-separated network runtimes, measured interleaved in one session (default onnxruntime,torch; "
        "the first one's figures are the headline, `results` in the JSON)",
    )  # fmt: skip
    parser.add_argument("--plain", action="store_true", help="torch: the module's forward, not the fast path")
    parser.add_argument("--json", type=Path, default=JSON_PATH, help=f"output file (default {JSON_PATH})")
    add_wait_quiet_option(parser)
    args = parser.parse_args()
    n = args.samples or (QUICK_SAMPLES if args.quick else DEFAULT_SAMPLES)
    if n < 5 or args.rounds < 1:
        parser.error("need --samples >= 5 and --rounds >= 1")
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    if not backends or any(b not in ("onnxruntime", "torch") for b in backends) or len(set(backends)) != len(backends):
        parser.error("--backends: distinct names out of onnxruntime, torch")
    torch.set_num_threads(1)
    load_at_start = settle_machine(args.wait_quiet, progress)
    model = RobotModel.from_name("hyq")
    net = load_model(args.weights)
    selectors, labels = {}, {}
    for backend in backends:
        selector = CnnFootholdSelector(FootholdEvaluator(model), net, fast=not args.plain, backend=backend)
        if selector.backend != backend:
            raise SystemExit(f"bench_vfa_cnn: backend {backend} is not available (onnxruntime / onnx not installed)")
        selectors[backend] = selector
        if backend == "onnxruntime":
            labels[backend] = f"onnxruntime {vfa_cnn_ort_version()} (module's forward exported to ONNX), 1 thread"
        else:
            path = "fast path (vfa_cnn_fast, TorchScript)" if selector.fast else "plain forward"
            labels[backend] = f"torch {torch.__version__}, {path}, 1 thread"
    progress(f"{n} terrains (seed {args.seed}), 4 legs, weights {args.weights.name}, backends: {', '.join(backends)}")
    cases = make_cases(model, n, args.seed)
    pooled = {b: {mode: {} for mode in MODES} for b in backends}
    round_medians = {b: {mode: {} for mode in MODES} for b in backends}
    others_busy = []
    for r in range(1, args.rounds + 1):
        for mode in MODES:
            for backend, selector in selectors.items():
                progress(f"round {r}/{args.rounds}: {mode}, {backend}")
                start = cpu_snapshot()
                if mode in BATCHES:
                    result = run_batch(selector, cases, BATCHES[mode])
                else:
                    result = run_single(selector, cases, verify=mode == "cnn_verified")
                others_busy.append(other_cores_busy(start, cpu_snapshot()))
                for key, value in result.items():
                    entry = pooled[backend][mode].setdefault(
                        key, {k: [] if isinstance(v, list) else 0 for k, v in value.items()}
                    )
                    for k, v in value.items():
                        entry[k] = entry[k] + v  # lists extend, counts add up over the rounds
                    round_medians[backend][mode].setdefault(key, []).append(float(np.median(value["ms"])))
    summaries = {}
    for backend in backends:
        summary = {mode: {key: {**r, "stats": latency_stats(r["ms"], VITAL_STATS),
                                "round_medians_ms": round_medians[backend][mode][key]}
                          for key, r in value.items()} for mode, value in pooled[backend].items()}  # fmt: skip
        for mode, legs in BATCHES.items():
            batch = summary[mode][f"{len(legs)}legs"]
            batch["per_leg_stats"] = latency_stats(batch["ms_per_leg"], VITAL_STATS)
        summaries[backend] = summary
    busy = [b for b in others_busy if b is not None]
    progress(f"other processes kept {np.mean(busy):.2f} cores busy on average" if busy else "CPU use unknown")
    for backend in backends:
        print(f"\n### {labels[backend]}\n")
        print(report(summaries[backend], n, labels[backend]))
    headlines = {b: headline(summaries[b]) for b in backends}
    print("\n" + comparison(headlines, labels))

    def strip(summary: dict) -> dict:
        return {mode: {key: {k: v for k, v in r.items() if k not in ("ms", "ms_per_leg")} for key, r in value.items()}
                for mode, value in summary.items()}  # fmt: skip

    first = backends[0]
    document = {
        "benchmark": "bench_vfa_cnn",
        "machine": machine_info(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "onnxruntime": vfa_cnn_ort_version(),
        "tal_perception": str(Path(tal_perception.__file__).parent),  # the code timed (see the docstring)
        "load_average_at_start": load_at_start,
        "weights": args.weights.name,
        "backend": first,
        "network_path": labels[first],
        "other_processes_cores_busy": others_busy,
        "rounds": args.rounds,
        "inputs": {"samples": n, "seed": args.seed},
        "thesis_mean_ms": THESIS_MEAN_MS,
        "goal_ms": GOAL_MS,
        "results": strip(summaries[first]),
        "backends": {
            b: {"label": labels[b], "headline_ms": headlines[b], "results": strip(summaries[b])} for b in backends
        },  # fmt: skip
        "samples_ms": {
            b: {mode: {key: r["ms"] for key, r in value.items()} for mode, value in summaries[b].items()}
            for b in backends
        },  # fmt: skip
    }
    write_json(args.json, document, log=progress)
    return 0


def vfa_cnn_ort_version() -> str | None:
    """The installed onnxruntime's version (None when it is not installed)."""
    try:
        import onnxruntime
    except ImportError:
        return None
    return str(onnxruntime.__version__)


if __name__ == "__main__":
    sys.exit(main())
