"""The sim_bridge node in a real rclpy graph (one process, private context): lockstep protocol, topic
rates in sim time, bad joint commands, start-up errors."""

from __future__ import annotations

import json
import math
from collections import Counter

import pytest
import rclpy
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState

from tal_control.stand_controller_node import StandControllerNode
from tal_core.errors import CourseConfigError
from tal_msgs.msg import ContactState, HeightMap, JointCommand
from tal_sim_bridge.sim_bridge_node import SimBridgeNode

pytestmark = pytest.mark.ros

TOPICS = {
    "clock": Clock, "joint_states": JointState, "imu": Imu, "ground_truth/odom": Odometry,
    "ground_truth/contacts": ContactState, "terrain/heightmap": HeightMap, "foot_contacts": ContactState,
}


class Probe:
    """Counts messages per topic and keeps the last one."""

    def __init__(self, ctx) -> None:
        self.node = rclpy.create_node("probe", context=ctx)
        self.counts: Counter[str] = Counter()
        self.last: dict[str, object] = {}
        for topic, msg_type in TOPICS.items():
            self.node.create_subscription(msg_type, topic, self._callback(topic), 1000)
        self.command_pub = self.node.create_publisher(JointCommand, "joint_command", 10)

    def _callback(self, topic: str):
        def on_message(msg) -> None:
            self.counts[topic] += 1
            self.last[topic] = msg
        return on_message




def test_lockstep_with_stand_controller_publishes_every_topic_at_its_rate(context, spin_until) -> None:
    bridge = SimBridgeNode(context=context, parameter_overrides=[
        Parameter("course", value="flat_t2"), Parameter("duration_s", value=1.0),
        Parameter("foot_sensors", value=True)])
    controller = StandControllerNode(context=context)
    probe = Probe(context)
    executor = SingleThreadedExecutor(context=context)
    for node in (bridge, controller, probe.node):
        executor.add_node(node)
    try:
        assert spin_until(executor, lambda: bridge.finished, 120.0), "bridge did not finish 1 s of sim time"
        spin_until(executor, lambda: False, 0.5)  # drain the last messages
    finally:
        executor.shutdown()
        for node in (bridge, controller, probe.node):
            node.destroy_node()
    summary = bridge.final_summary
    assert summary is not None
    # Lockstep: every control tick (250 in 1 s) was answered by the controller, none timed out.
    assert summary["lockstep_timeouts"] == 0
    # One answer per tick; the initial state may be answered twice (the bridge repeats it until the
    # first command arrives, and the controller answers a repeated state again).
    assert 250 <= summary["commands_accepted"] <= 252
    assert summary["sim_time_s"] == pytest.approx(1.0)
    assert summary["body_ground_contact"] == []
    assert summary["fell"] is False and summary["stopped_on_fall"] is False
    # Command latency: every tick after the initial state was timed once (a second answer is not).
    latency = summary["command_latency_ms"]
    assert 245 <= latency["count"] <= 250, latency
    assert 0.0 < latency["median_ms"] <= latency["p99_ms"] <= latency["max_ms"]
    # Rates in sim time: 1 kHz sensors, 250 Hz clock, ground truth and contacts, 20 Hz heightmap, plus the initial state and its
    # re-sends while the bridge waited for the controller (DDS discovery); a late-joining probe may miss
    # the very first ones.
    extra = 1 + summary["initial_state_repeats"]
    for topic, expected in (("clock", 250), ("joint_states", 1000), ("imu", 1000), ("ground_truth/odom", 250),
                            ("ground_truth/contacts", 250), ("terrain/heightmap", 20), ("foot_contacts", 250)):
        assert expected - 5 <= probe.counts[topic] <= expected + extra, (topic, probe.counts[topic], extra)
    last_clock = probe.last["clock"].clock
    assert last_clock.sec + last_clock.nanosec * 1e-9 == pytest.approx(1.0)
    joints = probe.last["joint_states"]
    assert list(joints.name) == list(bridge.core.sim.description.joint_names)
    assert all(math.isfinite(x) for x in joints.effort)
    contacts = probe.last["ground_truth/contacts"]
    assert all(contacts.in_contact)
    assert sum(f.z for f in contacts.force) == pytest.approx(86.774 * 9.81, rel=0.05)
    sensors = probe.last["foot_contacts"]   # the feet's sensors: noisy loads, flags, nothing a sensor cannot know
    assert all(sensors.in_contact)
    assert sum(f.z for f in sensors.force) == pytest.approx(86.774 * 9.81, rel=0.05)
    assert all(math.isnan(p.x) for p in sensors.foot_position) and all(math.isnan(d) for d in sensors.penetration)
    heightmap = probe.last["terrain/heightmap"]
    assert (heightmap.rows, heightmap.cols, len(heightmap.heights)) == (33, 33, 33 * 33)
    imu = probe.last["imu"]
    assert imu.linear_acceleration.z == pytest.approx(9.81, abs=0.5)


