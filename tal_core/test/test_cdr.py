"""CDR bytes both ways: the stamp read from serialised bytes, and a template whose fields written in the bytes
deserialise to exactly those values (every numeric field of tal's published message types)."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_msgs.msg import Point, Vector3
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Imu, JointState

from tal_core.errors import InputError
from tal_core.ros.cdr import CdrTemplate, stamp_ns_of
from tal_core.ros.node_utils import stamp_from_ns
from tal_msgs.msg import ContactState, GaitState, JointCommand, TerrainImpedance, WbcDiagnostics

NAMES = [f"{leg}_{j}_joint" for leg in ("lf", "rf", "lh", "rh") for j in ("haa", "hfe", "kfe")]


def _messages() -> list:
    gait = GaitState(gait="trot")
    gait.header.frame_id = "world"
    command = JointCommand(name=NAMES, effort=[0.0] * 12)
    full_command = JointCommand(name=NAMES, effort=[0.0] * 12, position=[0.0] * 12, velocity=[0.0] * 12,
                                kp=[0.0] * 12, kd=[0.0] * 12)
    diagnostics = WbcDiagnostics(contact_model="compliant", qp_status_text="solved", joint_names=NAMES,
                                 desired_torque=[0.0] * 12)
    odometry = Odometry(child_frame_id="base")
    odometry.header.frame_id = "world"
    return [gait, command, full_command, diagnostics, odometry,
            JointState(name=NAMES, position=[0.0] * 12, velocity=[0.0] * 12, effort=[0.0] * 12), Imu(),
            ContactState(), TerrainImpedance()]


def _leaf(msg, path: str):
    value = msg
    for part in path.replace("[", ".").replace("]", "").split("."):
        value = value[int(part)] if part.isdigit() else getattr(value, part)
    return value


@pytest.mark.parametrize("msg", _messages(), ids=lambda m: type(m).__name__)
def test_every_numeric_field_written_in_the_bytes_deserialises_to_its_value(msg) -> None:
    template = CdrTemplate(msg)
    assert template.offsets, "no numeric field found"
    rng = np.random.default_rng(7)
    expected = {}
    for path, (_, dtype, count) in template.offsets.items():
        view = template.field(path)
        if dtype == "?":
            values = rng.integers(0, 2, count).astype(bool)
        elif dtype.lstrip("<")[0] in "iu":
            values = rng.integers(0, 100, count).astype(dtype)
        else:
            values = rng.normal(size=count).astype(dtype)
        view[:] = values
        expected[path] = values
    template.set_stamp(12_345_678_901)
    decoded = deserialize_message(template.data(), type(msg))
    assert decoded.header.stamp.sec == 12 and decoded.header.stamp.nanosec == 345_678_901
    for path, values in expected.items():
        if path.startswith("header.stamp"):
            continue
        got = np.atleast_1d(np.asarray(_leaf(decoded, path)))
        np.testing.assert_array_equal(got, values, err_msg=f"{type(msg).__name__}.{path}")
    # Strings and sequence lengths are the template's own (padding bytes may differ between serialisations).
    assert len(serialize_message(decoded)) == len(template.data())
    assert deserialize_message(serialize_message(msg), type(msg)).header.frame_id == decoded.header.frame_id


def test_point_arrays_are_n_by_3_views() -> None:
    template = CdrTemplate(GaitState(gait="trot"))
    feet = template.field("target_foothold")
    assert feet.shape == (4, 3)
    feet[:] = np.arange(12.0).reshape(4, 3)
    velocity = template.field("hip_velocity")
    velocity[2] = (7.0, 8.0, 9.0)
    decoded = deserialize_message(template.data(), GaitState)
    assert decoded.target_foothold[3] == Point(x=9.0, y=10.0, z=11.0)
    assert decoded.hip_velocity[2] == Vector3(x=7.0, y=8.0, z=9.0)
    with pytest.raises(KeyError, match="no numeric field 'gait'"):
        template.field("gait")


def test_stamp_is_read_from_the_bytes() -> None:
    msg = JointState(name=NAMES, position=[0.0] * 12)
    msg.header.stamp = stamp_from_ns(3_004_000_000)
    assert stamp_ns_of(serialize_message(msg)) == 3_004_000_000
    with pytest.raises(InputError, match="too short"):
        stamp_ns_of(b"\x00\x01\x00\x00")


@pytest.mark.ros
def test_subscribe_stamped_skips_unwanted_and_reports_corrupt_samples() -> None:
    """Over DDS: only wanted stamps reach the callback; bytes that are no message go to on_error, the node
    keeps running."""
    import time

    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from tal_core.ros.cdr import subscribe_stamped

    context = rclpy.context.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("cdr_probe", context=context)
    got, errors = [], []
    subscribe_stamped(node, JointState, "cdr_test/joint_states", got.append, 50,
                      wants=lambda stamp: stamp % 4_000_000 == 0, on_error=errors.append)
    pub = node.create_publisher(JointState, "cdr_test/joint_states", 50)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        deadline = time.monotonic() + 10.0
        while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        for k in range(1, 9):
            msg = JointState(name=NAMES, position=[float(k)] * 12)
            msg.header.stamp = stamp_from_ns(k * 1_000_000)
            pub.publish(msg)
        pub.publish(b"\x00\x01\x00\x00")  # an encapsulation header and nothing else
        while (len(got) < 2 or not errors) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
    assert [m.position[0] for m in got] == [4.0, 8.0]
    assert len(errors) == 1 and "too short" in str(errors[0])
