"""The wbc node in real rclpy graphs: it trots the simulated HyQ, enters and leaves safe mode on stale
state, and rejects bad input without crashing."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from tal_control.cmd_vel_script_node import CmdVelScriptNode
from tal_control.wbc_node import WbcNode
from tal_core.robot_model import RobotModel
from tal_core.ros.node_utils import stamp_from_ns
from tal_estimation.state_estimator_node import StateEstimatorNode
from tal_msgs.msg import ContactState, GaitState, JointCommand, WbcDiagnostics
from tal_sim_bridge.sim_bridge_node import SimBridgeNode

pytestmark = pytest.mark.ros




@pytest.mark.slow
def test_graph_trots_forward_on_the_state_estimate_with_gait_state_and_diagnostics_at_250_hz(
        context, spin_until, tmp_path) -> None:
    """The default graph: the wbc closes the loop on the state_estimator's estimate (not ground truth)."""
    bridge = SimBridgeNode(context=context, parameter_overrides=[Parameter("duration_s", value=3.0)])
    wbc = WbcNode(context=context)
    estimator = StateEstimatorNode(context=context, parameter_overrides=[
        Parameter("summary_path", value=str(tmp_path / "estimator.json"))])
    script = CmdVelScriptNode(context=context, parameter_overrides=[
        Parameter("profile", value=[0.0, 0.0, 0.0, 0.0, 0.5, 0.3, 0.0, 0.0])])
    probe = rclpy.create_node("probe", context=context)
    counts = {"gait": 0, "diag": 0}
    last: dict[str, object] = {}

    def on_gait(msg: GaitState) -> None:
        counts["gait"] += 1
        last["gait"] = msg

    def on_diag(msg: WbcDiagnostics) -> None:
        counts["diag"] += 1
        last["diag"] = msg
    probe.create_subscription(GaitState, "gait_state", on_gait, 1000)
    probe.create_subscription(WbcDiagnostics, "wbc/diagnostics", on_diag, 1000)
    executor = SingleThreadedExecutor(context=context)
    nodes = (bridge, wbc, estimator, script, probe)
    for node in nodes:
        executor.add_node(node)
    start = bridge.core.sim.robot_state().base_position_m.copy()
    try:
        assert spin_until(executor, lambda: bridge.finished, 300.0)
        spin_until(executor, lambda: False, 0.3)
        end = bridge.core.sim.robot_state().base_position_m.copy()
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
    assert bridge.final_summary["lockstep_timeouts"] == 0
    assert bridge.final_summary["body_ground_contact"] == []
    assert end[2] > 0.6 * start[2]
    assert end[0] - start[0] > 0.3          # trotting forward (0.3 m/s command from 0.5 s, ramped)
    assert wbc.ticks == 750 or wbc.ticks == 751
    assert 740 <= counts["gait"] <= 751 and 740 <= counts["diag"] <= 751
    diag = last["diag"]
    assert diag.mode == WbcDiagnostics.MODE_NORMAL and diag.failed_qps == 0 and diag.rejected_inputs == 0
    assert sum(f.z for f in diag.desired_force) == pytest.approx(86.77 * 9.81, rel=0.3)
    gait = last["gait"]
    assert gait.gait == "trot" and max(gait.step_count) >= 3
    # The hips move forward with the trunk reference (the vfa node predicts the hip height at touchdown).
    assert all(math.isfinite(v.z) and v.x > 0.0 for v in gait.hip_velocity)
    # The estimator ran at 333 Hz in sim time, clean, and tracked the truth while the robot walked on it.
    report = json.loads((tmp_path / "estimator.json").read_text())
    assert 990 <= report["ticks"] <= 1001 and report["rejected"] == {} and report["restarts"] == 0
    assert max(abs(v) for v in report["final_drift_m"]) < 0.05
    assert max(report["velocity_rmse_m_s"]) < 0.1


