"""Parameters of the tal_control nodes (wbc, stand_controller, cmd_vel_script) at run time, as `ros2 param set`
sends them: a live one is validated and takes effect, a read-only one is refused with a reason, an invalid
live value is refused with the reason and changes nothing. The handlers are called directly (no DDS)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from geometry_msgs.msg import Twist
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from tal_control.cmd_vel_script_node import CmdVelScriptNode
from tal_control.motion.gait import TROT
from tal_control.stand_controller_node import StandControllerNode
from tal_control.wbc_node import WbcNode
from tal_core.ros.cdr import CdrView, view_of
from tal_core.ros.node_utils import stamp_from_ns

pytestmark = pytest.mark.ros


def set_one(node, name: str, value):
    return node.set_parameters([Parameter(name, value=value)])[0]


def joint_state(node: WbcNode, stamp_ns: int) -> CdrView:
    names = node.joint_names
    msg = JointState(name=names, position=list(node.model.description.nominal_joint_positions_rad),
                     velocity=[0.0] * len(names), effort=[0.0] * len(names))
    msg.header.stamp = stamp_from_ns(stamp_ns)
    return view_of(msg)  # what the node's subscription hands its callback


@pytest.mark.parametrize(("name", "value"), [("gait", "crawl"), ("control_period_s", 0.002),
                                             ("state_source", "ground_truth"), ("robot", "go1"),
                                             ("contact_model", "compliant"), ("watchdog_timeout_s", 0.1),
                                             ("terrain_stiffness_n_per_m", 1e5)])
def test_wbc_read_only_parameters_are_refused_with_a_reason(context, name: str, value) -> None:
    wbc = WbcNode(context=context)
    try:
        before = wbc.get_parameter(name).value
        result = set_one(wbc, name, value)
        assert not result.successful and "read-only" in result.reason
        assert wbc.get_parameter(name).value == before == wbc.p[name]
    finally:
        wbc.destroy_node()


def test_wbc_live_gains_and_qp_settings_take_effect_and_survive_a_restart(context) -> None:
    wbc = WbcNode(context=context)
    try:
        for name, value in (("K_x", 1500.0), ("D_theta", 150.0), ("friction_coefficient", 0.5),
                            ("max_normal_force_n", 800.0), ("touchdown_depth_m", 0.02),
                            ("foothold_feedback_s", 0.12)):
            result = set_one(wbc, name, value)
            assert result.successful, result.reason
            assert wbc.get_parameter(name).value == wbc.p[name] == value
        assert wbc.controller.wbc.gains.K_x == 1500.0 and wbc.controller.wbc.gains.D_theta == 150.0
        assert wbc.controller.wbc.gains.D_x == 400.0                    # the others as they were
        assert wbc.controller.wbc.settings.friction_coefficient == 0.5
        assert wbc.controller.wbc.settings.max_normal_force_n == 800.0
        assert wbc.controller.motion.params.touchdown_depth_m == 0.02
        assert wbc.controller.motion.params.k_feedback == 0.12
        # The simulation restarts (joint_states jump back): the new controller keeps the live values.
        before = wbc.controller
        wbc._on_joints(joint_state(wbc, 2_000_000_000))
        wbc._on_joints(joint_state(wbc, 100_000_000))
        assert wbc.controller is not before and wbc.policy.counters.restarts == 1
        assert wbc.controller.wbc.gains.K_x == 1500.0
        assert wbc.controller.wbc.settings.friction_coefficient == 0.5
        assert wbc.controller.motion.params.touchdown_depth_m == 0.02
    finally:
        wbc.destroy_node()


def test_wbc_invalid_live_values_are_refused_with_the_reason_and_change_nothing(context) -> None:
    wbc = WbcNode(context=context)
    try:
        crossed = set_one(wbc, "min_normal_force_n", 2000.0)            # above max_normal_force_n (1000 N)
        assert not crossed.successful and "min_normal_force_n" in crossed.reason and "min <= max" in crossed.reason
        assert wbc.get_parameter("min_normal_force_n").value == 10.0
        assert wbc.controller.wbc.settings.min_normal_force_n == 10.0
        negative = set_one(wbc, "K_x", -1.0)                            # outside the declared range
        assert not negative.successful and wbc.controller.wbc.gains.K_x == 2000.0
        periods = set_one(wbc, "stale_state_periods", 0)
        assert not periods.successful and wbc.policy.stale_ns == 10 * 4_000_000
    finally:
        wbc.destroy_node()


def test_wbc_velocity_limits_clamp_the_command_in_force_at_once(context) -> None:
    wbc = WbcNode(context=context)
    try:
        wbc._on_cmd_vel(Twist())
        command = Twist()
        command.linear.x, command.angular.z = 0.8, -0.9
        wbc._on_cmd_vel(command)
        assert wbc.cmd_vel == (0.8, 0.0, -0.9)
        assert set_one(wbc, "max_linear_velocity_m_s", 0.3).successful
        assert set_one(wbc, "max_yaw_rate_rad_s", 0.5).successful
        assert wbc.cmd_vel == (0.3, 0.0, -0.5)
        wbc._on_cmd_vel(command)
        assert wbc.cmd_vel == (0.3, 0.0, -0.5)
    finally:
        wbc.destroy_node()


def test_wbc_step_height_map_alignment_stale_periods_and_summary_path_are_live(context, tmp_path: Path) -> None:
    wbc = WbcNode(context=context)   # trot on the estimate
    try:
        assert set_one(wbc, "step_height_m", 0.15).successful
        assert wbc.controller.motion.gait.step_height_m == 0.15 == wbc.gait.step_height_m
        assert set_one(wbc, "step_height_m", 0.0).successful            # back to the preset
        assert wbc.controller.motion.gait.step_height_m == TROT.step_height_m
        aligner = wbc.map_aligner
        assert aligner is not None and aligner.time_constant_s == 1.0
        assert set_one(wbc, "map_alignment_time_constant_s", 3.0).successful
        assert wbc.map_aligner is aligner and aligner.time_constant_s == 3.0
        assert set_one(wbc, "map_alignment_time_constant_s", 0.0).successful and wbc.map_aligner is None
        assert set_one(wbc, "map_alignment_time_constant_s", 2.0).successful
        assert wbc.map_aligner is not None and wbc.map_aligner.time_constant_s == 2.0
        assert set_one(wbc, "stale_state_periods", 12).successful and wbc.policy.stale_ns == 48_000_000
        assert set_one(wbc, "impedance_min_confidence", 0.3).successful
        assert wbc.impedance_gate.min_confidence == 0.3
        assert set_one(wbc, "summary_path", str(tmp_path / "wbc.json")).successful
    finally:
        wbc.destroy_node()
    assert json.loads((tmp_path / "wbc.json").read_text())["gait"] == "trot"


def test_stand_controller_gains_are_live_and_its_robot_is_not(context) -> None:
    node = StandControllerNode(context=context)
    try:
        assert set_one(node, "kp_nm_per_rad", 900.0).successful and node.hold.kp == 900.0
        assert set_one(node, "kd_nms_per_rad", 25.0).successful and node.hold.kd == 25.0
        command = node.hold.command(node.hold.target_rad)
        assert set(command["kp"]) == {900.0} and set(command["kd"]) == {25.0}
        for name, value in (("robot", "go1"), ("control_period_s", 0.002)):
            refused = set_one(node, name, value)
            assert not refused.successful and "read-only" in refused.reason
        assert not set_one(node, "kp_nm_per_rad", -1.0).successful and node.hold.kp == 900.0
    finally:
        node.destroy_node()


def test_cmd_vel_script_profile_is_live_and_a_bad_one_is_refused_with_the_reason(context) -> None:
    node = CmdVelScriptNode(context=context, parameter_overrides=[Parameter("profile", value=[0.0, 0.1, 0.0, 0.0])])
    try:
        assert node._twist(2_000_000_000).linear.x == 0.1
        assert set_one(node, "profile", [0.0, 0.0, 0.0, 0.0, 1.0, 0.4, 0.0, 0.2]).successful
        twist = node._twist(2_000_000_000)
        assert (twist.linear.x, twist.angular.z) == (0.4, 0.2)
        bad = set_one(node, "profile", [1.0, 0.4, 0.0, 0.2, 0.5, 0.0, 0.0, 0.0])   # start times decrease
        assert not bad.successful and "profile" in bad.reason and "increasing" in bad.reason
        assert node._twist(2_000_000_000).linear.x == 0.4
        for name, value in (("period_s", 0.05), ("stamped", False), ("lead_s", 0.5)):
            refused = set_one(node, name, value)
            assert not refused.successful and "read-only" in refused.reason
    finally:
        node.destroy_node()
