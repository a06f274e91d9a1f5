"""STANCE in a real rclpy graph: the tce node estimates the terrain stiffness that the compliant wbc uses."""

from __future__ import annotations

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from tal_control.cmd_vel_script_node import CmdVelScriptNode
from tal_control.wbc_node import WbcNode
from tal_estimation.tce_node import TceNode
from tal_msgs.msg import TerrainImpedance, WbcDiagnostics
from tal_sim_bridge.sim_bridge_node import SimBridgeNode

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_tce_feeds_the_compliant_wbc_on_t2(context, spin_until) -> None:
    bridge = SimBridgeNode(context=context, parameter_overrides=[
        Parameter("course", value="flat_t2"), Parameter("duration_s", value=5.0),
        Parameter("heightmap_rows", value=81), Parameter("heightmap_cols", value=81)])
    wbc = WbcNode(context=context, parameter_overrides=[
        Parameter("gait", value="crawl"), Parameter("contact_model", value="compliant"),
        Parameter("state_source", value="ground_truth")])
    tce = TceNode(context=context)
    script = CmdVelScriptNode(context=context, parameter_overrides=[
        Parameter("profile", value=[0.0, 0.0, 0.0, 0.0, 1.0, 0.05, 0.0, 0.0])])
    probe = rclpy.create_node("probe", context=context)
    last: dict[str, object] = {}
    probe.create_subscription(TerrainImpedance, "terrain_impedance", lambda m: last.__setitem__("imp", m), 100)
    probe.create_subscription(WbcDiagnostics, "wbc/diagnostics", lambda m: last.__setitem__("diag", m), 100)
    executor = SingleThreadedExecutor(context=context)
    nodes = (bridge, wbc, tce, script, probe)
    for node in nodes:
        executor.add_node(node)
    try:
        assert spin_until(executor, lambda: bridge.finished, 600.0)
        spin_until(executor, lambda: False, 0.3)
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
    assert bridge.final_summary["body_ground_contact"] == []
    assert bridge.final_summary["lockstep_timeouts"] == 0
    impedance = last["imp"]
    assert all(impedance.valid)
    np.testing.assert_allclose(np.array(impedance.stiffness_normal), 8000.0, rtol=0.10)
    assert min(impedance.confidence) > 0.5
    assert tce.samples_outside_map == 0 and tce.rejected_inputs == 0
    diag = last["diag"]
    assert diag.contact_model == "compliant" and diag.failed_qps == 0
    assert max(diag.desired_penetration) > 0.005     # c3WBC plans centimetres of sinkage on T2
