#!/usr/bin/env python3
"""The whole node graph on the tour (issue 31): CPU per simulated second in lockstep, rates on the wall clock.

Run after ``source scripts/env.sh``:  ``python bench/bench_graph.py [--runs N] [--duration-s S]
[--skip-lockstep] [--skip-realtime] [--wait-quiet S]``. Prints a markdown table on stdout, progress on stderr,
and writes ``bench/out/bench_graph.json`` (``bench/report.py`` turns it into rows against the goals).

1. Lockstep tour: ``scripts/run_scenario.sh tour`` (what ``make run`` runs; ``DURATION_S`` = ``--duration-s``,
   40 s of sim time by default). From its run folder: ``resources.json`` (every process of each node, CPU time
   user + system sampled each second by ``tal_core.resource_monitor``; it includes each node's start-up and
   shutdown) over the bridge's ``sim_time_s`` gives the CPU seconds per simulated second per node and for the
   graph (goals: graph <= 1.5, no node above 0.4); the bridge's real-time factor; fell and distance.
2. Real-time tour, ``--runs`` times (default 3; the goal is 3 of 3): ``scripts/run_scenario.sh tour_realtime``.
   From ``graph_summary.json`` (``tal_lab.graph_report``: header stamps of the recorded messages) each node's
   rate on the wall clock (its main output's sim-time rate times the bridge's real-time factor) against its
   target (bridge 1 kHz, estimator 333 Hz, TCE and WBC 250 Hz, VPA >= 5 Hz with a design goal of 20 Hz) and
   its missed deadlines: missed ticks (stamp gaps of n periods miss n - 1) / expected ticks (received + missed),
   goal <= 1 %. Whether HyQ fell (``tal_lab.run_report.fall_of``: the bridge's fall detection) and its distance
   against the lockstep run's (goal: within 5 %). The bridge's ``command_latency_ms`` (joint state to command)
   when its summary has it.

Each real-time run also records a cross-check of the bridge's real-time factor from its log: sim time over the
wall time from "sim_bridge ready" to "run finished", a lower bound (it includes the wait for the first command).

``--skip-lockstep`` / ``--skip-realtime`` reuse the newest ``runs/*-tour`` / ``runs/*-tour_realtime`` folder
instead (marked ``reused``). Graphs run one at a time (the machine has 2 cores); each run's console output goes
to ``bench/out/bench_graph_<scenario>_<i>.log``. A benchmark, never a pass/fail test.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from common import OUT_DIR, ROOT, fmt, progress_for, requires_env, write_json  # bench/common.py
from machine import add_wait_quiet_option, cpu_snapshot, machine_record, other_cores_busy, settle_machine

with requires_env("bench_graph"):
    from tal_lab.graph_report import bench_rates
    from tal_lab.run_report import fall_of

DEFAULT_DURATION_S = 40.0  # [s] both tours (make run's lockstep tour is 60 s; the real-time one falls by 35 s)
DEFAULT_RUNS = 3
GOALS = {
    "graph_cpu_s_per_sim_s": 1.5,
    "node_cpu_s_per_sim_s": 0.4,
    "missed_deadline_share_pct": 1.0,
    "distance_deviation_pct": 5.0,
    # The rate each node holds on the wall clock (DESIGN.md section 3); the VPA's minimum is 5 Hz, its goal 20.
    "rate_hz": {"sim_bridge": 1000.0, "state_estimator": 1000.0 / 3.0, "tce": 250.0, "wbc": 250.0, "vpa": 5.0},
}
LOG_LINE = re.compile(r"^\[\w+\] \[(?P<t>\d+\.\d+)\] \[sim_bridge\]: (?P<what>sim_bridge ready|run finished)")

progress = progress_for("bench_graph")


# -- one run ---------------------------------------------------------------------------------------------------
def run_scenario(scenario: str, duration_s: float, log_path: Path) -> dict:
    """``bash scripts/run_scenario.sh SCENARIO`` with ``DURATION_S``; console output to ``log_path``. Returns the
    run folder (from the script's "[run] report: ..." line), exit code, wall time and the others' CPU use."""
    env = dict(os.environ, DURATION_S=f"{duration_s:.1f}")
    started = time.time()
    before = cpu_snapshot()
    t0 = time.monotonic()
    with log_path.open("w") as log:
        rc = subprocess.run(
            ["bash", str(ROOT / "scripts" / "run_scenario.sh"), scenario],
            cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, check=False,
        ).returncode  # fmt: skip
    wall = time.monotonic() - t0
    others = other_cores_busy(before, cpu_snapshot())
    text = log_path.read_text(errors="replace")
    found = re.findall(r"^\[run\] report: (.+)/report\.md$", text, flags=re.M)
    run_dir = Path(found[-1]) if found else newest_run(scenario, after=started - 2.0)
    return {
        "scenario": scenario,
        "run_dir": None if run_dir is None else str(run_dir),
        "exit_code": rc,
        "script_wall_s": round(wall, 1),
        "other_cores_busy": None if others is None else round(others, 3),
        "log": str(log_path.relative_to(ROOT)),
        "reused": False,
    }


def newest_run(scenario: str, after: float = 0.0) -> Path | None:
    """The newest ``runs/<timestamp>-<scenario>`` folder (modified after ``after``, epoch seconds)."""
    runs = ROOT / "runs"
    candidates = [p for p in runs.glob(f"*-{scenario}") if p.is_dir() and p.stat().st_mtime >= after]
    return max(candidates, key=lambda p: p.name, default=None)


def _json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def bridge_log_span(log: Path) -> float | None:
    """Wall time [s] from the bridge's "sim_bridge ready" to its "run finished" log line (None if absent)."""
    stamps: dict[str, float] = {}
    try:
        lines = log.read_text(errors="replace").splitlines()
    except OSError:
        return None
    for line in lines:
        m = LOG_LINE.match(line)
        if m:
            stamps.setdefault(m["what"], float(m["t"]))
    if "sim_bridge ready" in stamps and "run finished" in stamps:
        return stamps["run finished"] - stamps["sim_bridge ready"]
    return None


def latency(value: dict | None) -> dict | None:
    """The bridge's ``command_latency_ms`` (``tal_sim_bridge.latency``: median_ms, p99_ms, max_ms, count) as
    {median, p99, max, n}; None when the summary has none or no command was timed."""
    if not value or not value.get("count"):
        return None
    return {"median": value["median_ms"], "p99": value["p99_ms"], "max": value["max_ms"], "n": value["count"]}


def read_run(run: dict) -> dict:
    """Adds what the run folder holds to ``run``: the bridge's figures, CPU per sim-s, rates, fall, distance."""
    if run.get("run_dir") is None:
        run["error"] = "no run folder found"
        return run
    d = Path(run["run_dir"])
    bridge, resources = _json(d / "bridge_summary.json"), _json(d / "resources.json")
    summary, wbc = _json(d / "graph_summary.json"), _json(d / "wbc_summary.json")
    if bridge is None:
        run["error"] = f"no bridge_summary.json in {d} (did the graph finish? see {run.get('log')})"
        return run
    sim_s = float(bridge["sim_time_s"])
    touched = list(bridge.get("body_ground_contact", []))
    fall = fall_of(bridge)  # the reports' own reading of the bridge summary
    fell = fall is not None
    # Distance: the bridge's if it reports one, else graph_report's (to the fall's onset after a fall), else the
    # wbc's (ground-truth base, start to end).
    if bridge.get("distance_m") is not None:
        distance, source = bridge["distance_m"], "bridge"
    elif summary is not None and "distance_m" in summary:
        distance, source = summary["distance_m"], "graph_report" + (" (to the fall)" if fell else "")
    else:
        distance, source = (wbc or {}).get("distance_m"), "wbc (ground-truth base, start to end)"
    span = bridge_log_span(d / "sim_bridge.log")
    run.update(
        mode=bridge.get("mode"),
        sim_time_s=sim_s,
        bridge_wall_time_s=bridge.get("wall_time_s"),
        real_time_factor=bridge.get("real_time_factor"),
        bridge_log_span_s=None if span is None else round(span, 3),
        real_time_factor_log_lower_bound=round(sim_s / span, 4) if span else None,
        realtime_overruns=bridge.get("realtime_overruns"),
        lockstep_timeouts=bridge.get("lockstep_timeouts"),
        commands_accepted=bridge.get("commands_accepted"),
        fell=bool(fell),
        fall_time_s=None if fall is None else fall.time_s,
        fall_reason=None if fall is None else fall.reason,
        links_touching_terrain=touched,
        distance_m=distance,
        distance_source=source,
        command_latency_ms=latency(bridge.get("command_latency_ms")),
    )
    if resources is not None and sim_s > 0:
        nodes = {
            name: {"cpu_s": n["cpu_s"], "cpu_s_per_sim_s": round(n["cpu_s"] / sim_s, 4),
                   "peak_rss_mb": n.get("peak_rss_mb")}
            for name, n in sorted(resources["nodes"].items(), key=lambda kv: -kv[1]["cpu_s"])
        }  # fmt: skip
        total = sum(n["cpu_s"] for n in nodes.values())
        busiest = next(iter(nodes), None)
        run["cpu"] = {
            "monitor_wall_s": resources.get("wall_s"),
            "graph_cpu_s": round(total, 3),
            "graph_cpu_s_per_sim_s": round(total / sim_s, 4),
            "busiest_node": busiest,
            "busiest_cpu_s_per_sim_s": None if busiest is None else nodes[busiest]["cpu_s_per_sim_s"],
            "peak_total_rss_mb": resources.get("peak_total_rss_mb"),
            "nodes": nodes,
        }
    else:
        run["cpu"] = None
    if summary is not None:
        rates = bench_rates(summary)["nodes"]
        scale = (run["real_time_factor_log_lower_bound"] / run["real_time_factor"]
                 if run["real_time_factor_log_lower_bound"] and run["real_time_factor"] else None)  # fmt: skip
        for node, r in rates.items():
            misses, ticks = r.get("deadline_misses"), r.get("ticks") or 0
            expected = ticks + (misses or 0)
            r["missed_share_pct"] = None if misses is None or expected == 0 else round(100.0 * misses / expected, 3)
            r["achieved_hz_log_lower_bound"] = (
                None if scale is None or r["achieved_hz"] is None else round(r["achieved_hz"] * scale, 3)
            )
            r["goal_hz"] = GOALS["rate_hz"].get(node)
        run["rates"] = rates
    else:
        run["rates"] = None
        run.setdefault("error", f"no graph_summary.json in {d} (graph_report failed? see {run.get('log')})")
    return run


def reuse(scenario: str, duration_s: float) -> dict | None:
    d = newest_run(scenario)
    if d is None:
        return None
    progress(f"reusing {d.relative_to(ROOT)}")
    run = read_run({"scenario": scenario, "run_dir": str(d), "exit_code": None, "reused": True})
    if run.get("sim_time_s") is not None and abs(run["sim_time_s"] - duration_s) > 0.01:
        progress(f"warning: {d.name} ran {run['sim_time_s']:g} s of sim time, not {duration_s:g}")
    return run


# -- summary over the runs ---------------------------------------------------------------------------------------
def summarise(lockstep: dict | None, realtime: list[dict]) -> dict:
    """Per node over the real-time runs: worst rate, worst missed share, runs meeting both goals; falls, distance
    deviation from the lockstep run, latency."""
    reference = None if lockstep is None else lockstep.get("distance_m")
    out: dict = {"lockstep_distance_m": reference, "runs": len(realtime), "nodes": {}}
    good = [r for r in realtime if r.get("rates")]
    for node, goal in GOALS["rate_hz"].items():
        per_run = [r["rates"].get(node) for r in good if r["rates"].get(node)]
        if not per_run:
            continue
        rates = [p["achieved_hz"] for p in per_run if p["achieved_hz"] is not None]
        shares = [p["missed_share_pct"] for p in per_run if p["missed_share_pct"] is not None]
        met = sum(
            1 for p in per_run
            if p["achieved_hz"] is not None and p["achieved_hz"] >= goal
            and p["missed_share_pct"] is not None and p["missed_share_pct"] <= GOALS["missed_deadline_share_pct"]
        )  # fmt: skip
        out["nodes"][node] = {
            "target_hz": per_run[0]["target_hz"], "goal_hz": goal, "achieved_hz": rates,
            "worst_achieved_hz": min(rates, default=None), "missed_share_pct": shares,
            "worst_missed_share_pct": max(shares, default=None), "runs_meeting_goals": met,
        }  # fmt: skip
    finished = [r for r in realtime if "fell" in r]
    out["falls"] = sum(1 for r in finished if r["fell"])
    out["finished_runs"] = len(finished)
    deviations = []
    for r in finished:
        if reference and r.get("distance_m") is not None:
            r["distance_over_lockstep"] = round(r["distance_m"] / reference, 4)
            deviations.append(abs(r["distance_over_lockstep"] - 1.0) * 100.0)
    out["distance_deviation_pct"] = [round(x, 2) for x in deviations]
    out["worst_distance_deviation_pct"] = round(max(deviations), 2) if deviations else None
    lat = [r["command_latency_ms"] for r in finished if r.get("command_latency_ms")]
    out["command_latency_ms"] = {
        "median": [x["median"] for x in lat], "p99": [x["p99"] for x in lat]} if lat else None  # fmt: skip
    out["real_time_factor_log_lower_bound"] = [r.get("real_time_factor_log_lower_bound") for r in finished]
    out["realtime_overruns"] = [r.get("realtime_overruns") for r in finished]
    return out


def table(doc: dict) -> str:
    lines = ["| measurement | value | goal |", "|---|---|---|"]
    lock = doc.get("lockstep")
    if lock and lock.get("cpu"):
        c = lock["cpu"]
        lines.append(
            f"| lockstep tour: graph CPU per sim-s ({lock['sim_time_s']:.0f} s sim, RTF "
            f"{fmt(lock.get('real_time_factor'), 3)}) | {c['graph_cpu_s_per_sim_s']:.3f} "
            f"({c['graph_cpu_s']:.1f} CPU-s) | <= {GOALS['graph_cpu_s_per_sim_s']} |"
        )
        for name, n in c["nodes"].items():
            lines.append(
                f"| lockstep tour: {name} CPU per sim-s | {n['cpu_s_per_sim_s']:.3f} | "
                f"<= {GOALS['node_cpu_s_per_sim_s']} |"
            )
        lines.append(
            f"| lockstep tour: fell / distance | {'yes' if lock['fell'] else 'no'} / "
            f"{fmt(lock.get('distance_m'), 2)} m | no fall |"
        )
    elif lock:
        lines.append(f"| lockstep tour | failed: {lock.get('error', '?')} | - |")
    s = doc.get("summary", {})
    for node, n in s.get("nodes", {}).items():
        rates = ", ".join(fmt(x, 1) for x in n["achieved_hz"])
        shares = ", ".join(fmt(x, 2) for x in n["missed_share_pct"])
        lines.append(
            f"| tour_realtime: {node} rate on the wall clock [Hz] (per run) | {rates} | "
            f">= {n['goal_hz']:.4g} (target {n['target_hz']:.4g}) |"
        )
        lines.append(
            f"| tour_realtime: {node} missed deadlines [%] (per run) | {shares} | "
            f"<= {GOALS['missed_deadline_share_pct']} |"
        )
    for i, r in enumerate(doc.get("realtime", []), 1):
        if "fell" not in r:
            lines.append(f"| tour_realtime run {i} | failed: {r.get('error', '?')} | - |")
            continue
        ratio = r.get("distance_over_lockstep")
        lines.append(
            f"| tour_realtime run {i}: fell / distance (/ lockstep) | "
            f"{('yes, at ' + fmt(r.get('fall_time_s'), 2) + ' s') if r['fell'] else 'no'} / "
            f"{fmt(r.get('distance_m'), 2)} m ({fmt(ratio, 3)}) | no fall, within 5 % |")  # fmt: skip
        lines.append(
            f"| tour_realtime run {i}: bridge RTF (summary) / lower bound (log) / overruns | "
            f"{fmt(r.get('real_time_factor'), 3)} / {fmt(r.get('real_time_factor_log_lower_bound'), 3)} / "
            f"{r.get('realtime_overruns')} | - |")  # fmt: skip
        lat = r.get("command_latency_ms")
        lines.append(
            f"| tour_realtime run {i}: joint state -> command latency median / p99 [ms] | "
            + (f"{fmt(lat['median'])} / {fmt(lat['p99'])}" if lat else "not in bridge_summary.json")
            + " | - |"
        )
        if r.get("cpu"):
            lines.append(
                f"| tour_realtime run {i}: graph CPU per sim-s / busiest node | "
                f"{r['cpu']['graph_cpu_s_per_sim_s']:.3f} / {r['cpu']['busiest_node']} "
                f"{fmt(r['cpu']['busiest_cpu_s_per_sim_s'])} | - |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=DEFAULT_RUNS, help="real-time tours (the goal is 3 of 3)")
    parser.add_argument("--duration-s", type=float, default=DEFAULT_DURATION_S, help="[s] sim time of each tour")
    parser.add_argument("--skip-lockstep", action="store_true", help="reuse the newest runs/*-tour folder")
    parser.add_argument("--skip-realtime", action="store_true", help="reuse the newest runs/*-tour_realtime folder")
    parser.add_argument("--output", type=Path, default=OUT_DIR / "bench_graph.json")
    add_wait_quiet_option(parser)
    args = parser.parse_args(argv)
    if args.runs < 0 or args.duration_s <= 0:
        parser.error("--runs must be >= 0 and --duration-s > 0")
    if not os.environ.get("AMENT_PREFIX_PATH") or not (ROOT / "ros2_ws" / "install").is_dir():
        raise SystemExit("bench_graph: the ROS environment is not set up; run it after `source scripts/env.sh`")
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    load_at_start = settle_machine(args.wait_quiet, progress)
    started = time.monotonic()

    if args.skip_lockstep:
        lockstep = reuse("tour", args.duration_s)
    else:
        progress(f"lockstep tour, {args.duration_s:g} s of sim time (~2.5 min)")
        lockstep = read_run(run_scenario("tour", args.duration_s, OUT_DIR / "bench_graph_tour.log"))
        progress(f"lockstep: {lockstep.get('error') or lockstep['run_dir']}")
    realtime: list[dict] = []
    if args.skip_realtime:
        reused = reuse("tour_realtime", args.duration_s)
        realtime = [reused] if reused else []
    else:
        for i in range(1, args.runs + 1):
            progress(f"real-time tour {i} of {args.runs}, {args.duration_s:g} s (~1.5 min)")
            run = read_run(
                run_scenario("tour_realtime", args.duration_s, OUT_DIR / f"bench_graph_tour_realtime_{i}.log")
            )
            progress(f"real-time {i}: {run.get('error') or run['run_dir']}")
            realtime.append(run)

    busy = [r["other_cores_busy"] for r in [lockstep, *realtime] if r and r.get("other_cores_busy") is not None]
    doc = {
        "benchmark": "bench_graph",
        "machine": machine_record(load_at_start, round(sum(busy) / len(busy), 3) if busy else None),
        "settings": {
            "runs": args.runs,
            "duration_s": args.duration_s,
            "skip_lockstep": args.skip_lockstep,
            "skip_realtime": args.skip_realtime,
            "default_runs": DEFAULT_RUNS,
            "default_duration_s": DEFAULT_DURATION_S,
        },  # fmt: skip
        "goals": GOALS,
        "wall_s": round(time.monotonic() - started, 1),
        "lockstep": lockstep,
        "realtime": realtime,
        "summary": summarise(lockstep, realtime),
    }
    write_json(args.output, doc, log=progress)
    print(
        f"bench_graph {doc['machine']['date']}, {doc['machine']['cpus']} CPUs, commit {doc['machine']['git_commit']}, "
        f"tour {args.duration_s:g} s sim time: lockstep {'reused' if args.skip_lockstep else 'run'}, "
        f"{len(realtime)} real-time run(s); others used {fmt(doc['machine']['other_processes_cores_busy'], 2)} cores\n"
    )
    print(table(doc))
    measured = (lockstep is not None and "error" not in lockstep) or any("error" not in r for r in realtime)
    return 0 if measured else 1


if __name__ == "__main__":
    sys.exit(main())
