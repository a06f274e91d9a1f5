#!/usr/bin/env python3
"""Collect the benches' JSON (``bench/out/*.json``) into one table: ``results/bench.md``.

Run after the benches (``make bench`` runs it last):  ``python bench/report.py [--out-dir DIR] [--output MD]``.

One row per figure: what, the measured value with its unit, the goal (from the issues and DESIGN.md section 3;
each bench's docstring names its own), the thesis' or the peer's number where one exists, measured / goal and
whether the goal is met. A bench whose JSON is missing gives a "not run" row, one whose JSON lacks a field an
"unreadable" row; nothing here raises on a partial ``bench/out``. Two optional inputs written by other runs
add row groups when present: ``graph_rates.json`` (the real-time graph: per-node target and achieved rate,
deadline misses, peak memory) and ``across_hosts.json`` (tests/test_across_hosts.py: the graph split over two
network namespaces; its ``rows`` and its ``markdown`` section). ``bench_graph.json`` (issue 31: the whole graph on
the tour) gives the lockstep tour's CPU per simulated second and the real-time tours' rates, missed deadlines, walk
and latency; ``rows_peers`` the sWBC and c3WBC cycle medians over TSID's.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from common import OUT_DIR, ROOT  # bench/common.py (the script folder is on sys.path)
from machine import machine_info  # bench/machine.py

OUTPUT = ROOT / "results" / "bench.md"

# Thesis figures (seed 000_a1bc1bec5ccfad53.txt, line numbers there).
THESIS_QP = "thesis: QP 0.12-0.15 ms with slacks (i5; l. 1698-1703)"
THESIS_FRAMEWORK = "thesis: estimator + planner + WBC mean 0.68 ms sWBC, 0.74 ms STANCE, max < 2 ms (i7; l. 3459-3469)"
THESIS_VFA_MS, THESIS_VFA_CNN_MS = 7.5, 3.5  # mean +- 1 ms per leg (l. 5565-5567)
THESIS_VPA_MS, THESIS_VPA_CNN_MS = 720.0, 180.0  # mean +- 68 / 60 ms (l. 5568-5571)
ESTIMATOR_TICK_GOAL_MS = 0.1  # issue 31 ("control at the speed of C++ peers"; the earlier goal was 0.2 ms)


@dataclass(frozen=True)
class Goal:
    op: str  # "<=" (a time, a share) or ">=" (a rate, a real-time factor)
    value: float
    source: str = ""  # where the goal comes from

    def text(self, unit: str) -> str:
        return f"{self.op} {self.value:,.4g} {unit}".rstrip() + (f" ({self.source})" if self.source else "")


@dataclass(frozen=True)
class Row:
    group: str
    what: str
    value: float | None = None  # None: not measured (see note)
    unit: str = ""
    goal: Goal | None = None
    reference: str = ""  # the thesis' or the peer's number
    note: str = ""  # conditions, spread, why not run

    @property
    def ratio(self) -> float | None:
        """measured / goal (None without a goal or a value)."""
        if self.goal is None or self.value is None or self.goal.value == 0:
            return None
        return self.value / self.goal.value

    @property
    def met(self) -> bool | None:
        ratio = self.ratio
        if ratio is None:
            return None
        return ratio <= 1.0 if self.goal.op == "<=" else ratio >= 1.0


def fmt_number(x: float | None) -> str:
    """Three significant digits, no exponent for the ranges benches produce."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    if x == 0:
        return "0"
    magnitude = math.floor(math.log10(abs(x)))
    digits = max(0, 2 - magnitude)
    text = f"{x:,.{digits}f}"
    return text


def _others(cpu: dict | None) -> str:
    return "" if not cpu or cpu.get("other_cpus") is None else f"others used {cpu['other_cpus']:.2f} CPU"


