"""Resident memory and CPU time of a running node graph, sampled from /proc (Linux).

``scripts/run_graph.sh -m FILE`` starts this next to the nodes: each node is the leader of its own
session (``setsid``), so a node is every process whose session id is the node's pid (``ros2 run`` and the
Python interpreter it starts included). Every ``period_s`` the monitor sums the resident set size (RSS)
and the CPU time (user + system) per node and for the whole graph; it writes the JSON on SIGTERM/SIGINT
and every ``flush_period_s``, so a monitor killed hard still leaves its latest file.

Usage: python -m tal_core.resource_monitor --out resources.json [--period-s 1.0] NAME=PID ...
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

PAGE_KB = os.sysconf("SC_PAGE_SIZE") / 1024.0
CLOCK_TICKS_HZ = float(os.sysconf("SC_CLK_TCK"))


@dataclass
class ProcessSample:
    """One process: its session id, RSS [kB] and CPU time used so far [s]."""

    session: int
    rss_kb: float
    cpu_s: float


def read_process(pid: int) -> ProcessSample | None:
    """``/proc/<pid>/stat`` and ``statm`` of one process; None if it is gone (or not readable)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        statm = Path(f"/proc/{pid}/statm").read_text().split()
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        return None
    # The command name (field 2) may contain spaces and parentheses: split after its closing ')'.
    fields = stat[stat.rindex(")") + 2:].split()
    session = int(fields[3])                 # field 6 of stat
    cpu_ticks = int(fields[11]) + int(fields[12])   # utime + stime (fields 14, 15)
    return ProcessSample(session=session, rss_kb=int(statm[1]) * PAGE_KB, cpu_s=cpu_ticks / CLOCK_TICKS_HZ)


def sample_sessions(sessions: dict[int, str]) -> dict[str, tuple[float, float]]:
    """(RSS [MB], CPU [s]) summed over every live process of each session, keyed by node name."""
    totals = {name: (0.0, 0.0) for name in sessions.values()}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        sample = read_process(int(entry.name))
        if sample is None or sample.session not in sessions:
            continue
        name = sessions[sample.session]
        rss, cpu = totals[name]
        totals[name] = (rss + sample.rss_kb / 1024.0, cpu + sample.cpu_s)
    return totals


@dataclass
class NodeResources:
    """What the monitor keeps per node: peak RSS [MB] and the CPU time [s] last seen."""

    peak_rss_mb: float = 0.0
    last_rss_mb: float = 0.0
    cpu_s: float = 0.0


@dataclass
class GraphResources:
    """Per-node figures and the graph's total RSS series [(t [s] since start, MB)]."""

    period_s: float
    nodes: dict[str, NodeResources] = field(default_factory=dict)
    total_rss_mb: list[tuple[float, float]] = field(default_factory=list)
    wall_s: float = 0.0

    def add(self, t_s: float, totals: dict[str, tuple[float, float]]) -> None:
        live = 0.0
        for name, (rss, cpu) in totals.items():
            node = self.nodes.setdefault(name, NodeResources())
            if rss > 0.0:
                node.peak_rss_mb = max(node.peak_rss_mb, rss)
                node.last_rss_mb = rss
                node.cpu_s = max(node.cpu_s, cpu)  # a node's CPU time only grows; keep it after it exits
            live += rss
        self.total_rss_mb.append((round(t_s, 3), round(live, 2)))
        self.wall_s = t_s

    def to_dict(self) -> dict:
        series = [mb for _, mb in self.total_rss_mb]
        return {
            "period_s": self.period_s,
            "wall_s": round(self.wall_s, 3),
            "peak_total_rss_mb": round(max(series), 2) if series else None,
            "nodes": {name: {"peak_rss_mb": round(n.peak_rss_mb, 2), "last_rss_mb": round(n.last_rss_mb, 2),
                             "cpu_s": round(n.cpu_s, 3),
                             "cpu_fraction": round(n.cpu_s / self.wall_s, 4) if self.wall_s > 0 else None}
                      for name, n in self.nodes.items()},
            "total_rss_mb": self.total_rss_mb,
        }


def parse_targets(specs: list[str]) -> dict[int, str]:
    """``NAME=PID`` strings as {session id (= pid of the setsid leader): name}."""
    sessions: dict[int, str] = {}
    for spec in specs:
        name, sep, pid = spec.partition("=")
        if not sep or not name or not pid.isdigit():
            raise ValueError(f"target '{spec}' is not NAME=PID")
        sessions[int(pid)] = name
    return sessions


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="JSON written on exit and every flush period")
    parser.add_argument("--period-s", type=float, default=1.0, help="[s] sampling period")
    parser.add_argument("--flush-period-s", type=float, default=10.0, help="[s] how often the JSON is rewritten")
    parser.add_argument("targets", nargs="+", help="NAME=PID of each session leader")
    args = parser.parse_args(argv)
    if args.period_s <= 0.0:
        parser.error("--period-s must be > 0")
    try:
        sessions = parse_targets(args.targets)
    except ValueError as exc:
        parser.error(str(exc))
    stop = False

    def on_signal(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    result = GraphResources(period_s=args.period_s)
    start = last_flush = time.monotonic()

    def write() -> None:
        tmp = args.out.with_suffix(".tmp")
        tmp.write_text(json.dumps(result.to_dict(), indent=1))
        tmp.replace(args.out)

    while not stop:
        now = time.monotonic()
        result.add(now - start, sample_sessions(sessions))
        if now - last_flush >= args.flush_period_s:
            write()
            last_flush = now
        time.sleep(args.period_s)
    write()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
