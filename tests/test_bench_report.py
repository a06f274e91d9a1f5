"""bench/report.py: rows, ratios and goals from small bench JSON fixtures; missing benches give "not run" rows."""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture(scope="module")
def report():
    sys.path.insert(0, str(BENCH))  # report.py imports bench/machine.py as the benches do
    try:
        yield importlib.import_module("report")
    finally:
        sys.path.remove(str(BENCH))


def _stats(median: float, p99: float | None = None, n: int = 100, **extra) -> dict:
    return {
        "n": n,
        "median": median,
        "p99": p99 if p99 is not None else 2 * median,
        "max": 3 * median,
        "mean": median,
        **extra,
    }


WBC = {
    "benchmark": "bench_wbc",
    "machine": {"date": "2026-11-23T10:00:00+00:00", "git_commit": "abc1234", "other_processes_cores_busy": 0.5},
    "states_per_sequence": 100,
    "rounds": 2,
    "goals_ms": {"median": 0.4, "p99": 1.5},
    "summary": {
        "ours": {
            "4": {"cycle": _stats(0.6, 1.2), "qp_solve": _stats(0.09), "not_solved": 0},
            "2": {"cycle": _stats(0.8, 1.8), "qp_solve": _stats(0.2), "not_solved": 1},
        },
        "tsid": {"4": {"cycle": _stats(0.12)}, "2": {"cycle": _stats(0.05)}},
    },
    "tsid_error": None,
}

VPA = {
    "benchmark": "bench_vpa",
    "machine": {"date": "2026-11-23T11:00:00+00:00", "git_commit": "abc1234"},
    "rounds": 2,
    "inputs": {"scenes": 10},
    "thesis_mean_ms": {"exact": 720.0, "cnn": 180.0},
    "goal_ms": {"exact": 50.0, "cnn": 20.0},
    "results": {"exact": {"stats": _stats(200.0)}, "cnn": {"stats": _stats(16.0)}},
}

GRAPH_RATES = {
    "nodes": {
        "wbc": {"target_hz": 250, "achieved_hz": 200.0, "deadline_misses": 12, "ticks": 5000},
        "state_estimator": {"target_hz": 333, "achieved_hz": 333.0, "deadline_misses": 0, "ticks": 6660},
    },
    "peak_rss_mb": 812.5,
}


def _write(directory: Path, name: str, document: dict) -> None:
    (directory / f"{name}.json").write_text(json.dumps(document))


def _by_what(rows, fragment: str):
    found = [r for r in rows if fragment in r.what]
    assert len(found) == 1, [r.what for r in rows]
    return found[0]


def test_rows_ratios_and_goals_from_fixtures(report, tmp_path) -> None:
    _write(tmp_path, "bench_wbc", WBC)
    _write(tmp_path, "bench_vpa", VPA)
    rows, docs = report.collect(tmp_path)
    assert set(docs) == {"bench_wbc", "bench_vpa"}

    median4 = _by_what(rows, "torques), 4 stance legs, median")
    assert median4.value == pytest.approx(0.6) and median4.unit == "ms"
    assert (median4.goal.op, median4.goal.value) == ("<=", 0.4)
    assert median4.ratio == pytest.approx(1.5) and median4.met is False
    assert "TSID" in median4.reference and "5.00" in median4.reference  # 0.6 / 0.12, the peer ratio
    p99 = _by_what(rows, "cycle, 4 stance legs, p99")
    assert p99.ratio == pytest.approx(0.8) and p99.met is True
    worst = _by_what(rows, "worst of both sequences")
    assert worst.value == pytest.approx(2.4) and worst.goal.value == 4.0 and worst.met is True

    exact = _by_what(rows, "exact VPA update, median")
    assert exact.ratio == pytest.approx(4.0) and exact.met is False and "720" in exact.reference
    cnn_rate = _by_what(rows, "cnn VPA update rate")
    assert cnn_rate.value == pytest.approx(62.5) and cnn_rate.goal.op == ">=" and cnn_rate.met is True
    assert cnn_rate.ratio == pytest.approx(12.5)