# -- per bench: JSON document -> rows ----------------------------------------------------------------------------
def rows_bridge(doc: dict) -> list[Row]:
    g, rows = "bridge (PyBullet HyQ, 1 kHz physics)", []
    for course, s in doc["physics_only"].items():
        busiest = max((r["cpu"]["other_cpus"] for r in s["runs"]), default=None)
        rows.append(
            Row(
                g,
                f"physics alone, {course} (BridgeCore + StandHold, no ROS): RTF median of {len(s['runs'])}",
                s["median_rtf"],
                "x",
                Goal(">=", 3.0, "bench/README.md"),
                note=f"min {s['min_rtf']:.2f}; others used {busiest:.2f} CPU at most",
            )
        )
    for course, s in doc["physics_with_sensor_outputs"].items():
        rows.append(
            Row(
                g,
                f"physics + sensor outputs, {course} (no ROS): RTF median",
                s["median_rtf"],
                "x",
                note=f"min {s['min_rtf']:.2f}",
            )
        )
    for course, r in doc["lockstep_inprocess"].items():
        rows.append(
            Row(
                g,
                f"lockstep in-process, {course}, bridge + stand_controller, 1 executor: RTF",
                r["real_time_factor"],
                "x",
                Goal(">=", 1.0, "real time, 250 ticks/s"),
                note=f"{r['cpu_ms_per_control_tick']:.2f} ms CPU per 4 ms tick; {_others(r.get('cpu'))}",
            )
        )
    for rng, runs in doc["lockstep_multiprocess"].items():
        for name, r in runs.items():
            if name == "first_command_probe":
                what = f"2 processes, discovery {rng}: wait for the first command (1-tick run wall time)"
                if "error" in r:
                    rows.append(Row(g, what, note=f"failed: {r['error']}"))
                else:
                    rows.append(Row(g, what, r["wall_s"], "s", note=_others(r.get("cpu"))))
                continue
            what = (
                f"lockstep 2 processes (installed sim_bridge + stand_controller), discovery {rng}"
                + (", sensor_rate_hz 250" if name != "default" else "")
                + ": RTF"
            )
            if "error" in r:
                rows.append(Row(g, what, goal=Goal(">=", 1.0, "real time"), note=f"failed: {r['error']}"))
            else:
                rows.append(
                    Row(
                        g,
                        what,
                        float(r["real_time_factor"]),
                        "x",
                        Goal(">=", 1.0, "real time"),
                        note=f"{r['commands_accepted']} commands, {r['lockstep_timeouts']} timeouts; "
                        f"{_others(r.get('cpu'))}",
                    )
                )
    return rows


def rows_wbc(doc: dict) -> list[Row]:
    g, rows = "sWBC (250 Hz)", []
    summary, tsid = doc["summary"], doc["summary"].get("tsid") or {}
    goals = doc.get("goals_ms", {"median": 0.4, "p99": 1.5})
    for legs in ("4", "2"):
        ours = summary["ours"][legs]
        peer = tsid.get(legs)
        ref = THESIS_FRAMEWORK if legs == "4" else ""
        if peer:
            ratio = ours["cycle"]["median"] / peer["cycle"]["median"]
            ref = f"TSID 1.7.1 (peer, same states): {peer['cycle']['median']:.3f} ms, ours / TSID {ratio:.2f}" + (
                f"; {ref}" if ref else ""
            )
        elif doc.get("tsid_error"):
            ref = f"TSID not run: {doc['tsid_error']}" + (f"; {ref}" if ref else "")
        rows.append(
            Row(
                g,
                f"cycle (model.update + QP + torques), {legs} stance legs, median",
                ours["cycle"]["median"],
                "ms",
                Goal("<=", goals["median"], "issue"),
                ref,
                note=f"{ours['cycle']['n']} cycles, {ours['not_solved']} not solved",
            )
        )
        rows.append(
            Row(g, f"cycle, {legs} stance legs, p99", ours["cycle"]["p99"], "ms", Goal("<=", goals["p99"], "issue"))
        )
        rows.append(
            Row(
                g,
                f"QP solve alone ({str(doc.get('qp_solver', 'osqp')).upper()}), {legs} stance legs, median",
                ours["qp_solve"]["median"],
                "ms",
                reference=THESIS_QP,
            )
        )
    worst = max(summary["ours"][legs]["cycle"]["max"] for legs in ("4", "2"))
    rows.append(Row(g, "cycle, worst of both sequences (max)", worst, "ms", Goal("<=", 4.0, "4 ms tick at 250 Hz")))
    return rows


def rows_stance(doc: dict) -> list[Row]:
    g, rows = "STANCE: TCE (250 Hz) and c3WBC", []
    goals = doc.get("goals_ms", {"tce_update_median": 0.1, "c3wbc_cycle_median": 0.6})
    update, contact = doc["tce"]["update_ms"], doc["contact_states"]["contact_states_ms"]
    rows.append(
        Row(
            g,
            "TCE update, 4 legs, full windows, median",
            update["median"],
            "ms",
            Goal("<=", goals["tce_update_median"], "issue"),
        )
    )
    rows.append(
        Row(
            g,
            "TCE tick (contact states + update), sum of the p99s",
            contact["p99"] + update["p99"],
            "ms",
            Goal("<=", 4.0, "4 ms tick at 250 Hz"),
            note=f"contact states median {contact['median']:.3f} ms",
        )
    )
    for legs in ("4", "2"):
        rigid, compliant = doc["wbc"]["rigid"][legs], doc["wbc"]["compliant"][legs]
        rows.append(
            Row(
                g,
                f"c3WBC cycle, {legs} stance legs, median",
                compliant["median"],
                "ms",
                Goal("<=", goals["c3wbc_cycle_median"], "issue"),
                THESIS_FRAMEWORK if legs == "4" else "",
                note=f"p99 {compliant['p99']:.3f} ms; {compliant['fallbacks']} fallbacks",
            )
        )
        rows.append(
            Row(
                g,
                f"c3WBC / sWBC cycle median, {legs} stance legs (same run)",
                compliant["median"] / rigid["median"],
                "x",
                reference="thesis: STANCE / sWBC 0.74 / 0.68 = 1.09x (whole framework)" if legs == "4" else "",
            )
        )
    return rows


