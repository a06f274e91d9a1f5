"""run_report: a run in which the robot fell is marked invalid at the top and loses the figures the fall voids;
the bridge's command latency is shown."""

from __future__ import annotations

import json
from pathlib import Path

from tal_lab.run_report import fall_of, format_report, format_tce, main

WBC = {"gait": "crawl", "distance_m": 9.5, "height_error_mean_abs_m": 5.1, "velocity_error_mean_abs_m_s": 0.24,
       "yaw_rate_error_mean_abs_rad_s": 0.2, "ticks": 3000, "qp_fallbacks": 3, "safe_mode_ticks": 0,
       "rejected_inputs": 0}
ESTIMATOR = {"leg_odometry": "terrain_aware", "final_drift_m": [0.0, 0.0, 113.0], "rms_drift_m": [0.0, 0.0, 50.0],
             "velocity_rmse_m_s": [0.1, 0.1, 3.0], "compared_s": 25.0, "ticks": 8000, "rejected": {}, "restarts": 0,
             "reinitialisations": 0}


def bridge_summary(fell: bool) -> dict:
    """A bridge summary as the node writes it (the fields the reports read); the fall at 12 s, stopped there."""
    summary = {"sim_time_s": 12.2 if fell else 25.0, "wall_time_s": 50.0, "real_time_factor": 0.5,
               "course": "stance_course", "robot": "hyq", "mode": "lockstep", "commands_accepted": 3000,
               "commands_rejected": {}, "lockstep_timeouts": 0, "body_ground_contact": ["trunk"] if fell else [],
               "fell": fell, "fall_time_s": 12.0 if fell else None, "fall_confirmed_s": 12.2 if fell else None,
               "fall_position_m": [2.2, 0.01, 0.3] if fell else None,
               "fall_links": ["lf_upperleg", "trunk"] if fell else [],
               "fall_reason": "body-ground contact" if fell else None, "stop_on_fall": True, "stopped_on_fall": fell,
               "command_latency_ms": {"count": 3000, "untimed": 1, "median_ms": 4.25, "p99_ms": 11.5,
                                      "max_ms": 40.0}}
    return summary

TCE = {"final": {"LF": {"stiffness_n_per_m": 3500.0, "damping_ns_per_m": 400.0, "confidence": 0.9, "samples": 250}},
       "ticks": 3000, "rejected_inputs": 0, "samples_outside_map": 0, "history": []}


def test_a_run_stopped_at_the_fall_keeps_the_distance_to_it_and_drops_the_errors() -> None:
    report = format_report(bridge_summary(fell=True), WBC, "crawl")
    assert report.splitlines()[2] == "**INVALID RUN: HyQ fell at t = 12.00 s, x = 2.20 m (links lf_upperleg, trunk).**"
    assert "| distance travelled to the fall (wbc, base estimate) | 9.500 m |" in report
    assert "the run stopped there" in report
    assert "height error" not in report.split("|---|---|")[1] and "velocity error" not in report
    assert "4.25 / 11.50 / 40.00 ms (3000 commands)" in report


def test_a_run_that_went_on_after_the_fall_loses_the_distance_and_the_tce_estimates() -> None:
    bridge = dict(bridge_summary(fell=True), stopped_on_fall=False, stop_on_fall=False, sim_time_s=25.0)
    report = format_report(bridge, WBC, "crawl")
    assert "INVALID RUN" in report and "| distance travelled" not in report
    assert "the distance travelled (it runs past the fall)" in report
    assert "the run went on (stop_on_fall false)" in report
    tce = format_tce(TCE, fall_of(bridge))
    assert "left out" in tce and "3500" not in tce
    assert "3500" in format_tce(TCE, fall_of(bridge_summary(fell=True)))  # stopped: the estimates at the fall


def test_a_summary_from_before_fall_detection_falls_back_on_trunk_contact() -> None:
    legacy = {k: v for k, v in bridge_summary(fell=False).items()
              if not k.startswith(("fall", "fell", "stop", "robot", "command_latency"))}
    assert fall_of(legacy) is None
    assert "| fell | no |" in format_report(legacy, WBC, "crawl") and "latency" not in format_report(legacy, WBC, "c")
    legacy["body_ground_contact"] = ["lf_upperleg"]  # thighs on step edges alone were not a fall then
    assert fall_of(legacy) is None
    legacy["body_ground_contact"] = ["lf_upperleg", "trunk"]
    report = format_report(legacy, WBC, "crawl")
    assert report.splitlines()[2] == "**INVALID RUN: the robot fell (links lf_upperleg, trunk).**"
    assert "| distance travelled" not in report and "time unknown" in report


def test_the_command_line_report_leaves_out_the_estimator_drift_of_a_fallen_run(tmp_path: Path, capsys) -> None:
    for name, content in (("bridge", bridge_summary(fell=True)), ("wbc", WBC), ("estimator", ESTIMATOR)):
        (tmp_path / f"{name}.json").write_text(json.dumps(content))
    out = tmp_path / "report.md"
    assert main(["--bridge", str(tmp_path / "bridge.json"), "--wbc", str(tmp_path / "wbc.json"),
                 "--estimator", str(tmp_path / "estimator.json"), "--output", str(out)]) == 0
    report = out.read_text()
    assert "INVALID RUN" in report and "final drift [m]" not in report and "113" not in report
    assert "drift and its velocity RMSE (over the whole run, fall included) are left out" in report