def test_a_missing_bench_json_gives_a_not_run_row(report, tmp_path) -> None:
    _write(tmp_path, "bench_vpa", VPA)
    rows, _ = report.collect(tmp_path)
    not_run = [r for r in rows if r.note.startswith("not run")]
    assert {r.what for r in not_run} == {
        f"`bench/{name}.py`"
        for name in (
            "bench_bridge",
            "bench_wbc",
            "bench_stance",
            "bench_estimator",
            "bench_bags",
            "bench_vfa",
            "bench_vfa_cnn",
            "bench_graph",
        )
    }
    assert all(r.value is None and r.ratio is None and r.met is None for r in not_run)
    text = report.render(rows, {}, {"date": "today"})
    assert "| sWBC (250 Hz) | `bench/bench_wbc.py` | **not run** |" in text


def test_a_json_without_the_expected_fields_gives_an_unreadable_row(report, tmp_path) -> None:
    _write(tmp_path, "bench_estimator", {"summary": {"rigid": {}}})
    (tmp_path / "bench_stance.json").write_text("{not json")
    rows, docs = report.collect(tmp_path)
    assert "bench_estimator" not in docs
    assert any(r.group.startswith("state estimator") and r.note.startswith("unreadable") for r in rows)
    assert any(r.group.startswith("STANCE") and r.note.startswith("unreadable bench_stance.json") for r in rows)


def test_optional_graph_rates_are_left_out_when_absent_and_listed_when_present(report, tmp_path) -> None:
    rows, _ = report.collect(tmp_path)
    assert not any(r.group.startswith("graph rates") for r in rows)
    _write(tmp_path, "graph_rates", GRAPH_RATES)
    rows, _ = report.collect(tmp_path)
    wbc = _by_what(rows, "wbc: achieved rate")
    assert wbc.ratio == pytest.approx(0.8) and wbc.met is False and "deadline misses 12" in wbc.note
    assert _by_what(rows, "state_estimator: achieved rate").met is True
    assert _by_what(rows, "peak resident memory").value == pytest.approx(812.5)


def test_across_hosts_rows_and_section(report, tmp_path) -> None:
    _write(
        tmp_path,
        "across_hosts",
        {
            "rows": [
                {
                    "what": "lockstep wall time per tick, added",
                    "value": 0.3,
                    "unit": "ms",
                    "goal_op": "<=",
                    "goal": 4.0,
                    "goal_source": "4 ms tick",
                }
            ],
            "markdown": "## Across hosts\n\nmeasured here",
        },
    )
    rows, docs = report.collect(tmp_path)
    row = _by_what(rows, "per tick, added")
    assert row.ratio == pytest.approx(0.075) and row.met is True
    assert "## Across hosts" in report.render(rows, docs, {})


def test_main_writes_the_markdown(report, tmp_path) -> None:
    _write(tmp_path, "bench_wbc", WBC)
    output = tmp_path / "results" / "bench.md"
    assert report.main(["--out-dir", str(tmp_path), "--output", str(output), "--note", "Quiet machine."]) == 0
    text = output.read_text()
    assert "| group | what | measured | goal | measured / goal | met | thesis / peer | notes |" in text
    assert "0.600 ms" in text and "1.50 |" in text  # measured and measured / goal
    assert "100 states x 2 sequences x 2 rounds (reduced)" in text
    assert "CPUs" in text  # machine info
    assert "\nQuiet machine.\n" in text


def test_the_vfa_cnn_rows_name_the_runtime_and_the_other_backend_of_the_session(report, tmp_path) -> None:
    def results(one_leg: float, batch: float) -> dict:
        leg = {"stats": {"median": one_leg, "p99": 2 * one_leg, "n": 10}, "fallbacks": 1}
        return {
            "cnn": {name: dict(leg) for name in ("LF", "RF", "LH", "RH")},
            "cnn_4legs": {"4legs": {"per_leg_stats": {"median": batch, "p99": 0.6}}},
            "cnn_verified": {name: dict(leg) for name in ("LF", "RF", "LH", "RH")},
        }

    headline = {"4legs_per_leg": {"median": 0.47, "p99": 0.66}, "one_leg": {"median": 0.9, "p99": 1.1}}
    doc = {
        "goal_ms": 0.5,
        "backend": "onnxruntime",
        "results": results(0.62, 0.46),
        "backends": {
            "onnxruntime": {"label": "onnxruntime X", "results": results(0.62, 0.46)},
            "torch": {"label": "torch Y", "headline_ms": headline, "results": results(0.9, 0.47)},
        },
    }
    _write(tmp_path, "bench_vfa_cnn", doc)
    rows, _ = report.collect(tmp_path)
    batch = _by_what(rows, "4 legs in one batch")
    assert batch.value == pytest.approx(0.46) and batch.met is True
    assert "same session, torch Y: 0.470 ms per leg batched, 0.900 ms one leg" in batch.note
    assert "onnxruntime X" in _by_what(rows, "one leg per call").note