def rows_estimator(doc: dict) -> list[Row]:
    g, rows = "state estimator (333 Hz)", []
    budget = float(doc.get("budget_ms", 3.0))
    for mode, s in doc["summary"].items():
        u = s["update"]
        rows.append(
            Row(
                g,
                f"tick (StateEstimator.update), {mode} leg odometry, median",
                u["median"],
                "ms",
                Goal("<=", ESTIMATOR_TICK_GOAL_MS, "issue 31"),
                note=f"{u['n']} ticks",
            )
        )
        rows.append(
            Row(
                g,
                f"tick, {mode} leg odometry, p99",
                u["p99"],
                "ms",
                Goal("<=", budget, f"{budget:g} ms period at 333 Hz"),
                note=f"max {u['max']:.3f} ms",
            )
        )
    return rows


def rows_bags(doc: dict) -> list[Row]:
    g, rows = "bags (record, read, replay)", []
    goals = doc.get(
        "goals",
        {"recorder_cpu_share_of_one_core": 0.10, "replay_real_time_factor": 20.0, "memory_long_over_short": 1.2},
    )
    traffic = float(doc["messages_per_robot_second"])
    real_time = Goal(">=", traffic, "the graph's traffic")
    w, r = doc["writer"], doc["reader"]
    rows.append(
        Row(
            g,
            "BagWriter (zstd, 1 MiB chunks), graph traffic",
            w["messages_per_s"],
            "msg/s",
            real_time,
            note=f"{w['mb_per_s']:.1f} MB/s; {100 * w['cpu_share_of_one_core_at_real_time']:.1f} % of a core "
            "per real-time second",
        )
    )
    rows.append(
        Row(
            g,
            "BagReader, decoding every message",
            r["messages_per_s"],
            "msg/s",
            real_time,
            note=f"{r['mb_per_s']:.1f} MB/s",
        )
    )
    if "live_recorder" in doc:
        lv = doc["live_recorder"]
        rows.append(
            Row(
                g,
                f"bag_recorder node live, {lv['duration_s']:.0f} s at real time: CPU share of one core",
                100 * lv["recorder_cpu_share_of_one_core"],
                "%",
                Goal("<=", 100 * goals["recorder_cpu_share_of_one_core"], "issue"),
                note=f"recorded {lv['recorded']:,} of {lv['published']:,} published",
            )
        )
    for mode, rp in doc.get("replay", {}).items():
        rows.append(
            Row(
                g,
                f"offline replay (estimator + TCE, {mode}) of {rp['bag']}: x real time",
                rp["real_time_factor"],
                "x",
                Goal(">=", goals["replay_real_time_factor"], "issue"),
                note=f"{rp['bag_time_s']:.0f} s of robot time",
            )
        )
    memory = doc.get("memory", [])
    for case in ("write", "read"):
        pair = sorted((m for m in memory if m["case"] == case), key=lambda m: m["duration_s"])
        if len(pair) == 2:
            rows.append(
                Row(
                    g,
                    f"peak memory, {case}: {pair[1]['duration_s']:.0f} s bag / {pair[0]['duration_s']:.0f} s bag",
                    pair[1]["peak_rss_mb"] / pair[0]["peak_rss_mb"],
                    "x",
                    Goal("<=", goals["memory_long_over_short"], "issue"),
                    note=f"{pair[1]['peak_rss_mb']:.1f} vs {pair[0]['peak_rss_mb']:.1f} MB",
                )
            )
    return rows


def _worst_leg(results: dict, key: str = "median") -> tuple[float, str]:
    values = {leg: r["stats"][key] for leg, r in results.items()}
    return max(values.values()), f"legs {min(values.values()):.3f}-{max(values.values()):.3f} ms"


def rows_vfa(doc: dict) -> list[Row]:
    g, rows = "ViTAL: VFA (per leg)", []
    goal = Goal("<=", float(doc.get("goal_ms", 1.0)), "issue 6")
    thesis = f"thesis: {doc.get('thesis_mean_ms', THESIS_VFA_MS)} +- 1 ms mean (i7)"
    lazy = doc["results"]["vfa"]
    median, spread = _worst_leg(lazy)
    mean = max(r["stats"]["mean"] for r in lazy.values())
    rows.append(
        Row(
            g,
            "exact VFA (lazy search), median of the worst leg",
            median,
            "ms",
            goal,
            thesis,
            note=f"{spread}; mean {mean:.3f} ms (worst leg); {doc['inputs']['samples']} terrains",
        )
    )
    p99, _ = _worst_leg(lazy, "p99")
    rows.append(Row(g, "exact VFA, p99 of the worst leg", p99, "ms"))
    full, spread = _worst_leg(doc["results"]["vfa_full"])
    rows.append(Row(g, "full FEC on all candidates + argmin, median of the worst leg", full, "ms", note=spread))
    return rows


