"""Machine description recorded next to every benchmark figure (shared by the bench scripts)."""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

from common import ROOT  # bench/common.py (the script folder is on sys.path)


def machine_info() -> dict[str, object]:
    cpu = "unknown"
    try:
        cpu = next(
            line.split(":", 1)[1].strip()
            for line in Path("/proc/cpuinfo").read_text().splitlines()
            if line.startswith("model name")
        )
    except (OSError, StopIteration):
        pass
    commit = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
    ).stdout.strip()
    return {
        "date": dt.datetime.now().astimezone().isoformat(timespec="seconds"),
        "cpus": os.cpu_count(),
        "cpu_model": cpu,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "git_commit": commit,
        "rmw": os.environ.get("RMW_IMPLEMENTATION", "default (rmw_fastrtps_cpp)"),
        "load_average_1_5_15min": [round(x, 2) for x in os.getloadavg()],
    }


def machine_record(load_at_start: list[float], other_busy: float | None) -> dict[str, object]:
    """``machine_info()`` plus the 1/5/15 min load averages when the measurement started and how many cores other
    processes kept busy on average meanwhile (the ``machine`` section of bench_wbc's and bench_estimator's JSON)."""
    return {
        **machine_info(),
        "load_average_at_start_1_5_15min": load_at_start,
        "other_processes_cores_busy": other_busy,
    }


def cpu_snapshot() -> tuple[float, float, float] | None:
    """(wall [s], busy CPU time of the whole machine [s], CPU time of this process and its children [s])."""
    try:
        fields = [int(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    except (OSError, ValueError, IndexError):
        return None
    ticks = os.sysconf("SC_CLK_TCK")
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    t = os.times()
    return time.monotonic(), (sum(fields[:8]) - idle) / ticks, t.user + t.system + t.children_user + t.children_system


def other_cores_busy(start, end) -> float | None:
    """Average number of cores other processes kept busy between two snapshots (0 = a quiet machine)."""
    if start is None or end is None or end[0] <= start[0]:
        return None
    return max(0.0, ((end[1] - start[1]) - (end[2] - start[2])) / (end[0] - start[0]))


def wait_for_quiet_machine(timeout_s: float, threshold_cores: float = 0.15, window_s: float = 5.0,
                           log: Callable[[str], None] | None = None) -> float | None:
    """Wait (up to timeout_s) for a window in which other processes keep < threshold cores busy; returns
    the last measured load of the others (cores)."""
    deadline = time.monotonic() + timeout_s
    while True:
        start = cpu_snapshot()
        time.sleep(window_s)
        busy = other_cores_busy(start, cpu_snapshot())
        if busy is None or busy < threshold_cores or time.monotonic() > deadline:
            return busy
        if log is not None:
            log(f"other processes keep {busy:.2f} cores busy; waiting for a quiet machine")


def add_wait_quiet_option(parser: argparse.ArgumentParser) -> None:
    """The benches' ``--wait-quiet S`` option (see ``settle_machine``)."""
    parser.add_argument(
        "--wait-quiet", type=float, default=0.0, metavar="S",
        help="first wait up to S seconds for 5 s in which other processes use < 0.15 cores (shared machines)",
    )  # fmt: skip


def settle_machine(wait_quiet_s: float, log: Callable[[str], None]) -> list[float]:
    """Wait for a quiet machine when ``wait_quiet_s`` > 0 (logging the others' load), then return the
    1/5/15 min load averages at the start of the measurement."""
    if wait_quiet_s > 0:
        busy = wait_for_quiet_machine(wait_quiet_s, log=log)
        log(f"other processes keep {'unknown' if busy is None else f'{busy:.2f}'} cores busy; starting")
    return [round(v, 2) for v in os.getloadavg()]
