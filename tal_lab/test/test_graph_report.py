"""graph_report: rates and missed ticks from stamps, stiffness attributed to the patch under the foot, a run
that fell reported invalid and cut at the fall."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from tal_lab.graph_report import (
    BagSeries,
    bench_rates,
    build_report,
    estimator_sections,
    fallbacks_by_section,
    read_bag,
    stiffness_table,
    topic_rates,
)

from tal_core.ros.bag_io import BagWriter
from tal_core.ros.node_utils import stamp_from_ns
from tal_msgs.msg import ContactState, TerrainImpedance

MS = 1_000_000


def test_rates_count_the_missed_ticks_of_each_gap() -> None:
    ticks = [k * 4 * MS for k in range(1001)]          # 250 Hz for 4 s
    del ticks[500:503]                                  # one gap of 4 periods: 3 ticks missed
    del ticks[100]                                      # one gap of 2 periods: 1 missed
    rates = {r.topic: r for r in topic_rates({"gait_state": [0, 0, 0] + ticks}, real_time_factor=0.5)}  # re-sends
    gait = rates["gait_state"]
    assert gait.missed_ticks == 4
    assert gait.messages == 997
    assert gait.sim_rate_hz == pytest.approx(996 / 4.0)
    assert gait.wall_rate_hz == pytest.approx(0.5 * 996 / 4.0)
    assert rates["joint_states"].messages == 0 and rates["joint_states"].sim_rate_hz is None
    assert rates["footholds"].target_hz is None


def test_bench_rates_take_the_bridge_rate_from_its_contacts_when_joint_states_was_not_recorded() -> None:
    """A real-time tour records no 1 kHz topic: the bridge's physics rate is its contacts' times four."""
    stamps = {"ground_truth/contacts": [k * 4 * MS for k in range(251)], "joint_command": [k * 4 * MS for k in
                                                                                          range(0, 251, 2)]}
    rates = [r.__dict__ for r in topic_rates(stamps, real_time_factor=0.8)]
    nodes = bench_rates({"rates": rates, "mode": "realtime", "real_time_factor": 0.8,
                         "peak_total_rss_mb": 1.0})["nodes"]
    assert nodes["sim_bridge"]["topic"] == "ground_truth/contacts x 4"
    assert nodes["sim_bridge"]["target_hz"] == 1000.0 and nodes["sim_bridge"]["achieved_hz"] == pytest.approx(800.0)
    assert nodes["wbc"]["deadline_misses"] == 125 and nodes["wbc"]["achieved_hz"] == pytest.approx(100.0)
    with_joints = bench_rates({"rates": [r.__dict__ for r in topic_rates({**stamps, "joint_states": [0, MS]}, 1.0)],
                               "mode": "realtime", "real_time_factor": 1.0, "peak_total_rss_mb": 1.0})
    assert with_joints["nodes"]["sim_bridge"]["topic"] == "joint_states"


def _write_walk(path: Path, base: bool = False) -> None:
    """Every foot walks along x at 0.1 m/s from x = 1.0 (stance_course: rigid up to 2, T1 3500 N/m on
    [2, 4]); the estimate reported is the true stiffness under the foot, except LF's which is doubled. With
    ``base``: ground_truth/odom (the base 0.55 m above the ground, sinking at 10 m/s from FALL_S on) and a
    state_estimate 0.05 m ahead in x."""
    with BagWriter(path) as bag:
        for k in range(0, 25_000, 20):                  # 25 s at 50 Hz
            t_ns = k * MS
            x = 1.0 + 0.1e-3 * k
            if base:
                truth, estimate = Odometry(), Odometry()
                truth.header.stamp = estimate.header.stamp = stamp_from_ns(t_ns)
                z = 0.55 - 10.0 * max(0.0, k * 1e-3 - FALL_S)
                truth.pose.pose.position.x, truth.pose.pose.position.z = x, z
                estimate.pose.pose.position.x, estimate.pose.pose.position.z = x + 0.05, z
                bag.write("/ground_truth/odom", truth, t_ns)
                bag.write("/state_estimate", estimate, t_ns)
            contacts, impedance = ContactState(), TerrainImpedance()
            contacts.header.stamp = impedance.header.stamp = stamp_from_ns(t_ns)
            for i in range(4):
                contacts.in_contact[i] = True
                contacts.foot_position[i].x = x
                true_k = 3500.0 if 2.0 <= x < 4.0 else 2.0e6
                impedance.stiffness_normal[i] = true_k * (2.0 if i == 0 else 1.0)
                impedance.valid[i] = True
                impedance.confidence[i] = 0.05 if i == 1 else 0.9   # RF below the wbc's threshold
            bag.write("/ground_truth/contacts", contacts, t_ns)
            bag.write("/terrain_impedance", impedance, t_ns)


def test_an_estimate_counts_for_a_patch_only_once_the_lookback_lies_on_it(tmp_path: Path) -> None:
    _write_walk(tmp_path / "bag")
    series = read_bag(tmp_path / "bag", "stance_course", lookback_s=2.5)
    assert set(series.stiffness) == {"default", "soft_t1"}
    t1 = np.array([s[0] for s in series.stiffness["soft_t1"]])
    # The foot enters T1 at t = 10 s: its estimates count from 12.5 s (lookback) on; it is still on T1 at the end.
    assert t1.min() == pytest.approx(12.5, abs=0.01)
    assert t1.max() == pytest.approx(24.98, abs=0.01)  # the last sample of the 25 s
    rows = {r["patch"]: r for r in stiffness_table(series, "stance_course")}
    assert rows["soft_t1"]["true_n_per_m"] == 3500.0
    assert rows["soft_t1"]["median_n_per_m"] == 3500.0     # 3 of 4 legs exact, LF doubled
    assert rows["soft_t1"]["p90_n_per_m"] == 7000.0
    assert rows["soft_t1"]["confident_share"] == pytest.approx(0.75, abs=0.01)   # RF's are not adopted
    assert rows["soft_t1"]["confident_median_n_per_m"] == 3500.0                 # LH, RH exact, LF doubled
    assert rows["default"]["true_n_per_m"] == 2.0e6
    # the soft-reading census: every confident T1 estimate is below 5e4 N/m, no confident rigid one is
    assert rows["soft_t1"]["confident_below_5e4"] == rows["soft_t1"]["confident_samples"] > 0
    assert rows["default"]["confident_below_5e4"] == 0 < rows["default"]["confident_samples"]
    assert rows["soft_t1"]["samples"] == len(t1) == pytest.approx(4 * (25.0 - 12.5) / 0.020, abs=8)


# --- a run in which the robot fell ----------------------------------------------------------------------
FALL_S = 12.0  # [s] onset of the synthetic fall


def bridge_summary(fell: bool) -> dict:
    """A bridge summary as the node writes it (trimmed to what the reports read)."""
    summary = {"sim_time_s": FALL_S + 0.2 if fell else 25.0, "wall_time_s": 50.0, "real_time_factor": 0.5,
               "course": "stance_course", "robot": "hyq", "mode": "lockstep", "commands_accepted": 3000,
               "commands_rejected": {}, "lockstep_timeouts": 0, "body_ground_contact": ["trunk"] if fell else [],
               "fell": False, "fall_time_s": None, "fall_confirmed_s": None, "fall_position_m": None,
               "fall_links": [], "fall_reason": None, "stop_on_fall": True, "stopped_on_fall": fell,
               "command_latency_ms": {"count": 3000, "untimed": 1, "median_ms": 4.25, "p99_ms": 11.5,
                                      "max_ms": 40.0}}
    if fell:
        summary.update(fell=True, fall_time_s=FALL_S, fall_confirmed_s=FALL_S + 0.2,
                       fall_position_m=[2.2, 0.01, 0.3], fall_links=["lf_upperleg", "trunk"],
                       fall_reason="body-ground contact")
    return summary


WBC = {"gait": "crawl", "distance_m": 9.5, "height_error_mean_abs_m": 5.1, "velocity_error_mean_abs_m_s": 0.24,
       "yaw_rate_error_mean_abs_rad_s": 0.2, "ticks": 3000, "qp_fallbacks": 3, "safe_mode_ticks": 0,
       "rejected_inputs": 0}
ESTIMATOR = {"leg_odometry": "terrain_aware", "final_drift_m": [0.0, 0.0, 113.0], "rms_drift_m": [0.0, 0.0, 50.0],
             "velocity_rmse_m_s": [0.1, 0.1, 3.0], "compared_s": 25.0, "ticks": 8000, "rejected": {}, "restarts": 0,
             "reinitialisations": 0}


def _write_run(run_dir: Path, fell: bool) -> None:
    """The walk of ``_write_walk`` plus the nodes' summaries; the ground-truth base walks at 0.1 m/s from
    x = 1 and, from FALL_S on, sinks through the ground (as the old bridge let it, to -117 m)."""
    _write_walk(run_dir / "bag", base=True)
    (run_dir / "bridge_summary.json").write_text(json.dumps(bridge_summary(fell)))
    (run_dir / "wbc_summary.json").write_text(json.dumps(WBC))
    (run_dir / "estimator_summary.json").write_text(json.dumps(ESTIMATOR))


def test_a_run_that_fell_is_reported_invalid_and_cut_at_the_fall(tmp_path: Path) -> None:
    _write_run(tmp_path, fell=True)
    report = build_report(tmp_path, "tour")
    lines = report.splitlines()
    assert lines[0] == "# tour"
    assert lines[2] == "**INVALID RUN: HyQ fell at t = 12.00 s, x = 2.20 m (links lf_upperleg, trunk).**"
    assert "left out" in lines[4] and "height, velocity and yaw-rate errors" in lines[4]
    # The figures the fall voids are gone; the distance and the base position are those at the fall.
    for gone in ("body height error", "velocity error (mean", "final drift [m]", "RMS drift [m]", "113", "9.500 m"):
        assert gone not in report, gone
    assert "| distance travelled to the fall (ground truth) | 1.200 m |" in report     # 0.1 m/s for 12 s
    assert "| base position at the fall (ground truth) | x 2.20 m, z 0.55 m |" in report
    assert "| drift at the fall's onset [m] | +0.0500 | +0.0000 | +0.0000 |" in report
    assert "| joint state -> command latency, wall time (median / p99 / max) | 4.25 / 11.50 / 40.00 ms " \
           "(3000 commands) |" in report
    summary = json.loads((tmp_path / "graph_summary.json").read_text())
    assert summary["fell"] is True and summary["fall_time_s"] == FALL_S
    assert summary["fall_links"] == ["lf_upperleg", "trunk"]
    assert summary["distance_m"] == pytest.approx(1.2, abs=1e-3)
    assert summary["command_latency_ms"]["p99_ms"] == 11.5
    # Stiffness estimates after the fall's onset no longer count: T1 ([2, 4] m) entered at 10 s, counted from
    # 12.5 s (lookback) on, i.e. none before the fall.
    assert {row["patch"] for row in summary["stiffness"]} == {"default"}


def test_a_run_that_did_not_fall_keeps_every_figure(tmp_path: Path) -> None:
    _write_run(tmp_path, fell=False)
    report = build_report(tmp_path, "tour")
    assert "INVALID" not in report and "left out" not in report
    assert "| fell | no |" in report
    assert "| distance travelled | 9.500 m |" in report
    assert "| body height error (mean abs, after 2 s) | 5100.0 mm |" in report
    assert "| final drift [m] | +0.0000 | +0.0000 | +113.0000 |" in report
    assert "4.25 / 11.50 / 40.00 ms" in report
    summary = json.loads((tmp_path / "graph_summary.json").read_text())
    assert summary["fell"] is False and summary["distance_m"] == 9.5
    assert {row["patch"] for row in summary["stiffness"]} == {"default", "soft_t1"}


def test_node_rates_come_from_each_nodes_own_counter(tmp_path: Path) -> None:
    """10 s of sim time at a real-time factor of 0.5 (20 s of wall time): the wbc's 2,000 ticks + 100 safe-mode
    ticks are 105 Hz with 400 missed; the bridge's physics is 1 kHz x 0.5; a node without a summary is left out."""
    from tal_lab.graph_report import node_rates
    (tmp_path / "wbc_summary.json").write_text(json.dumps({"ticks": 2000, "safe_mode_ticks": 100}))
    (tmp_path / "tce_summary.json").write_text(json.dumps({"ticks": 2500}))
    bridge = {"sim_time_s": 10.0, "real_time_factor": 0.5}
    rates = {r["node"]: r for r in node_rates(tmp_path, bridge)}
    assert sorted(rates) == ["sim_bridge", "tce", "wbc"]
    assert rates["wbc"]["wall_rate_hz"] == pytest.approx(105.0) and rates["wbc"]["missed_ticks"] == 400
    assert rates["tce"]["missed_ticks"] == 0 and rates["sim_bridge"]["wall_rate_hz"] == pytest.approx(500.0)
    nodes = bench_rates({"rates": [r.__dict__ for r in topic_rates({}, 0.5)], "node_rates": list(rates.values()),
                         "mode": "realtime", "real_time_factor": 0.5, "peak_total_rss_mb": 1.0})["nodes"]
    assert nodes["wbc"]["achieved_hz"] == pytest.approx(105.0) and "node counter" in nodes["wbc"]["topic"]
    assert node_rates(tmp_path, {"sim_time_s": None}) == []