def rows_vfa_cnn(doc: dict) -> list[Row]:
    g, rows = "ViTAL: VFA CNN (per leg)", []
    goal = Goal("<=", float(doc.get("goal_ms", 0.5)), "issue 6")
    thesis = f"thesis: {doc.get('thesis_mean_ms', THESIS_VFA_CNN_MS)} +- 1 ms mean (i7, CPU)"
    median, spread = _worst_leg(doc["results"]["cnn"])
    backends = doc.get("backends", {})  # bench_vfa_cnn measures several network runtimes in one session
    first = doc.get("backend")
    if first in backends:
        runtime = backends[first]["label"]
    else:
        runtime = f"torch {doc.get('torch', '?')}, {doc.get('torch_threads', '?')} thread"
    others = [
        f"same session, {b['label']}: {b['headline_ms']['4legs_per_leg']['median']:.3f} ms per leg batched, "
        f"{b['headline_ms']['one_leg']['median']:.3f} ms one leg"
        for name, b in backends.items()
        if name != first
    ]
    rows.append(
        Row(
            g,
            "CNN VFA, one leg per call, median of the worst leg",
            median,
            "ms",
            goal,
            thesis,
            note=f"{spread}; {runtime}",
        )
    )
    batch = doc["results"]["cnn_4legs"]["4legs"]
    rows.append(
        Row(
            g,
            "CNN VFA, 4 legs in one batch: time per leg, median",
            batch["per_leg_stats"]["median"],
            "ms",
            goal,
            thesis,
            note=f"p99 {batch['per_leg_stats']['p99']:.3f} ms" + "".join(f"; {o}" for o in others),
        )
    )
    pair = doc["results"].get("cnn_2legs", {}).get("2legs")  # recorded since the planner batches a trot's pair
    if pair is not None:
        rows.append(
            Row(
                g,
                "CNN VFA, 2 legs (a trot's pair) in one batch: time per leg, median",
                pair["per_leg_stats"]["median"],
                "ms",
                goal,
                thesis,
                note=f"p99 {pair['per_leg_stats']['p99']:.3f} ms",
            )
        )
    verified = doc["results"]["cnn_verified"]
    median, spread = _worst_leg(verified)
    fallbacks = sum(r.get("fallbacks", 0) for r in verified.values())
    total = sum(r["stats"]["n"] for r in verified.values())
    rows.append(
        Row(
            g,
            "CNN VFA + exact verification (the `vfa` node's `cnn` selector), median of the worst leg",
            median,
            "ms",
            goal,
            note=f"{spread}; fell back to the exact search {fallbacks} of {total}",
        )
    )
    return rows


def rows_vpa(doc: dict) -> list[Row]:
    g, rows = "ViTAL: VPA (4 legs, N_h = 2)", []
    goals = doc.get("goal_ms", {"exact": 50.0, "cnn": 20.0})
    thesis = doc.get("thesis_mean_ms", {"exact": THESIS_VPA_MS, "cnn": THESIS_VPA_CNN_MS})
    spread = {"exact": 68, "cnn": 60}
    for mode in ("exact", "cnn"):
        r = doc["results"].get(mode)
        if r is None:
            rows.append(Row(g, f"{mode} VPA update", note="not in the JSON"))
            continue
        median = r["stats"]["median"]
        rows.append(
            Row(
                g,
                f"{mode} VPA update, median",
                median,
                "ms",
                Goal("<=", float(goals[mode]), "issue 6"),
                f"thesis: {thesis[mode]:.0f} +- {spread[mode]} ms mean (i7)",
                note=f"p99 {r['stats']['p99']:.1f} ms; {doc['inputs']['scenes']} scenes",
            )
        )
        rows.append(
            Row(
                g,
                f"{mode} VPA update rate (1 / median)",
                1e3 / median,
                "Hz",
                Goal(">=", 5.0, "DESIGN.md: 5 Hz, goal 20 Hz"),
                f"thesis: {1e3 / thesis[mode]:.1f} Hz" + (' ("roughly 5 Hz", l. 5571)' if mode == "cnn" else ""),
            )
        )
    return rows


def rows_graph_rates(doc: dict) -> list[Row]:
    g, rows = "graph rates (real-time graph run)", []
    for node, r in doc.get("nodes", {}).items():
        target = r.get("target_hz")
        note = ", ".join(f"{k.replace('_', ' ')} {r[k]}" for k in ("deadline_misses", "ticks") if k in r)
        rows.append(
            Row(
                g,
                f"{node}: achieved rate",
                r.get("achieved_hz"),
                "Hz",
                Goal(">=", float(target), "DESIGN.md section 3") if target else None,
                note=note,
            )
        )
    if doc.get("peak_rss_mb") is not None:
        rows.append(Row(g, "peak resident memory of the graph", doc["peak_rss_mb"], "MB"))
    return rows


