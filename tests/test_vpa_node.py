"""The vpa node in a real rclpy graph: it holds the default pose (flagged) without a map, adapts the pose
from the map at its update period of gait-state time, runs the TBR baseline from the vfa's footholds,
rejects (and counts) bad messages without stopping and refuses invalid parameters at start-up."""

from __future__ import annotations

import math

import pytest
from geometry_msgs.msg import Point
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from vital_fakes import MS, FakeWbc

from tal_core.ros.node_utils import ns_from_stamp
from tal_msgs.msg import BodyPoseReference, Foothold, FootholdArray, GaitState
from tal_perception.errors import VpaConfigError
from tal_perception.vpa_node import VpaNode

pytestmark = pytest.mark.ros


def start(context, **overrides):
    vpa = VpaNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
    wbc = FakeWbc(context)
    poses: list[BodyPoseReference] = []
    wbc.node.create_subscription(BodyPoseReference, "body_pose_reference", poses.append, 10)
    footholds = wbc.node.create_publisher(FootholdArray, "footholds", 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(vpa)
    executor.add_node(wbc.node)
    return vpa, wbc, poses, footholds, executor


def stop(executor, *nodes) -> None:
    executor.shutdown()
    for node in nodes:
        node.destroy_node()


def matched(wbc: FakeWbc) -> bool:
    return wbc.gait.get_subscription_count() >= 1 and wbc.node.count_publishers("body_pose_reference") >= 1


def test_default_pose_without_a_map_then_the_adapted_pose_at_the_update_period(context, spin_until) -> None:
    vpa, wbc, poses, _, executor = start(context, update_period_s=0.05)
    try:
        assert spin_until(executor, lambda: matched(wbc), 20.0)
        wbc.gait.publish(wbc.gait_state(1000 * MS))
        assert spin_until(executor, lambda: len(poses) == 1, 20.0)
        blind = poses[0]
        assert blind.source == "vpa" and not blind.optimal and ns_from_stamp(blind.header.stamp) == 1000 * MS
        assert blind.base_height == pytest.approx(wbc.base_z, abs=0.02) and blind.roll == 0.0 and blind.pitch == 0.0
        # A flat map; the next tick 4 ms later is within the update period: no new pose.
        wbc.maps.publish(wbc.heightmap(1002 * MS))
        wbc.gait.publish(wbc.gait_state(1004 * MS))
        spin_until(executor, lambda: False, 0.5)
        assert len(poses) == 1
        wbc.gait.publish(wbc.gait_state(1052 * MS))
        assert spin_until(executor, lambda: len(poses) == 2, 20.0)
        flat = poses[1]
        assert flat.optimal and ns_from_stamp(flat.header.stamp) == 1052 * MS
        assert abs(flat.roll) < 0.05 and abs(flat.pitch) < 0.05
        assert 0.2 <= flat.base_height <= 0.8 and min(flat.safe_footholds) > 0
        assert len(flat.hip_height) == 4 and all(math.isfinite(h) for h in flat.hip_height)
        assert vpa.counters()["status_ok"] == 1 and vpa.counters()["status_no_map"] == 1
        # Gait states within the period are not even deserialised; a due one or an older stamp (a restart or an
        # out-of-order sample to reject) is.
        assert not vpa.planner.wants(1056 * MS)
        assert vpa.planner.wants(1102 * MS) and vpa.planner.wants(1000 * MS)
    finally:
        stop(executor, vpa, wbc.node)


def test_tbr_follows_the_plane_of_the_vfa_footholds(context, spin_until) -> None:
    vpa, wbc, poses, footholds, executor = start(context, source="tbr", tbr_height_m=0.55)
    try:
        assert spin_until(executor, lambda: matched(wbc) and footholds.get_subscription_count() >= 1, 20.0)
        # Footholds on a plane rising 0.2 m per metre forward (x), from the hips' positions.
        msg = FootholdArray()
        msg.header.frame_id = "world"
        for leg in range(4):
            x, y = float(wbc.hips[leg, 0]), float(wbc.hips[leg, 1])
            msg.footholds.append(Foothold(leg=leg, step_count=3, selected=Point(x=x, y=y, z=0.1 + 0.2 * x)))
        footholds.publish(msg)
        spin_until(executor, lambda: False, 0.3)
        wbc.gait.publish(wbc.gait_state(1000 * MS))
        assert spin_until(executor, lambda: len(poses) == 1, 20.0)
        pose = poses[0]
        assert pose.source == "tbr" and pose.optimal
        assert pose.pitch == pytest.approx(-math.atan(0.2), abs=1e-6)  # nose up on a rising plane
        assert pose.roll == pytest.approx(0.0, abs=1e-6)
        assert pose.base_height == pytest.approx(0.1 + 0.55 / math.sqrt(1.0 + 0.04), abs=0.02)
    finally:
        stop(executor, vpa, wbc.node)


def test_bad_messages_are_counted_and_the_node_keeps_running(context, spin_until) -> None:
    vpa, wbc, poses, footholds, executor = start(context)
    try:
        assert spin_until(executor, lambda: matched(wbc), 20.0)
        nan_state = wbc.gait_state(1000 * MS)
        nan_state.base_twist.linear.x = math.nan
        wbc.gait.publish(nan_state)
        short = wbc.heightmap(1000 * MS)
        short.heights = short.heights[:-1]
        wbc.maps.publish(short)
        wrong_frame = GaitState()
        wrong_frame.header.frame_id = "odom"
        wbc.gait.publish(wrong_frame)
        bad = FootholdArray(footholds=[Foothold(leg=7, selected=Point(x=0.0, y=0.0, z=0.0))])
        footholds.publish(bad)
        assert spin_until(executor, lambda: sum(vpa.rejections.values()) == 4, 10.0)
        assert dict(vpa.rejections) == {"gait_state_nan": 1, "heightmap_size": 1, "gait_state_frame": 1,
                                        "foothold_invalid": 1}
        wbc.gait.publish(wbc.gait_state(1100 * MS))  # the node still answers
        assert spin_until(executor, lambda: len(poses) == 1, 20.0)
    finally:
        stop(executor, vpa, wbc.node)


def test_invalid_parameters_are_refused_at_start(context) -> None:
    with pytest.raises(ValueError, match=r"parameter 'source'"):
        VpaNode(context=context, parameter_overrides=[Parameter("source", value="learned")])
    with pytest.raises(ValueError, match=r"parameter 'update_period_s'"):
        VpaNode(context=context, parameter_overrides=[Parameter("update_period_s", value=0.0)])
    with pytest.raises((ValueError, VpaConfigError), match=r"cost"):
        VpaNode(context=context, parameter_overrides=[Parameter("cost", value="max")])


def test_a_repeated_gait_state_gets_the_same_pose_and_map_period_holds_an_update_for_its_map(
        context, spin_until) -> None:
    """The wbc re-sends a gait state whose answer is overdue: the vpa sends its pose again without a new update.
    With map_period_s an update waits for the map due at it."""
    vpa, wbc, poses, _, executor = start(context, update_period_s=0.05, map_period_s=0.05)
    try:
        assert spin_until(executor, lambda: matched(wbc), 20.0)
        wbc.maps.publish(wbc.heightmap(950 * MS))
        assert spin_until(executor, lambda: len(vpa.maps_inbox) == 1, 5.0)
        wbc.gait.publish(wbc.gait_state(1000 * MS))
        assert spin_until(executor, lambda: len(poses) == 1, 20.0)
        wbc.gait.publish(wbc.gait_state(1000 * MS))            # re-sent
        assert spin_until(executor, lambda: len(poses) == 2, 20.0)
        assert poses[1].base_height == poses[0].base_height and vpa.counters()["answers_resent"] == 1
        assert sum(v for k, v in vpa.counters().items() if k.startswith("status_")) == 1
        wbc.gait.publish(wbc.gait_state(1052 * MS))            # due: the map of 1000 ms, not here yet
        spin_until(executor, lambda: False, 0.5)
        assert len(poses) == 2 and vpa.counters()["updates_held_for_maps"] == 1
        wbc.maps.publish(wbc.heightmap(1000 * MS))
        assert spin_until(executor, lambda: len(poses) == 3, 20.0)
        assert ns_from_stamp(poses[2].header.stamp) == 1052 * MS and vpa.counters()["late_maps"] == 0
    finally:
        stop(executor, vpa, wbc.node)