def _graph_run(name: str, fell: bool, distance: float, wbc_hz: float, wbc_misses: int, latency: dict | None) -> dict:
    return {
        "run_dir": f"/x/runs/{name}",
        "reused": False,
        "sim_time_s": 40.0,
        "real_time_factor": 0.999,
        "real_time_factor_log_lower_bound": 0.95,
        "realtime_overruns": 3,
        "fell": fell,
        "distance_m": distance,
        "command_latency_ms": latency,
        "cpu": {"graph_cpu_s_per_sim_s": 2.0, "busiest_node": "wbc", "busiest_cpu_s_per_sim_s": 0.6},
        "rates": {"wbc": {"achieved_hz": wbc_hz, "deadline_misses": wbc_misses, "ticks": 10000 - wbc_misses}},
    }


BENCH_GRAPH = {
    "benchmark": "bench_graph",
    "machine": {"date": "2026-11-28T02:00:00+00:00", "git_commit": "abc1234", "other_processes_cores_busy": 0.1},
    "settings": {"runs": 2, "duration_s": 40.0, "default_runs": 3, "default_duration_s": 40.0},
    "goals": {
        "graph_cpu_s_per_sim_s": 1.5,
        "node_cpu_s_per_sim_s": 0.4,
        "missed_deadline_share_pct": 1.0,
        "distance_deviation_pct": 5.0,
        "rate_hz": {"wbc": 250.0, "vpa": 5.0},
    },
    "lockstep": {
        "run_dir": "/x/runs/20261128-020000-tour",
        "sim_time_s": 40.0,
        "real_time_factor": 0.45,
        "fell": False,
        "distance_m": 10.0,
        "links_touching_terrain": [],
        "other_cores_busy": 0.05,
        "cpu": {
            "graph_cpu_s": 120.0,
            "graph_cpu_s_per_sim_s": 3.0,
            "busiest_node": "wbc",
            "busiest_cpu_s_per_sim_s": 1.0,
            "nodes": {"wbc": {"cpu_s_per_sim_s": 1.0}, "tce": {"cpu_s_per_sim_s": 0.3}},
        },
    },
    "realtime": [
        _graph_run("a-tour_realtime", False, 10.3, 249.0, 50, {"median": 1.2, "p99": 3.5}),
        _graph_run("b-tour_realtime", True, 7.0, 200.0, 2000, {"median": 1.5, "p99": 6.0}),
    ],
    "summary": {
        "lockstep_distance_m": 10.0,
        "runs": 2,
        "nodes": {
            "wbc": {
                "target_hz": 250.0,
                "goal_hz": 250.0,
                "achieved_hz": [249.0, 200.0],
                "worst_achieved_hz": 200.0,
                "missed_share_pct": [0.5, 20.0],
                "worst_missed_share_pct": 20.0,
                "runs_meeting_goals": 0,
            },
            "vpa": {
                "target_hz": 20.0,
                "goal_hz": 5.0,
                "achieved_hz": [19.0, 10.0],
                "worst_achieved_hz": 10.0,
                "missed_share_pct": [0.0, 40.0],
                "worst_missed_share_pct": 40.0,
                "runs_meeting_goals": 1,
            },
        },
        "falls": 1,
        "finished_runs": 2,
        "distance_deviation_pct": [3.0, 30.0],
        "worst_distance_deviation_pct": 30.0,
        "command_latency_ms": {"median": [1.2, 1.5], "p99": [3.5, 6.0]},
        "real_time_factor_log_lower_bound": [0.95, 0.95],
        "realtime_overruns": [3, 3],
    },
}