GRAPH_GROUP_LOCKSTEP = "whole graph: lockstep tour (make run)"
GRAPH_GROUP_REALTIME = "whole graph: tour_realtime (wall clock)"


def _run_name(run: dict) -> str:
    name = Path(run["run_dir"]).name if run.get("run_dir") else "?"
    return f"{name} (reused)" if run.get("reused") else name


def _fall(run: dict) -> str:
    if not run.get("fell"):
        return "no fall"
    at = run.get("fall_time_s")
    return (
        "fell"
        + (f" at {at:.2f} s of sim time" if isinstance(at, (int, float)) else "")
        + (f" ({run['fall_reason']})" if run.get("fall_reason") else "")
    )


def rows_bench_graph(doc: dict) -> list[Row]:
    """Issue 31's goals 1 and 2 from bench_graph.py: CPU per simulated second of the lockstep tour; per node the
    rate on the wall clock and the missed deadlines of the real-time tours, whether HyQ walks the course as in
    lockstep, and the joint-state-to-command latency."""
    goals, rows = doc["goals"], []
    g = GRAPH_GROUP_LOCKSTEP
    lock = doc.get("lockstep")
    if lock is None:
        rows.append(Row(g, "lockstep tour", note="not run (--skip-lockstep and no runs/*-tour folder)"))
    elif lock.get("cpu") is None:
        rows.append(Row(g, "lockstep tour", note=f"failed: {lock.get('error', 'no resources.json')}"))
    else:
        cpu, sim_s = lock["cpu"], lock["sim_time_s"]
        rows.append(
            Row(
                g,
                "lockstep tour: graph CPU per sim-s",
                cpu["graph_cpu_s_per_sim_s"],
                "CPU-s/sim-s",
                Goal("<=", goals["graph_cpu_s_per_sim_s"], "issue 31"),
                note="; ".join(
                    part
                    for part in (
                        f"{cpu['graph_cpu_s']:.1f} CPU-s (user + system, every process of the {len(cpu['nodes'])} "
                        f"nodes, start-up included) over {sim_s:g} s of sim time",
                        f"RTF {lock['real_time_factor']}",
                        _others({"other_cpus": lock.get("other_cores_busy")}),
                        _run_name(lock),
                    )
                    if part
                ),
            )
        )
        others = ", ".join(
            f"{name} {n['cpu_s_per_sim_s']:.2f}" for name, n in cpu["nodes"].items() if name != cpu["busiest_node"]
        )
        rows.append(
            Row(
                g,
                f"lockstep tour: busiest node CPU per sim-s ({cpu['busiest_node']})",
                cpu["busiest_cpu_s_per_sim_s"],
                "CPU-s/sim-s",
                Goal("<=", goals["node_cpu_s_per_sim_s"], "issue 31: no node above"),
                note=f"the others: {others}",
            )
        )
        touched = lock.get("links_touching_terrain") or []
        rows.append(
            Row(
                g,
                "lockstep tour walks the course: distance",
                lock.get("distance_m"),
                "m",
                note=f"fell: {'yes' if lock.get('fell') else 'no'}"
                + (f" ({', '.join(touched)} touched the terrain)" if touched else "")
                + "; the real-time runs' reference",
            )
        )
    g = GRAPH_GROUP_REALTIME
    runs = doc.get("realtime", [])
    if not runs:
        rows.append(Row(g, "tour_realtime", note="not run (--skip-realtime and no runs/*-tour_realtime folder)"))
        return rows
    summary = doc["summary"]
    finished = [r for r in runs if "fell" in r]
    n = len(runs)
    failed = [f"run {i}: {r.get('error')}" for i, r in enumerate(runs, 1) if "error" in r]
    for node, s in summary.get("nodes", {}).items():
        lower = [
            r["rates"][node]["achieved_hz_log_lower_bound"]
            for r in runs
            if r.get("rates") and r["rates"].get(node) and r["rates"][node].get("achieved_hz_log_lower_bound")
        ]
        worst = s["worst_achieved_hz"]
        design = f"; design goal {s['target_hz']:.4g} Hz" + (
            f": worst / goal {worst / s['target_hz']:.2f}" if worst is not None else ""
        )
        rows.append(
            Row(
                g,
                f"tour_realtime, {node}: rate on the wall clock, worst of {n}",
                s["worst_achieved_hz"],
                "Hz",
                Goal(">=", float(s["goal_hz"]), "issue 31"),
                note=f"runs: {', '.join(f'{x:.1f}' for x in s['achieved_hz'])} Hz"
                + (f"; from the bridge's log span at least {min(lower):.1f} Hz" if lower else "")
                + (design if s["goal_hz"] != s["target_hz"] else ""),
            )
        )
        rows.append(
            Row(
                g,
                f"tour_realtime, {node}: missed deadlines, worst of {n}",
                s["worst_missed_share_pct"],
                "%",
                Goal("<=", goals["missed_deadline_share_pct"], "issue 31"),
                note=f"missed / expected ticks at {s['target_hz']:.4g} Hz, runs: "
                f"{', '.join(f'{x:.2f}' for x in s['missed_share_pct'])} %; rate and deadlines met in "
                f"{s['runs_meeting_goals']} of {n} runs",
            )
        )
    if finished:
        falls = summary["falls"]
        rows.append(
            Row(
                g,
                f"tour_realtime walks the course: runs without a fall ({len(finished) - falls} of {n})",
                100.0 * (len(finished) - falls) / n,
                "%",
                Goal(">=", 100.0, f"issue 31: {n} of {n}"),
                note="; ".join(f"{_run_name(r)}: {_fall(r)}" for r in finished),
            )
        )
        ratios = [r.get("distance_over_lockstep") for r in finished]
        rows.append(
            Row(
                g,
                "tour_realtime walks the course: distance vs lockstep, worst deviation",
                summary.get("worst_distance_deviation_pct"),
                "%",
                Goal("<=", goals["distance_deviation_pct"], "issue 31"),
                note="distances "
                + ", ".join("n/a" if r.get("distance_m") is None else f"{r['distance_m']:.2f} m" for r in finished)
                + f" vs lockstep {fmt_number(summary.get('lockstep_distance_m'))} m; ratios "
                + ", ".join("n/a" if x is None else f"{x:.3f}" for x in ratios),
            )
        )
        latency = summary.get("command_latency_ms")
        for key in ("median", "p99"):
            what = f"tour_realtime: joint state -> command latency, {key} (worst of {n})"
            values = [x for x in (latency or {}).get(key, []) if x is not None]
            if values:
                rows.append(Row(g, what, max(values), "ms", note=f"runs: {', '.join(f'{x:.3f}' for x in values)} ms"))
            else:
                rows.append(Row(g, what, note="not in bridge_summary.json (command_latency_ms)"))
        bounds = [x for x in summary.get("real_time_factor_log_lower_bound", []) if x is not None]
        if bounds:
            rows.append(
                Row(
                    g,
                    "tour_realtime: bridge real-time factor, lower bound from its log (worst run)",
                    min(bounds),
                    "x",
                    note="sim time / wall time from 'sim_bridge ready' to 'run finished' (includes the wait for "
                    "the first command); the summary's RTF "
                    + ", ".join(str(r.get("real_time_factor")) for r in finished)
                    + " leaves out the time dropped by "
                    + ", ".join(str(r.get("realtime_overruns")) for r in finished)
                    + " overruns",
                )
            )
        cpu = [r["cpu"] for r in finished if r.get("cpu")]
        if cpu:
            rows.append(
                Row(
                    g,
                    "tour_realtime: graph CPU per sim-s (worst run)",
                    max(c["graph_cpu_s_per_sim_s"] for c in cpu),
                    "CPU-s/sim-s",
                    note="busiest node "
                    + ", ".join(f"{c['busiest_node']} {c['busiest_cpu_s_per_sim_s']:.2f}" for c in cpu),
                )
            )
    if failed:
        rows.append(Row(g, f"tour_realtime: failed runs ({len(failed)} of {n})", note="; ".join(failed)))
    return rows


