"""Command latency without ROS (tal_sim_bridge.latency): stamps matched once, a bounded table, percentiles."""

from __future__ import annotations

import pytest

from tal_sim_bridge.latency import CommandLatency

MS = 1_000_000


def test_a_command_is_timed_from_the_joint_state_of_its_stamp() -> None:
    latency = CommandLatency()
    for k in range(1, 101):                     # 1 kHz joint states, a command every 4 ms answering 2-3 ms later
        latency.published(k * MS, k * 1e-3)
        if k % 4 == 0:
            assert latency.command(k * MS, k * 1e-3 + (0.002 if k < 100 else 0.030)) == pytest.approx(
                0.002 if k < 100 else 0.030)
    summary = latency.summary()
    assert summary["count"] == 25 and summary["untimed"] == 0
    assert summary["median_ms"] == pytest.approx(2.0)
    assert summary["max_ms"] == pytest.approx(30.0)
    assert 2.0 < summary["p99_ms"] <= 30.0


def test_untimed_commands_stamp_zero_a_second_answer_and_a_forgotten_stamp() -> None:
    latency = CommandLatency(pending=4)
    latency.published(0, 0.0)                   # the initial state: re-sent until a controller joins
    assert latency.command(0, 5.0) is None
    latency.published(4 * MS, 1.0)
    assert latency.command(4 * MS, 1.001) == pytest.approx(0.001)
    assert latency.command(4 * MS, 1.002) is None   # the same stamp answered twice: timed once
    for k in range(5, 11):
        latency.published(k * MS, 1.0 + k * 1e-3)
    assert latency.command(5 * MS, 2.0) is None     # dropped from the 4-entry table
    assert latency.command(10 * MS, 1.012) == pytest.approx(0.002)
    assert latency.summary()["count"] == 2 and latency.summary()["untimed"] == 3


def test_percentiles_run_over_the_last_window_count_and_max_over_all() -> None:
    latency = CommandLatency(window=10)
    for k in range(1, 31):
        latency.published(k * MS, 0.0)
        latency.command(k * MS, 0.1 if k <= 20 else 0.001)
    summary = latency.summary()
    assert summary["count"] == 30 and summary["max_ms"] == pytest.approx(100.0)
    assert summary["median_ms"] == pytest.approx(1.0) and summary["p99_ms"] == pytest.approx(1.0)


def test_an_empty_summary_and_bad_sizes() -> None:
    assert CommandLatency().summary() == {"count": 0, "untimed": 0, "median_ms": None, "p99_ms": None,
                                          "max_ms": None}
    with pytest.raises(ValueError, match="pending >= 1"):
        CommandLatency(pending=0)
