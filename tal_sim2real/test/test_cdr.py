"""The recording's high-rate messages decoded straight from their CDR bytes (cdr.py, issue 34: rclpy's
decoding was 3.6 s of an 8 s recording's workflow) must read what rclpy reads, field for field and bit for
bit, whatever the strings' lengths do to the alignment; what they cannot parse is left to rclpy."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from geometry_msgs.msg import Quaternion, Vector3
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Imu, JointState

from tal_core.robot_description import load_robot_description
from tal_msgs.msg import ContactState, JointCommand
from tal_sim2real import cdr
from tal_sim2real.hidden_effects import generate_hidden
from tal_sim2real.measured import load_measured

RNG = np.random.default_rng(7)


def _stamp(msg, sec: int, nanosec: int, frame: str) -> None:
    msg.header.stamp.sec = sec
    msg.header.stamp.nanosec = nanosec
    msg.header.frame_id = frame


@pytest.mark.parametrize("frame", ["", "b", "base", "base_lnk", "wörld_frame_9"])
@pytest.mark.parametrize("with_effort", [True, False])
def test_joint_states_read_as_rclpy_reads_them(frame: str, with_effort: bool) -> None:
    msg = JointState()
    _stamp(msg, 12, 345_678_901, frame)
    msg.name = ["lf_haa_joint", "a", "rf_kfe", "xy", "lh_hfe_joint_long_name"]
    msg.position = RNG.normal(size=5).tolist()
    msg.velocity = RNG.normal(size=5).tolist()
    msg.effort = RNG.normal(size=5).tolist() if with_effort else []
    data = serialize_message(msg)
    fast, slow = cdr.decode("sensor_msgs/msg/JointState", data), deserialize_message(data, JointState)
    assert (fast.header.stamp.sec, fast.header.stamp.nanosec, fast.header.frame_id) == (
        slow.header.stamp.sec,
        slow.header.stamp.nanosec,
        slow.header.frame_id,
    )
    assert fast.name == list(slow.name)
    for field in ("position", "velocity", "effort"):
        np.testing.assert_array_equal(getattr(fast, field), np.asarray(getattr(slow, field), dtype=float))
    assert len(fast.effort) == len(slow.effort)


@pytest.mark.parametrize("frame", ["", "i", "imu_lin", "imu_link", "imu_link_frame"])
def test_imu_messages_read_as_rclpy_reads_them(frame: str) -> None:
    msg = Imu()
    _stamp(msg, -3, 999_999_999, frame)
    msg.orientation = Quaternion(x=0.1, y=-0.2, z=0.3, w=math.sqrt(1 - 0.14))
    msg.angular_velocity = Vector3(x=1e-3, y=-2.5, z=math.pi)
    msg.linear_acceleration = Vector3(x=0.3, y=-0.1, z=9.81)
    msg.orientation_covariance = RNG.normal(size=9).tolist()
    data = serialize_message(msg)
    fast, slow = cdr.decode("sensor_msgs/msg/Imu", data), deserialize_message(data, Imu)
    assert fast.header.stamp == (slow.header.stamp.sec, slow.header.stamp.nanosec)
    for field in ("angular_velocity", "linear_acceleration"):
        a, b = getattr(fast, field), getattr(slow, field)
        assert (a.x, a.y, a.z) == (b.x, b.y, b.z)
    o = slow.orientation
    assert tuple(fast.orientation) == (o.x, o.y, o.z, o.w)


@pytest.mark.parametrize(("frame", "child"), [("", ""), ("odom", "base"), ("world", "base_link"), ("w", "trunk_")])
def test_odometry_reads_as_rclpy_reads_it(frame: str, child: str) -> None:
    msg = Odometry()
    _stamp(msg, 5, 1000, frame)
    msg.child_frame_id = child
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z = RNG.normal(size=3).tolist()
    q.x, q.y, q.z, q.w = (0.0, 0.6, 0.0, 0.8)
    t = msg.twist.twist
    t.linear = Vector3(x=0.2, y=-0.01, z=1e-9)
    t.angular = Vector3(x=-0.3, y=0.02, z=0.5)
    msg.pose.covariance = RNG.normal(size=36).tolist()
    msg.twist.covariance = RNG.normal(size=36).tolist()
    data = serialize_message(msg)
    fast, slow = cdr.decode("nav_msgs/msg/Odometry", data), deserialize_message(data, Odometry)
    assert fast.child_frame_id == slow.child_frame_id and fast.header.frame_id == slow.header.frame_id
    sp, sq = slow.pose.pose.position, slow.pose.pose.orientation
    assert tuple(fast.pose.pose.position) == (sp.x, sp.y, sp.z)
    assert tuple(fast.pose.pose.orientation) == (sq.x, sq.y, sq.z, sq.w)
    st = slow.twist.twist
    assert tuple(fast.twist.twist.linear) == (st.linear.x, st.linear.y, st.linear.z)
    assert tuple(fast.twist.twist.angular) == (st.angular.x, st.angular.y, st.angular.z)


@pytest.mark.parametrize("filled", [(), ("position",), ("kp", "kd"), ("position", "velocity", "kp", "kd")])
def test_joint_commands_read_as_rclpy_reads_them(filled: tuple[str, ...]) -> None:
    msg = JointCommand()
    _stamp(msg, 7, 250_000_000, "")
    msg.name = ["lf_haa_joint", "lf_hfe_joint", "rh_kfe_joint"]
    msg.effort = RNG.normal(size=3).tolist()
    for field in filled:
        setattr(msg, field, RNG.normal(size=3).tolist())
    data = serialize_message(msg)
    fast, slow = cdr.decode("tal_msgs/msg/JointCommand", data), deserialize_message(data, JointCommand)
    assert fast.header.stamp == (slow.header.stamp.sec, slow.header.stamp.nanosec)
    assert fast.name == list(slow.name)
    np.testing.assert_array_equal(fast.effort, np.asarray(slow.effort, dtype=float))


@pytest.mark.parametrize("frame", ["", "world"])
def test_contact_states_read_as_rclpy_reads_them(frame: str) -> None:
    msg = ContactState()
    _stamp(msg, 1, 2, frame)
    msg.in_contact = [True, False, False, True]
    msg.probability = [1.0, 0.0, 0.0, 1.0]
    msg.force = [Vector3(x=float(i), y=-0.5 * i, z=100.0 + i) for i in range(4)]
    msg.penetration = [1e-3, float("nan"), 0.0, 2e-3]
    data = serialize_message(msg)
    fast, slow = cdr.decode("tal_msgs/msg/ContactState", data), deserialize_message(data, ContactState)
    assert fast.header.stamp == (slow.header.stamp.sec, slow.header.stamp.nanosec)
    assert fast.in_contact == [bool(b) for b in slow.in_contact]
    assert [tuple(f) for f in fast.force] == [(f.x, f.y, f.z) for f in slow.force]


def test_what_does_not_parse_exactly_is_left_to_rclpy() -> None:
    msg = JointState()
    msg.name = ["j"]
    msg.position, msg.velocity, msg.effort = [1.0], [2.0], [3.0]
    data = serialize_message(msg)
    assert cdr.decode("sensor_msgs/msg/JointState", data) is not None
    assert cdr.decode("sensor_msgs/msg/JointState", data[:-3]) is None  # truncated
    assert cdr.decode("sensor_msgs/msg/JointState", data + b"\x00" * 4) is None  # bytes no field explains
    assert cdr.decode("sensor_msgs/msg/JointState", b"\x00\x00" + data[2:]) is None  # big-endian CDR
    assert cdr.decode("sensor_msgs/msg/Imu", data) is None  # another type's bytes
    assert cdr.decode("geometry_msgs/msg/Twist", data) is None  # not one of the decoded types
    msg.velocity, msg.effort = [], []  # the serialiser leaves 8 unused bytes at the end
    data = serialize_message(msg)
    padded = cdr.decode("sensor_msgs/msg/JointState", data)
    assert padded is not None and padded.position.tolist() == [1.0] and padded.effort.size == 0
    assert cdr.decode("sensor_msgs/msg/JointState", data + b"\x00" * 8) is None


def test_a_recording_loads_the_same_as_with_rclpy_alone(tmp_path, monkeypatch) -> None:
    bag, _ = generate_hidden(tmp_path, "short", [], seed=3, duration_s=1.0)
    description = load_robot_description("hyq")
    fast = load_measured(bag, description)
    monkeypatch.setattr(cdr, "DECODERS", {})
    slow = load_measured(bag, description)
    assert fast.rejected == slow.rejected and fast.joint_names == slow.joint_names
    for f in dataclasses.fields(fast):
        a, b = getattr(fast, f.name), getattr(slow, f.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=f.name)
    for f in dataclasses.fields(fast.base):
        a, b = getattr(fast.base, f.name), getattr(slow.base, f.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=f.name)
    assert fast.effort_nm is not None and fast.gyro_rad_s is not None and fast.contact_in is not None