def test_bench_graph_rows_cpu_per_sim_second_rates_deadlines_walk_and_latency(report, tmp_path) -> None:
    _write(tmp_path, "bench_graph", BENCH_GRAPH)
    rows, docs = report.collect(tmp_path)
    assert "bench_graph" in docs
    graph = _by_what(rows, "lockstep tour: graph CPU per sim-s")
    assert graph.value == pytest.approx(3.0) and graph.goal.value == 1.5 and graph.ratio == pytest.approx(2.0)
    assert graph.met is False and "120.0 CPU-s" in graph.note
    busiest = _by_what(rows, "busiest node CPU per sim-s (wbc)")
    assert busiest.ratio == pytest.approx(2.5) and "tce 0.30" in busiest.note
    wbc_rate = _by_what(rows, "wbc: rate on the wall clock, worst of 2")
    assert wbc_rate.ratio == pytest.approx(0.8) and wbc_rate.goal.op == ">=" and "249.0, 200.0 Hz" in wbc_rate.note
    vpa_rate = _by_what(rows, "vpa: rate on the wall clock")
    assert vpa_rate.goal.value == 5.0 and vpa_rate.met is True and "design goal 20 Hz" in vpa_rate.note
    missed = _by_what(rows, "wbc: missed deadlines")
    assert missed.value == pytest.approx(20.0) and missed.unit == "%" and missed.met is False
    falls = _by_what(rows, "runs without a fall (1 of 2)")
    assert falls.value == pytest.approx(50.0) and falls.goal.value == 100.0 and falls.met is False
    distance = _by_what(rows, "distance vs lockstep")
    assert distance.value == pytest.approx(30.0) and distance.goal.value == 5.0 and "10.30 m, 7.00 m" in distance.note
    assert _by_what(rows, "latency, median").value == pytest.approx(1.5)
    assert _by_what(rows, "latency, p99").value == pytest.approx(6.0)
    assert "2 real-time run(s) (reduced)" in report.render(rows, docs, {})


def test_bench_graph_without_latency_or_realtime_runs(report, tmp_path) -> None:
    doc = json.loads(json.dumps(BENCH_GRAPH))
    doc["summary"]["command_latency_ms"] = None
    _write(tmp_path, "bench_graph", doc)
    rows, _ = report.collect(tmp_path)
    assert _by_what(rows, "latency, median").value is None
    assert "not in bridge_summary.json" in _by_what(rows, "latency, p99").note
    doc["realtime"] = []
    _write(tmp_path, "bench_graph", doc)
    rows, _ = report.collect(tmp_path)
    assert _by_what(rows, "tour_realtime").note.startswith("not run")
    assert _by_what(rows, "lockstep tour: graph CPU per sim-s").value == pytest.approx(3.0)


def test_peer_ratios_and_the_estimator_tick_goal(report, tmp_path) -> None:
    _write(tmp_path, "bench_wbc", WBC)
    legs = lambda m4, m2: {"4": _stats(m4, fallbacks=0), "2": _stats(m2, fallbacks=0)}  # noqa: E731
    stance = {
        "tce": {"update_ms": _stats(0.05)},
        "contact_states": {"contact_states_ms": _stats(0.2)},
        "wbc": {"rigid": legs(0.3, 0.4), "compliant": legs(0.36, 0.5)},
    }
    _write(tmp_path, "bench_stance", stance)
    u = _stats(0.15)
    _write(tmp_path, "bench_estimator", {"summary": {"rigid": {"update": u}}, "budget_ms": 3.0})
    rows, _ = report.collect(tmp_path)
    swbc = _by_what(rows, "sWBC / TSID cycle median, 4 stance legs")
    assert swbc.value == pytest.approx(5.0) and swbc.goal.value == 1.0 and swbc.met is False
    c3 = _by_what(rows, "c3WBC / TSID cycle median, 2 stance legs")
    assert c3.value == pytest.approx(10.0)
    tick = _by_what(rows, "tick (StateEstimator.update), rigid leg odometry, median")
    assert tick.goal.value == 0.1 and tick.ratio == pytest.approx(1.5)