class FakeRobot:
    """Publishes joint_states and ground-truth odometry of a standing HyQ with chosen stamps."""

    def __init__(self, context) -> None:
        self.node = rclpy.create_node("fake_robot", context=context)
        self.model = RobotModel.from_name("hyq")
        self.joints = self.node.create_publisher(JointState, "joint_states", 10)
        self.odom = self.node.create_publisher(Odometry, "ground_truth/odom", 10)
        self.commands: list[JointCommand] = []
        self.diagnostics: list[WbcDiagnostics] = []
        self.node.create_subscription(JointCommand, "joint_command", self.commands.append, 100)
        self.node.create_subscription(WbcDiagnostics, "wbc/diagnostics", self.diagnostics.append, 100)
        self.q = self.model.description.nominal_joint_positions_rad.copy()
        self.base_z = float(self.model.neutral_q()[2])

    def matched(self) -> bool:
        """True once the wbc subscribes to our topics and publishes to our subscriptions."""
        return (self.joints.get_subscription_count() >= 1 and self.odom.get_subscription_count() >= 1
                and self.node.count_publishers("joint_command") >= 1)

    def publish_joints(self, stamp_ns: int, position=None) -> None:
        msg = JointState()
        msg.header.stamp = stamp_from_ns(stamp_ns)
        msg.name = list(self.model.description.joint_names)
        msg.position = list(self.q if position is None else position)
        msg.velocity = [0.0] * 12
        msg.effort = [0.0] * 12
        self.joints.publish(msg)

    def publish_odom(self, stamp_ns: int, z: float | None = None) -> None:
        msg = Odometry()
        msg.header.stamp = stamp_from_ns(stamp_ns)
        msg.pose.pose.position.z = self.base_z if z is None else z
        msg.pose.pose.orientation.w = 1.0
        self.odom.publish(msg)


