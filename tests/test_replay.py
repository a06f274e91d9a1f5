"""Offline replay of a recorded run through the estimator gives the live estimates (to 1e-9): the graph
(bridge, state_estimator, wbc on the estimate, cmd_vel_script, bag_recorder on sim time) runs in one
process in lockstep, then tal_lab.estimation_replay runs on the bag."""

from __future__ import annotations

import json

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from tal_lab.estimation_replay import main as replay_main
from tal_lab.estimation_replay import replay_bag

from tal_control.cmd_vel_script_node import CmdVelScriptNode
from tal_control.wbc_node import WbcNode
from tal_core.robot_model import RobotModel
from tal_estimation.state_estimator_node import StateEstimatorNode
from tal_sim_bridge.bag_recorder_node import BagRecorderNode
from tal_sim_bridge.sim_bridge_node import SimBridgeNode

pytestmark = [pytest.mark.ros, pytest.mark.slow]
TOPICS = ["joint_states", "imu", "ground_truth/odom", "state_estimate", "joint_command"]


def test_replay_of_a_recorded_trot_reproduces_the_live_estimates(context, spin_until, tmp_path) -> None:
    bag = tmp_path / "bag"
    bridge = SimBridgeNode(context=context, parameter_overrides=[Parameter("duration_s", value=2.0)])
    wbc = WbcNode(context=context)
    estimator = StateEstimatorNode(context=context)
    script = CmdVelScriptNode(context=context, parameter_overrides=[
        Parameter("profile", value=[0.0, 0.0, 0.0, 0.0, 0.5, 0.3, 0.0, 0.0])])
    recorder = BagRecorderNode(context=context, parameter_overrides=[
        Parameter("output", value=str(bag)), Parameter("use_sim_time", value=True), Parameter("topics", value=TOPICS)])
    nodes = (recorder, bridge, estimator, wbc, script)
    executor = SingleThreadedExecutor(context=context)
    for node in nodes:
        executor.add_node(node)
    try:
        assert spin_until(executor, lambda: len(recorder._subscribed) == len(TOPICS), 30.0), recorder._subscribed
        assert spin_until(executor, lambda: bridge.finished, 300.0)
        spin_until(executor, lambda: False, 0.5)
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
    assert bridge.final_summary["body_ground_contact"] == []

    replay, summary = replay_bag(bag, RobotModel.from_name("hyq"))
    live = summary["vs_live_estimate"]
    assert live["samples"] >= 660  # 2 s at 333 Hz, every tick compared
    assert live["max_abs_position_m"] <= 1e-9 and live["max_abs_velocity_m_s"] <= 1e-9
    truth = summary["vs_ground_truth"]
    assert max(abs(v) for v in truth["final_drift_m"]) < 0.05
    counts = summary["counts"]
    assert counts["rejected"] == 0 and counts["held_imu_ticks"] == 0 and counts["restarts"] == 0
    assert counts["tce_ticks"] == counts["ticks"] and counts["tce_rejected"] == 0
    assert summary["real_time_factor"] > 0.0  # speed is measured in bench/, not asserted here (shared machine)

    # The command-line tool writes the report and plots next to the bag.
    assert replay_main([str(bag), "--out", str(tmp_path / "report")]) == 0
    assert json.loads((tmp_path / "report" / "summary.json").read_text())["vs_live_estimate"]["samples"] >= 660
    assert (tmp_path / "report" / "replay_state.png").stat().st_size > 10_000
    assert "against the live state_estimate" in (tmp_path / "report" / "report.md").read_text()