def rows_peers(docs: dict[str, dict]) -> list[Row]:
    """Issue 31 goal 3, control at the speed of the C++ peers: sWBC and c3WBC cycle medians over TSID's (bench_wbc's
    TSID side; bench_stance's c3WBC solves the same seeded states in another session)."""
    g, rows = "control vs the C++ peer (TSID)", []
    tsid = (docs.get("bench_wbc", {}).get("summary") or {}).get("tsid") or {}
    goal = Goal("<=", 1.0, "issue 31: the speed of the C++ peer")
    for legs in ("4", "2"):
        peer = tsid.get(legs, {}).get("cycle", {}).get("median")
        if not peer:
            continue
        ours = docs["bench_wbc"]["summary"]["ours"][legs]["cycle"]["median"]
        rows.append(
            Row(
                g,
                f"sWBC / TSID cycle median, {legs} stance legs",
                ours / peer,
                "x",
                goal,
                f"TSID 1.7.1: {peer:.3f} ms",
                note=f"sWBC {ours:.3f} ms, same states, same session (bench_wbc)",
            )
        )
        compliant = (docs.get("bench_stance", {}).get("wbc") or {}).get("compliant", {}).get(legs)
        if compliant:
            rows.append(
                Row(
                    g,
                    f"c3WBC / TSID cycle median, {legs} stance legs",
                    compliant["median"] / peer,
                    "x",
                    goal,
                    f"TSID 1.7.1: {peer:.3f} ms",
                    note=f"c3WBC {compliant['median']:.3f} ms (bench_stance), TSID from bench_wbc: same seeded "
                    "states, another session",
                )
            )
    return rows


