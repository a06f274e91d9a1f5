"""Parameters of the estimation nodes (state_estimator, tce) at run time, as `ros2 param set` sends them: a
live one is validated and takes effect from the next tick, a read-only one is refused with a reason, an
invalid live value is refused with the reason and changes nothing. Messages go to the handlers directly
(no DDS); what the nodes publish is caught at the publisher."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu, JointState

from tal_core.ros.cdr import CdrView, view_of
from tal_core.ros.node_utils import stamp_from_ns
from tal_estimation.state_estimator_node import StateEstimatorNode
from tal_estimation.tce_node import TceNode
from tal_msgs.msg import ContactState, HeightMap, TerrainImpedance

pytestmark = pytest.mark.ros

MS = 1_000_000  # [ns]


class Caught:
    """Stands in for a publisher: keeps what the node publishes (serialised outputs deserialised as
    ``msg_type``, as a subscriber would get them)."""

    def __init__(self, msg_type) -> None:
        self.msg_type = msg_type
        self.messages: list = []

    def publish(self, msg) -> None:
        self.messages.append(deserialize_message(msg, self.msg_type) if isinstance(msg, bytes) else msg)

    def get_subscription_count(self) -> int:
        return 1  # a listener: outputs built only for one are built


def set_one(node, name: str, value):
    return node.set_parameters([Parameter(name, value=value)])[0]


def standing_joints(node, stamp_ns: int) -> CdrView:
    """The robot standing on its nominal joints with the torques holding its weight on four feet."""
    model = node.model
    q = np.asarray(model.description.nominal_joint_positions_rad, float)
    model.update(model.make_q(np.array([0.0, 0.0, model.nominal_base_height_m]), np.array([0.0, 0.0, 0.0, 1.0]), q),
                 np.zeros(model.nv))
    h = model.nonlinear_effects()
    grf = np.array([0.0, 0.0, model.total_mass_kg * 9.81 / 4.0])
    tau = np.concatenate([h[model.leg_joint_v_indices(leg)] + model.leg_torques_for_foot_force(leg, grf)
                          for leg in range(4)])
    names = list(model.description.joint_names)
    msg = JointState(name=names, position=q.tolist(), velocity=[0.0] * len(names), effort=tau.tolist())
    msg.header.stamp = stamp_from_ns(stamp_ns)
    return view_of(msg)  # what the node's subscription hands its callback


def imu_at_rest(stamp_ns: int) -> CdrView:
    msg = Imu()
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.linear_acceleration.z = 9.81
    return view_of(msg)


def feed(node: StateEstimatorNode, ks) -> None:
    for k in ks:
        node._on_imu(imu_at_rest(k * MS))
        node._on_joints(standing_joints(node, k * MS))


@pytest.mark.parametrize(("node_class", "name", "value"), [
    (StateEstimatorNode, "robot", "solo12"), (StateEstimatorNode, "period_s", 0.004),
    (StateEstimatorNode, "leg_odometry", "terrain_aware"), (StateEstimatorNode, "initial_pose_source", "standing"),
    (StateEstimatorNode, "use_magnetometer", True), (TceNode, "robot", "solo12"), (TceNode, "base_source", "estimate"),
    (TceNode, "control_period_s", 0.002), (TceNode, "window", 100), (TceNode, "estimate_tangential", True)])
def test_structural_parameters_are_read_only(context, node_class, name: str, value) -> None:
    """Robot, topics, rates, sources and buffer shapes are fixed at start-up: a set is refused with a reason."""
    node = node_class(context=context)
    try:
        before = node.get_parameter(name).value
        result = set_one(node, name, value)
        assert not result.successful and "read-only" in result.reason
        assert node.get_parameter(name).value == before
    finally:
        node.destroy_node()


def test_state_estimator_live_parameters_take_effect_from_the_next_tick(context, tmp_path: Path) -> None:
    node = StateEstimatorNode(context=context, parameter_overrides=[Parameter("initial_pose_source", value="standing")])
    contacts = node.pub_contact = Caught(ContactState)
    try:
        feed(node, range(0, 4))
        assert [list(c.in_contact) for c in contacts.messages] == [[True] * 4]   # a quarter of the weight each

        # 30 % of the weight per leg: the standing legs are not in contact any more.
        result = set_one(node, "contact_threshold_weight_fraction", 0.3)
        assert result.successful, result.reason
        feed(node, range(4, 7))
        assert list(contacts.messages[-1].in_contact) == [False] * 4

        # A 5 m/s^2 accelerometer range: the IMU at rest (9.81 m/s^2) is rejected as saturated.
        assert not node.rejections
        assert set_one(node, "accel_range_m_s2", 5.0).successful
        feed(node, [7])
        assert node.rejections == {"imu_saturated": 1} and node.estimator.settings.accel_range_m_s2 == 5.0

        # Invalid live values are refused with the reason and change nothing.
        refused = set_one(node, "accel_range_m_s2", -1.0)
        assert not refused.successful and "out of range" in refused.reason and node.estimator.settings.accel_range_m_s2 == 5.0
        refused = set_one(node, "initial_xy_m", [1.0])
        assert not refused.successful and "2 values" in refused.reason and node.stream.initial_xy == (0.0, 0.0)

        assert set_one(node, "summary_path", str(tmp_path / "estimator.json")).successful
    finally:
        node.destroy_node()
    assert json.loads((tmp_path / "estimator.json").read_text())["rejected"] == {"imu_saturated": 1}


def heightmap(stamp_ns: int) -> HeightMap:
    """4 m x 4 m of flat ground at z = 0 around the origin."""
    msg = HeightMap(resolution=0.1, rows=40, cols=40, heights=[0.0] * 1600)
    msg.header.stamp = stamp_from_ns(stamp_ns)
    return msg


def base_at_rest(node: TceNode, stamp_ns: int) -> CdrView:
    msg = Odometry()
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.pose.pose.position.z = node.model.nominal_base_height_m
    msg.pose.pose.orientation.w = 1.0
    return view_of(msg)


def test_tce_live_parameters_take_effect_from_the_next_tick(context) -> None:
    # wait_for_base false: a tick takes the latest base state as it arrives (the stale check at work).
    node = TceNode(context=context, parameter_overrides=[Parameter("wait_for_base", value=False)])
    published = node.pub = Caught(TerrainImpedance)
    try:
        node._on_heightmap(heightmap(0))
        node._on_base(base_at_rest(node, 0))
        node._on_joints(standing_joints(node, 100 * MS))          # the base state is 25 periods old: skipped
        assert published.messages == [] and node.driver.stale_ticks == 1

        assert set_one(node, "stale_state_periods", 1000).successful
        node._on_joints(standing_joints(node, 200 * MS))
        assert len(published.messages) == 1 and list(published.messages[0].samples) == [1, 1, 1, 1]

        # A contact threshold above the quarter weight (213 N): the feet stop feeding their windows.
        assert set_one(node, "contact_force_threshold_n", 300.0).successful
        node._on_joints(standing_joints(node, 204 * MS))
        assert list(published.messages[-1].samples) == [1, 1, 1, 1]

        refused = set_one(node, "min_samples", 1000)            # more than the window holds
        assert not refused.successful and "min_samples" in refused.reason and node.tce.settings.min_samples == 50
        assert node.get_parameter("min_samples").value == 50
    finally:
        node.destroy_node()


def test_tce_node_waits_for_the_base_state_of_its_tick(context) -> None:
    """The default: a tick whose joint state comes before its base state is published when the base state
    arrives, stamped with the tick."""
    node = TceNode(context=context)
    published = node.pub = Caught(TerrainImpedance)
    try:
        node._on_heightmap(heightmap(0))
        node._on_joints(standing_joints(node, 0))
        assert published.messages == []
        node._on_base(base_at_rest(node, 0))
        assert len(published.messages) == 1 and published.messages[0].header.stamp.nanosec == 0
        node._on_base(base_at_rest(node, 4 * MS))  # the base first this time
        node._on_joints(standing_joints(node, 4 * MS))
        assert [m.header.stamp.nanosec for m in published.messages] == [0, 4 * MS]
        assert node.summary()["late_base_ticks"] == 0
    finally:
        node.destroy_node()


def test_tce_node_answers_a_repeated_joint_state_again_and_waits_for_the_map_of_its_tick(context) -> None:
    """The bridge repeats its first state until the first command: each repeat gets the last answer again (the
    first one may have been published before DDS matched the wbc's reader). With heightmap_period_s the tick at
    the map's grid point waits for that map."""
    node = TceNode(context=context, parameter_overrides=[Parameter("heightmap_period_s", value=0.008)])
    published = node.pub = Caught(TerrainImpedance)
    try:
        node._on_base(base_at_rest(node, 0))
        node._on_joints(standing_joints(node, 0))
        assert published.messages == []                      # waits for the map of 0 ms
        node._on_heightmap(heightmap(0))
        assert len(published.messages) == 1
        node._on_joints(standing_joints(node, 0))             # a repeat: the same answer again
        first, again = published.messages
        assert again.header == first.header and list(again.samples) == list(first.samples)
        np.testing.assert_array_equal(again.stiffness_normal, first.stiffness_normal)  # NaN: no estimate yet
        assert node.summary()["answers_resent"] == 1 and node.tce.estimates[0].samples == 1
        node._on_base(base_at_rest(node, 4 * MS))
        node._on_joints(standing_joints(node, 4 * MS))        # the map of 0 ms is due: at once
        node._on_base(base_at_rest(node, 8 * MS))
        node._on_joints(standing_joints(node, 8 * MS))
        assert [m.header.stamp.nanosec for m in published.messages] == [0, 0, 4 * MS]
        node._on_heightmap(heightmap(8 * MS))
        assert [m.header.stamp.nanosec for m in published.messages] == [0, 0, 4 * MS, 8 * MS]
        assert node.summary()["late_heightmaps"] == 0 and node.summary()["late_heightmap_ticks"] == 0
    finally:
        node.destroy_node()