def standing_wbc_with_robot(context, *overrides: Parameter) -> tuple[WbcNode, FakeRobot, SingleThreadedExecutor]:
    """A standing wbc on ground-truth odometry (plus ``overrides``), a FakeRobot and an executor spinning both."""
    wbc = WbcNode(context=context, parameter_overrides=[Parameter("gait", value="stand"),
                                                        Parameter("state_source", value="ground_truth"), *overrides])
    robot = FakeRobot(context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(wbc)
    executor.add_node(robot.node)
    return wbc, robot, executor


def test_stale_state_enters_safe_mode_and_fresh_state_leaves_it(context, spin_until) -> None:
    wbc, robot, executor = standing_wbc_with_robot(context)
    try:
        assert spin_until(executor, robot.matched, 20.0)  # DDS discovery in both directions
        # Tick 0: fresh state -> normal torque command (no damping term).
        robot.publish_odom(0)
        robot.publish_joints(0)
        assert spin_until(executor, lambda: len(robot.commands) >= 1, 10.0)
        assert len(robot.commands[-1].kd) == 0 and wbc.mode == WbcDiagnostics.MODE_NORMAL
        # A tick at 8 ms whose ground truth does not come (4 ms: deferred, decided at 8 ms on the 0 ms state):
        # 2 periods old, not stale: a normal command on the base state predicted to the tick.
        robot.publish_joints(4_000_000)
        robot.publish_joints(8_000_000)
        assert spin_until(executor, lambda: len(robot.commands) >= 2, 10.0)
        assert len(robot.commands[-1].kd) == 0 and wbc.mode == WbcDiagnostics.MODE_NORMAL
        assert wbc.predicted_base_ticks == 1
        # Ticks at 44 and 48 ms while the last base state is from 0 ms: the 44 ms tick waits for its
        # ground truth; when the 48 ms joint state arrives it is decided: 11 periods old > 10 -> safe mode.
        robot.publish_joints(44_000_000)
        spin_until(executor, lambda: False, 0.3)
        assert len(robot.commands) == 2
        robot.publish_joints(48_000_000)
        assert spin_until(executor, lambda: len(robot.commands) >= 3, 10.0)
        safe = robot.commands[-1]
        assert len(safe.kd) == 12 and all(k > 0 for k in safe.kd) and all(e == 0.0 for e in safe.effort)
        assert spin_until(executor, lambda: any(d.mode == WbcDiagnostics.MODE_SAFE for d in robot.diagnostics), 5.0)
        # Fresh state again at 52 ms (arrival order joints, then odom): back to normal.
        robot.publish_joints(52_000_000)
        robot.publish_odom(52_000_000)
        assert spin_until(executor, lambda: len(robot.commands) >= 4, 10.0)
        assert len(robot.commands[-1].kd) == 0 and wbc.mode == WbcDiagnostics.MODE_NORMAL
    finally:
        executor.shutdown()
        wbc.destroy_node()
        robot.node.destroy_node()


def test_nan_and_unknown_joints_are_rejected_and_counted(context, spin_until) -> None:
    wbc, robot, executor = standing_wbc_with_robot(context)
    try:
        assert spin_until(executor, robot.matched, 20.0)
        bad_q = robot.q.copy()
        bad_q[3] = np.nan
        robot.publish_joints(0, position=bad_q)
        robot.publish_odom(0, z=float("nan"))
        unknown = JointState(name=["no_joint"] * 12, position=[0.0] * 12, velocity=[0.0] * 12)
        robot.joints.publish(unknown)
        assert spin_until(executor, lambda: wbc.rejected_inputs >= 3, 10.0)
        assert robot.commands == []          # nothing computed from bad input
        robot.publish_odom(4_000_000)
        robot.publish_joints(4_000_000)
        assert spin_until(executor, lambda: len(robot.commands) >= 1, 10.0)
        assert np.all(np.isfinite(robot.commands[-1].effort))
        assert wbc.rejected_inputs == 3
    finally:
        executor.shutdown()
        wbc.destroy_node()
        robot.node.destroy_node()


def test_stamped_commands_apply_from_their_tick_and_late_ones_are_counted(context, spin_until) -> None:
    """cmd_vel_stamped: a command applies from the first tick at or after its stamp, whatever the arrival
    order; one that arrives after its tick applies at once and is counted as late."""
    wbc, robot, executor = standing_wbc_with_robot(context)
    commands = robot.node.create_publisher(TwistStamped, "cmd_vel_stamped", 100)

    def command(stamp_ns: int, vx: float) -> None:
        msg = TwistStamped()
        msg.header.stamp = stamp_from_ns(stamp_ns)
        msg.twist.linear.x = vx
        commands.publish(msg)

    def tick(stamp_ns: int) -> None:
        n = len(robot.commands)
        robot.publish_odom(stamp_ns)
        robot.publish_joints(stamp_ns)
        assert spin_until(executor, lambda: len(robot.commands) > n, 10.0)

    try:
        assert spin_until(executor, lambda: robot.matched() and commands.get_subscription_count() >= 1, 20.0)
        command(8_000_000, 0.2)   # out of order: the later one first
        command(4_000_000, 0.1)
        spin_until(executor, lambda: False, 0.3)
        tick(0)
        assert wbc.cmd_vel == (0.0, 0.0, 0.0)
        tick(4_000_000)
        assert wbc.cmd_vel == (0.1, 0.0, 0.0)
        tick(8_000_000)
        assert wbc.cmd_vel == (0.2, 0.0, 0.0)
        command(4_000_000, 0.5)   # older than the command in force: ignored
        command(10_000_000, 0.3)  # its tick (12 ms) has not run: queued
        spin_until(executor, lambda: False, 0.3)
        tick(12_000_000)
        assert wbc.cmd_vel == (0.3, 0.0, 0.0) and wbc.command_input.late == 0
        command(14_000_000, 0.4)  # after the tick at 12 ms, for the tick at 16 ms: in time
        command(12_000_000, 0.35)  # for the tick at 12 ms, which has run: applied now, late
        assert spin_until(executor, lambda: wbc.command_input.late == 1, 10.0)
        assert wbc.cmd_vel == (0.35, 0.0, 0.0)
        tick(16_000_000)
        assert wbc.cmd_vel == (0.4, 0.0, 0.0) and wbc.summary()["late_cmd_vel"] == 1
    finally:
        executor.shutdown()
        wbc.destroy_node()
        robot.node.destroy_node()


def test_first_tick_waits_for_the_command_source(context, spin_until) -> None:
    """With command_source_wait_s the lockstep run does not start (no joint_command) until a cmd_vel_stamped
    publisher exists; the bridge keeps repeating its initial state meanwhile, and the first command follows
    once the command source appears."""
    bridge = SimBridgeNode(context=context, parameter_overrides=[Parameter("duration_s", value=0.2)])
    wbc = WbcNode(context=context, parameter_overrides=[Parameter("state_source", value="ground_truth"),
                                                        Parameter("command_source_wait_s", value=60.0)])
    executor = SingleThreadedExecutor(context=context)
    for node in (bridge, wbc):
        executor.add_node(node)
    script = None
    try:
        spin_until(executor, lambda: False, 1.5)
        assert wbc.ticks == 0 and wbc.command_source_waits > 0 and bridge.core.commands.accepted == 0
        script = CmdVelScriptNode(context=context)
        executor.add_node(script)
        assert spin_until(executor, lambda: bridge.finished, 120.0)
    finally:
        executor.shutdown()
        for node in (bridge, wbc, script):
            if node is not None:
                node.destroy_node()
    assert wbc.ticks >= 50 and bridge.final_summary["lockstep_timeouts"] == 0


def test_contact_feedback_waits_for_the_ticks_contacts_and_searches_with_a_hovering_foot(context, spin_until) -> None:
    """contact_source ground_truth: a tick waits for the contacts of its stamp (the bridge sends them right
    after the joint state); a planned stance foot reported without contact searches for the ground."""
    wbc, robot, executor = standing_wbc_with_robot(context, Parameter("contact_source", value="ground_truth"))
    contacts = robot.node.create_publisher(ContactState, "ground_truth/contacts", 10)
    try:
        assert spin_until(executor, lambda: robot.matched() and contacts.get_subscription_count() >= 1, 20.0)
        robot.publish_odom(0)
        robot.publish_joints(0)
        spin_until(executor, lambda: False, 0.3)
        assert robot.commands == []  # waiting for the tick's contacts
        message = ContactState()
        message.header.stamp = stamp_from_ns(0)
        message.in_contact = [True, True, False, True]
        contacts.publish(message)
        assert spin_until(executor, lambda: len(robot.commands) >= 1, 10.0)
        assert wbc.controller.touchdown_search.searches.tolist() == [0, 0, 1, 0]
        assert wbc.summary()["touchdown_searches_per_leg"] == [0, 0, 1, 0]
        # Contacts that stop coming: the tick after is decided when the next joint state arrives, on the plan.
        robot.publish_odom(4_000_000)
        robot.publish_joints(4_000_000)
        robot.publish_odom(8_000_000)
        robot.publish_joints(8_000_000)
        assert spin_until(executor, lambda: len(robot.commands) >= 2, 10.0)
        assert wbc.deferred_ticks >= 1
    finally:
        executor.shutdown()
        wbc.destroy_node()
        robot.node.destroy_node()


def test_live_parameters_take_effect_at_the_next_tick(context, spin_until) -> None:
    """`ros2 param set` while running: a shorter stale_state_periods makes a base state 2 periods old stale
    (safe mode, which the default 10 periods would not enter), and the safe command holds with the new
    safe_damping_nms_per_rad; a read-only parameter is refused with a reason."""
    wbc, robot, executor = standing_wbc_with_robot(context)
    try:
        assert spin_until(executor, robot.matched, 20.0)
        robot.publish_odom(0)
        robot.publish_joints(0)
        assert spin_until(executor, lambda: len(robot.commands) >= 1, 10.0)
        assert len(robot.commands[-1].kd) == 0
        for name, value in (("stale_state_periods", 1), ("safe_damping_nms_per_rad", 55.0)):
            result = wbc.set_parameters([Parameter(name, value=value)])[0]
            assert result.successful, result.reason
        refused = wbc.set_parameters([Parameter("control_period_s", value=0.002)])[0]
        assert not refused.successful and "read-only" in refused.reason
        robot.publish_joints(4_000_000)   # its ground truth does not come: deferred
        robot.publish_joints(8_000_000)   # decided on the 0 ms base state: 8 ms > 1 period old
        assert spin_until(executor, lambda: len(robot.commands) >= 2, 10.0)
        assert list(robot.commands[-1].kd) == [55.0] * 12 and wbc.mode == WbcDiagnostics.MODE_SAFE
    finally:
        executor.shutdown()
        wbc.destroy_node()
        robot.node.destroy_node()


def test_a_tick_waiting_for_a_lost_answer_sends_its_gait_state_again(context, spin_until) -> None:
    """wait_for_footholds (lockstep): the tick at 4 ms waits for the answer to the gait state of 0 ms. A producer
    that never got that gait state (DDS matched its reader after it was sent) gets it again after RESEND_AFTER_S
    of wall time; its answer completes the tick, and an answer sent twice is used once."""
    from tal_control.wbc_node import RESEND_AFTER_S
    from tal_msgs.msg import FootholdArray

    wbc, robot, executor = standing_wbc_with_robot(context, Parameter("wait_for_footholds", value=True))
    producer = rclpy.create_node("vfa", context=context)
    gait_states: list[GaitState] = []
    producer.create_subscription(GaitState, "gait_state", gait_states.append, 10)
    footholds = producer.create_publisher(FootholdArray, "footholds", 10)
    executor.add_node(producer)
    try:
        assert spin_until(executor, lambda: robot.matched() and footholds.get_subscription_count() >= 1
                          and wbc.pub_gait.get_subscription_count() >= 1, 20.0)
        robot.publish_odom(0)
        robot.publish_joints(0)
        assert spin_until(executor, lambda: len(robot.commands) == 1 and len(gait_states) == 1, 10.0)
        gait_states.clear()                        # as if it had been lost
        robot.publish_odom(4_000_000)
        robot.publish_joints(4_000_000)
        assert spin_until(executor, lambda: len(gait_states) >= 1, 10.0 * RESEND_AFTER_S)
        assert gait_states[0].header.stamp.nanosec == 0 and wbc.gait_state_resends >= 1
        assert len(robot.commands) == 1            # the tick at 4 ms still waits
        answer = FootholdArray()
        answer.header.stamp = stamp_from_ns(0)
        answer.header.frame_id = "world"
        footholds.publish(answer)
        footholds.publish(answer)                  # the producer answered the re-sent state too
        assert spin_until(executor, lambda: len(robot.commands) == 2, 10.0)
        assert spin_until(executor, lambda: wbc.summary()["repeated_answers"] == 1, 5.0)
        assert wbc.summary()["gait_state_resends"] == wbc.gait_state_resends
    finally:
        executor.shutdown()
        for node in (wbc, robot.node, producer):
            node.destroy_node()


def test_an_unknown_startup_input_is_refused_with_the_known_ones(context) -> None:
    from tal_core.errors import InputError

    with pytest.raises(InputError, match=r"startup_inputs: unknown input\(s\) \['maps'\]; known: impedance"):
        WbcNode(context=context, parameter_overrides=[Parameter("startup_inputs", value="impedance, maps")])
    swbc = WbcNode(context=context, parameter_overrides=[Parameter("startup_inputs", value="impedance,footholds")])
    try:  # the sWBC reads no impedance: only the footholds' producer is waited for at the start
        assert swbc.policy.config.startup_inputs == ("footholds",)
    finally:
        swbc.destroy_node()