def test_bad_joint_commands_are_rejected_counted_and_the_bridge_keeps_damping(context, spin_until) -> None:
    bridge = SimBridgeNode(context=context, parameter_overrides=[
        Parameter("mode", value="realtime"), Parameter("course", value="flat_rigid"),
        # No valid command ever comes: physics starts after the start-up timeout, with the safe damping.
        Parameter("startup_timeout_s", value=0.2),
        Parameter("stop_on_fall", value=False)])  # it collapses under damping and must go on stepping
    probe = Probe(context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(bridge)
    executor.add_node(probe.node)
    names = list(bridge.core.sim.description.joint_names)
    bad = []
    unknown = JointCommand(name=["no_such_joint"] + names[1:], effort=[0.0] * 12)
    bad.append(unknown)
    bad.append(JointCommand(name=names, effort=[0.0] * 11))
    bad.append(JointCommand(name=names, effort=[float("nan")] + [0.0] * 11))
    bad.append(JointCommand(name=names, effort=[0.0] * 12, position=[0.0] * 12, kp=[-1.0] * 12))
    try:
        assert spin_until(executor, lambda: probe.counts["joint_states"] > 5, 20.0)
        # Publish only once DDS has matched the bridge's subscription (else the first ones are dropped).
        assert spin_until(executor, lambda: probe.command_pub.get_subscription_count() >= 1, 20.0)
        for _ in range(3):
            for msg in bad:
                probe.command_pub.publish(msg)
            spin_until(executor, lambda: False, 0.2)
        assert spin_until(executor, lambda: bridge.core.commands.rejected_total == 12, 10.0)
        steps_before = bridge.core.sim.step_count
        assert spin_until(executor, lambda: bridge.core.sim.step_count > steps_before + 50, 20.0), \
            "the bridge stopped stepping after bad commands"
    finally:
        executor.shutdown()
        bridge.destroy_node()
        probe.node.destroy_node()
    assert dict(bridge.core.commands.rejections) == {
        "unknown_joint": 3, "wrong_size": 3, "non_finite": 3, "negative_gain": 3}
    assert bridge.core.commands.held is None  # still damping: no valid command ever arrived
    joints = probe.last["joint_states"]
    damping = bridge.params["safe_damping_nms_per_rad"]
    # The delivered torque is the damping torque of the previous step's velocity. The robot collapses
    # under damping alone, so that velocity may differ from the published one by a few rad/s (impacts,
    # real-time catch-up steps): bound it by the joint speed limit (12 rad/s), far below any command.
    for effort in joints.effort:
        assert abs(effort) <= damping * 12.0


def test_a_fall_ends_the_run_with_a_summary_saying_when_and_where(context, spin_until, tmp_path) -> None:
    """No controller: HyQ collapses under the bridge's joint damping, a fall, which ends the run long before
    duration_s (as duration_s would: summary written, ``finished``)."""
    path = tmp_path / "bridge_summary.json"
    bridge = SimBridgeNode(context=context, parameter_overrides=[
        Parameter("mode", value="realtime"), Parameter("course", value="flat_t4"), Parameter("duration_s", value=20.0),
        Parameter("summary_path", value=str(path))])
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(bridge)
    try:
        assert spin_until(executor, lambda: bridge.finished, 60.0), "the bridge did not stop at the fall"
        step_at_finish = bridge.core.sim.step_count
        spin_until(executor, lambda: False, 0.2)
        assert bridge.core.sim.step_count == step_at_finish  # no step after the run ended
    finally:
        executor.shutdown()
        bridge.destroy_node()
    summary = json.loads(path.read_text())
    assert summary == json.loads(json.dumps(bridge.final_summary))
    assert summary["fell"] is True and summary["stopped_on_fall"] is True
    assert 0.0 < summary["fall_time_s"] < summary["sim_time_s"] < 5.0
    assert summary["sim_time_s"] == pytest.approx(summary["fall_time_s"] + 0.2, abs=0.01)   # fall_confirm_s
    assert summary["fall_position_m"][2] < 0.6 * bridge.core.sim.nominal_base_height_m + 0.01
    assert isinstance(summary["fall_links"], list) and summary["fall_reason"]
    assert summary["command_latency_ms"]["count"] == 0  # no controller


def test_invalid_course_fails_at_start_up_naming_file_patch_and_field(context, tmp_path) -> None:
    course = tmp_path / "bad_course.yaml"
    course.write_text(
        "course:\n  name: bad\n  extent: {x: [-2.0, 4.0], y: [-1.0, 1.0]}\n"
        "  default: {terrain: T4}\n"
        "  patches:\n    - {name: mud, type: flat, x: [1.0, 2.0], stiffness_n_per_m: -5, damping_ns_per_m: 400}\n")
    with pytest.raises(CourseConfigError, match=r"bad_course\.yaml.*'mud'.*stiffness_n_per_m"):
        SimBridgeNode(context=context, parameter_overrides=[Parameter("course", value=str(course))])


def test_invalid_parameter_fails_at_start_up_naming_it(context) -> None:
    with pytest.raises(ValueError, match="mode"):
        SimBridgeNode(context=context, parameter_overrides=[Parameter("mode", value="fast")])
    with pytest.raises(ValueError, match="torque_gain"):
        SimBridgeNode(context=context, parameter_overrides=[Parameter("effects.torque_gain", value=0.0)])


def test_realtime_physics_waits_for_the_first_command(context, spin_until) -> None:
    """A robot does not walk before its controller runs: in realtime mode the bridge re-sends its initial state
    and steps no physics until a command arrives (or the start-up timeout passes)."""
    bridge = SimBridgeNode(context=context, parameter_overrides=[Parameter("mode", value="realtime")])
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(bridge)
    try:
        spin_until(executor, lambda: False, 0.5)
        assert bridge.core.sim.step_count == 0 and bridge.initial_state_repeats >= 3
    finally:
        executor.shutdown()
        bridge.destroy_node()


def test_a_waiting_lockstep_tick_sends_the_last_heightmaps_again_for_a_late_subscriber(context, spin_until) -> None:
    """DDS drops what a writer publishes before it has matched a late reader; a map consumer (vfa, vpa, tce)
    holds its answer for the map due at its tick, so a lockstep bridge whose tick waits re-sends its last two
    maps, oldest first (the tour once stalled 2 s on a vpa whose heightmap subscription matched after the 0.05 s
    map; once the vpa's held update at 0.052 s, due the 0 s map, was released by the 0.05 s map alone and ran
    without a map)."""
    bridge = SimBridgeNode(context=context, parameter_overrides=[
        Parameter("course", value="flat_rigid"), Parameter("lockstep_timeout_s", value=60.0)])
    controller = StandControllerNode(context=context)
    executor = SingleThreadedExecutor(context=context)
    for node in (bridge, controller):
        executor.add_node(node)
    late = rclpy.create_node("late_map_consumer", context=context)
    stamps: list[int] = []
    try:
        assert spin_until(executor, lambda: bridge.core.sim.time_ns >= 60_000_000, 60.0)
        executor.remove_node(controller)  # the controller stops answering: the bridge waits at its tick
        waiting_at = bridge.core.sim.time_ns
        assert bridge.heightmap_resends == 0
        late.create_subscription(HeightMap, "terrain/heightmap",
                                 lambda msg: stamps.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec), 10)
        executor.add_node(late)
        assert spin_until(executor, lambda: {0, 50_000_000} <= set(stamps), 20.0), (stamps, bridge.heightmap_resends)
    finally:
        executor.shutdown()
        for node in (bridge, controller, late):
            node.destroy_node()
    assert bridge.core.sim.time_ns == waiting_at and bridge.gate.timeouts == 0  # it waited, and sent the map
    assert stamps[:2] == [0, 50_000_000] and set(stamps) == {0, 50_000_000} and bridge.heightmap_resends >= 2
    assert bridge.summary()["heightmap_resends"] == bridge.heightmap_resends