def test_qp_fallbacks_are_placed_on_the_course_by_the_base_track() -> None:
    """The wbc lists its QP fallbacks' sim times; the report says on which section of graph_tour the base was
    (T1 from x 1.5 m, stairs from 5.5 m) and over which x, so a user sees where a run struggled."""
    t = np.arange(0.0, 40.0, 0.004)
    position = np.stack([0.2 * t, np.zeros_like(t), np.full_like(t, 0.6)], axis=1)   # 0.2 m/s along x
    series = BagSeries(t, position, np.zeros(0), np.zeros((0, 3)), {}, {})
    text = fallbacks_by_section([8.0, 9.0, 27.0, 28.5, 29.0], series, "graph_tour")
    assert text == "soft_t1 2 (x 1.60-1.80 m), default 1 (x 5.40-5.40 m), stairs_up 2 (x 5.70-5.80 m)"
    assert fallbacks_by_section([], series, "graph_tour") == ""


def test_the_estimator_drift_is_split_by_course_section() -> None:
    """An estimate that gains 2 cm of z per metre on T1 (x 1.5-3 m) and nothing elsewhere: the T1 section holds
    its +3 cm at +0.02 m/m, the rigid sections before and after none, and the sections add up to the final
    drift (issue 32: the rate of drift per section in the report)."""
    t = np.arange(0.0, 25.0, 0.004)
    truth = np.stack([0.2 * t, np.zeros_like(t), np.full_like(t, 0.6)], axis=1)
    t_est = np.arange(0.0, 25.0, 0.003)
    x = 0.2 * t_est
    z_error = 0.02 * np.clip(x - 1.5, 0.0, 1.5)
    estimate = np.stack([x, np.zeros_like(x), 0.6 + z_error], axis=1)
    sections = estimator_sections(BagSeries(t, truth, t_est, estimate, {}, {}), "graph_tour")
    names = [s["name"] for s in sections]
    assert names == ["default", "soft_t1", "moderate_t2", "default"]
    by_name = {s["name"]: s for s in sections[:3]}
    assert by_name["soft_t1"]["drift_m"][2] == pytest.approx(0.03, abs=1e-3)
    assert by_name["soft_t1"]["z_drift_per_m"] == pytest.approx(0.02, abs=1e-3)
    assert abs(by_name["default"]["drift_m"][2]) < 1e-9 and abs(by_name["moderate_t2"]["drift_m"][2]) < 1e-3
    assert sum(s["drift_m"][2] for s in sections) == pytest.approx(z_error[-1], abs=1e-3)
    assert estimator_sections(BagSeries(t, truth, np.zeros(0), np.zeros((0, 3)), {}, {}), "graph_tour") == []