def rows_across_hosts(doc: dict) -> list[Row]:
    g, rows = "across hosts (2 network namespaces)", []
    for r in doc.get("rows", []):
        goal = Goal(r["goal_op"], float(r["goal"]), r.get("goal_source", "")) if r.get("goal") is not None else None
        rows.append(
            Row(g, r["what"], r.get("value"), r.get("unit", ""), goal, r.get("reference", ""), r.get("note", ""))
        )
    return rows


# name -> (row group, rows, required?): required benches give a "not run" row when their JSON is missing.
BENCHES: dict[str, tuple[str, Callable[[dict], list[Row]], bool]] = {
    "bench_bridge": ("bridge (PyBullet HyQ, 1 kHz physics)", rows_bridge, True),
    "bench_wbc": ("sWBC (250 Hz)", rows_wbc, True),
    "bench_stance": ("STANCE: TCE (250 Hz) and c3WBC", rows_stance, True),
    "bench_estimator": ("state estimator (333 Hz)", rows_estimator, True),
    "bench_bags": ("bags (record, read, replay)", rows_bags, True),
    "bench_vfa": ("ViTAL: VFA (per leg)", rows_vfa, True),
    "bench_vfa_cnn": ("ViTAL: VFA CNN (per leg)", rows_vfa_cnn, True),
    "bench_vpa": ("ViTAL: VPA (4 legs, N_h = 2)", rows_vpa, True),
    "bench_graph": ("whole graph: tour (lockstep and real time)", rows_bench_graph, True),
    "graph_rates": ("graph rates (real-time graph run)", rows_graph_rates, False),
    "across_hosts": ("across hosts (2 network namespaces)", rows_across_hosts, False),
}


def load(out_dir: Path, name: str) -> tuple[dict | None, str]:
    """(document, "") or (None, why not)."""
    path = out_dir / f"{name}.json"
    if not path.is_file():
        return None, f"not run ({path.name} missing)"
    try:
        return json.loads(path.read_text()), ""
    except (OSError, json.JSONDecodeError) as exc:
        return None, f"unreadable {path.name}: {exc}"


def collect(out_dir: Path) -> tuple[list[Row], dict[str, dict]]:
    """All rows, in BENCHES order, and the documents that could be read."""
    rows: list[Row] = []
    docs: dict[str, dict] = {}
    for name, (group, extract, required) in BENCHES.items():
        doc, why = load(out_dir, name)
        if doc is None:
            if required or not why.startswith("not run"):
                rows.append(Row(group, f"`bench/{name}.py`" if required else name, note=why))
            continue
        try:
            rows += extract(doc)
        except (KeyError, TypeError, ValueError, ZeroDivisionError, IndexError) as exc:
            rows.append(Row(group, name, note=f"unreadable {name}.json: {type(exc).__name__} {exc}"))
            continue
        docs[name] = doc
    try:
        rows += rows_peers(docs)
    except (KeyError, TypeError, ValueError, ZeroDivisionError) as exc:
        rows.append(Row("control vs the C++ peer (TSID)", "ratios", note=f"unreadable: {type(exc).__name__} {exc}"))
    return rows, docs


def _size(name: str, doc: dict) -> str:
    """The run's size, marked "reduced" when smaller than the bench's default."""

    def mark(text: str, reduced: bool) -> str:
        return f"{text} (reduced)" if reduced else text

    if name == "bench_bridge":
        s = doc.get("settings", {})
        quick = s.get("quick") == "True"
        return mark(
            f"{s.get('repeats')} x {s.get('steps')} steps, lockstep {s.get('duration_s')} s",
            quick or int(s.get("steps", 4000)) < 4000 or float(s.get("duration_s", 5.0)) < 5.0,
        )
    if name == "bench_wbc":
        n = doc.get("states_per_sequence", 0)
        return mark(f"{n} states x 2 sequences x {doc.get('rounds')} rounds", n < 500)
    if name == "bench_stance":
        return mark(
            "--quick" if doc.get("settings", {}).get("quick") else "full", bool(doc.get("settings", {}).get("quick"))
        )
    if name == "bench_estimator":
        n = doc.get("ticks_per_round", 0)
        return mark(f"{n} ticks x {doc.get('rounds')} rounds per mode", n < 3000)
    if name == "bench_bags":
        quick = bool(doc.get("settings", {}).get("quick"))
        return mark("--quick (10 s / 100 s bags, 5 s live)" if quick else "60 s / 600 s bags, 20 s live", quick)
    if name in ("bench_vfa", "bench_vfa_cnn"):
        n = doc.get("inputs", {}).get("samples", 0)
        return mark(f"{n} terrains x {doc.get('rounds')} rounds", n < 200)
    if name == "bench_graph":
        s = doc.get("settings", {})
        runs, duration = int(s.get("runs", 0)), float(s.get("duration_s", 40.0))
        text = f"tour {duration:g} s: lockstep{' reused' if s.get('skip_lockstep') else ''} + " + (
            "real time reused" if s.get("skip_realtime") else f"{runs} real-time run(s)"
        )
        return mark(text, runs < int(s.get("default_runs", 3)) or duration < float(s.get("default_duration_s", 40.0)))
    if name == "bench_vpa":
        n = doc.get("inputs", {}).get("scenes", 0)
        return mark(f"{n} scenes x {doc.get('rounds')} rounds", n < 40)
    return "-"


