"""resource_monitor: a node's RSS is the sum over its session (children included); the JSON survives SIGTERM."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tal_core.resource_monitor import GraphResources, parse_targets, sample_sessions

# A session leader (bash) whose child touches 120 MB and then waits: the node's memory lives in a child,
# as with `ros2 run` starting the node's interpreter.
HOG = ("import time; x = bytearray(120 * 1024 * 1024)\n"
       "for i in range(0, len(x), 4096): x[i] = 1\n"
       "print('ready', flush=True); time.sleep(60)")


@pytest.fixture
def hog():
    proc = subprocess.Popen(["bash", "-c", f'{sys.executable} -c "$0"; exit', HOG], stdout=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        yield proc
    finally:
        proc.kill()
        subprocess.run(["pkill", "-KILL", "-s", str(proc.pid)], check=False)
        proc.wait()


def test_the_rss_of_a_session_includes_its_children(hog) -> None:
    totals = sample_sessions({hog.pid: "hog"})
    rss_mb, cpu_s = totals["hog"]
    assert 120.0 < rss_mb < 200.0
    assert cpu_s >= 0.0
    assert sample_sessions({2**22 + 7: "gone"}) == {"gone": (0.0, 0.0)}


def test_peaks_and_cpu_are_kept_after_a_node_exits() -> None:
    graph = GraphResources(period_s=1.0)
    graph.add(1.0, {"a": (100.0, 2.0), "b": (50.0, 1.0)})
    graph.add(2.0, {"a": (0.0, 0.0), "b": (60.0, 1.5)})   # a exited
    result = graph.to_dict()
    assert result["nodes"]["a"] == {"peak_rss_mb": 100.0, "last_rss_mb": 100.0, "cpu_s": 2.0, "cpu_fraction": 1.0}
    assert result["peak_total_rss_mb"] == 150.0
    assert result["total_rss_mb"] == [(1.0, 150.0), (2.0, 60.0)]


def test_targets_must_be_name_equals_pid() -> None:
    assert parse_targets(["wbc=12", "vpa=13"]) == {12: "wbc", 13: "vpa"}
    with pytest.raises(ValueError, match="'wbc:12' is not NAME=PID"):
        parse_targets(["wbc:12"])


def test_the_monitor_writes_its_json_when_stopped(hog, tmp_path: Path) -> None:
    out = tmp_path / "resources.json"
    monitor = subprocess.Popen([sys.executable, "-m", "tal_core.resource_monitor", "--out", str(out),
                                "--period-s", "0.2", f"hog={hog.pid}"])
    time.sleep(1.5)
    monitor.send_signal(signal.SIGTERM)
    assert monitor.wait(timeout=10) == 0
    result = json.loads(out.read_text())
    assert result["nodes"]["hog"]["peak_rss_mb"] > 120.0
    assert len(result["total_rss_mb"]) >= 3