def _others_busy(doc: dict) -> float | None:
    """Cores other processes kept busy on average while the bench measured (None: not recorded)."""
    others = doc.get("machine", {}).get("other_processes_cores_busy", doc.get("other_processes_cores_busy"))
    if isinstance(others, list):
        others = [x for x in others if x is not None]
        others = sum(others) / len(others) if others else None
    return float(others) if isinstance(others, (int, float)) else None


def _load_of_others(doc: dict) -> str:
    m = doc.get("machine", {})
    others = _others_busy(doc)
    load = (
        m.get("load_average_at_start_1_5_15min") or doc.get("load_average_at_start") or m.get("load_average_1_5_15min")
    )
    parts = []
    if others is not None:
        parts.append(f"others {others:.2f} cores")
    if load:
        parts.append(f"load avg {load[0]}")
    return ", ".join(parts) or "-"


def render(rows: list[Row], docs: dict[str, dict], machine: dict, note: str = "") -> str:
    def cell(text: str) -> str:
        return text.replace("|", "\\|") or "-"

    lines = [
        "# Benchmarks (`make bench`)",
        "",
        f"Written by `bench/report.py` on {machine.get('date')} from `bench/out/*.json`. Machine: "
        f"{machine.get('cpus')} CPUs ({machine.get('cpu_model')}), Python {machine.get('python')}, "
        f"{machine.get('platform')}, {machine.get('rmw')}, commit {machine.get('git_commit')}, load average "
        f"{machine.get('load_average_1_5_15min')} (1/5/15 min). The machine is a 2-vCPU VM shared with other "
        "engineers' builds and tests: every figure moves with their load (see Sources); compare figures of the "
        "same run and read ratios rather than absolute times.",
        "",
        *(
            [
                f"While the benches that record it measured, other processes kept {min(busy):.2f}-{max(busy):.2f} of "
                f"the {machine.get('cpus')} cores busy on average.",
                "",
            ]
            if (busy := [b for b in map(_others_busy, docs.values()) if b is not None])
            else []
        ),
        *([note.strip(), ""] if note.strip() else []),
        "measured / goal: below 1 is good for a time or a share (goal `<=`), above 1 for a rate or a real-time "
        "factor (goal `>=`).",
        "",
        "| group | what | measured | goal | measured / goal | met | thesis / peer | notes |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        value = (
            "**not run**"
            if r.value is None and r.note.startswith("not run")
            else ("n/a" if r.value is None else f"{fmt_number(r.value)} {r.unit}".rstrip())
        )
        met = {None: "-", True: "yes", False: "**no**"}[r.met]
        goal = r.goal.text(r.unit) if r.goal else ""
        ratio = fmt_number(r.ratio) if r.ratio is not None else ""
        lines.append(
            f"| {cell(r.group)} | {cell(r.what)} | {cell(value)} | {cell(goal)} | {cell(ratio)} | {met} | "
            f"{cell(r.reference)} | {cell(r.note)} |"
        )
    for name, (group, _, required) in BENCHES.items():
        if not required and name not in docs:
            lines.append(f'\nNo `bench/out/{name}.json`: the row group "{group}" is left out.')
    lines += ["", "## Sources", "", "| JSON | date | commit | size | load while measuring |", "|---|---|---|---|---|"]
    for name, doc in docs.items():
        m = doc.get("machine", {})
        lines.append(
            f"| `bench/out/{name}.json` | {m.get('date', doc.get('date', '-'))} | "
            f"{m.get('git_commit', '-')} | {_size(name, doc)} | {_load_of_others(doc)} |"
        )
    across = docs.get("across_hosts", {}).get("markdown")
    if across:
        lines += ["", across.strip()]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", type=Path, default=OUT_DIR, help="where the benches wrote their JSON")
    parser.add_argument("--output", type=Path, default=OUTPUT, help="the markdown file to write")
    parser.add_argument("--note", default="", help="a paragraph on the run's conditions, printed under the header")
    args = parser.parse_args(argv)
    rows, docs = collect(args.out_dir)
    text = render(rows, docs, machine_info(), args.note)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text)
    not_run = sum(1 for r in rows if r.note.startswith(("not run", "unreadable")))
    print(f"bench/report.py: {len(rows)} rows ({not_run} not run or unreadable) -> {args.output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
