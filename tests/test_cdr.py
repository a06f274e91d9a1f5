"""Messages read and written as CDR bytes (tal_core.ros.cdr): the in-place readers give the numbers, checks and
errors of the message path they replace, and the serialised writers the content of the messages they replace."""

from __future__ import annotations

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Imu, JointState

from tal_control.locomotion import BaseState, LocomotionController
from tal_control.motion.gait import TROT
from tal_control.msg_conversions import WbcDiagnosticsWriter, wbc_diagnostics_message
from tal_core.errors import InputError
from tal_core.robot_model import RobotModel
from tal_core.ros.cdr import CdrReader, view_of
from tal_core.ros.conversions import (
    JointStateReader,
    base_state_from_odometry,
    base_state_from_odometry_view,
    canonical_joint_state,
)
from tal_core.ros.node_utils import stamp_from_ns
from tal_core.rotations import cross3, cross_rows
from tal_estimation.messages import joint_state_arrays
from tal_msgs.msg import ContactState, TerrainImpedance, WbcDiagnostics

NAMES = [f"{leg}_{joint}" for leg in ("lf", "rf", "lh", "rh") for joint in ("haa", "hfe", "kfe")]
INDEX = {name: i for i, name in enumerate(NAMES)}


def joint_state(rng: np.random.Generator, names=NAMES, stamp_ns: int = 7_004_000_000) -> JointState:
    n = len(names)
    msg = JointState(name=list(names), position=rng.normal(size=n).tolist(), velocity=rng.normal(size=n).tolist(),
                     effort=rng.normal(size=n).tolist())
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.header.frame_id = "base"
    return msg


def test_reader_gives_the_numbers_of_the_deserialised_message() -> None:
    rng = np.random.default_rng(3)
    imu = Imu()
    imu.header.frame_id = "imu_link"
    imu.header.stamp = stamp_from_ns(12_345_678_901)
    imu.linear_acceleration.x, imu.linear_acceleration.y, imu.linear_acceleration.z = rng.normal(size=3).tolist()
    imu.angular_velocity.x, imu.angular_velocity.y, imu.angular_velocity.z = rng.normal(size=3).tolist()
    view = view_of(imu)
    assert view.stamp_ns == 12_345_678_901
    assert view.vector("linear_acceleration").tolist() == [imu.linear_acceleration.x, imu.linear_acceleration.y,
                                                           imu.linear_acceleration.z]
    assert view.vector("angular_velocity")[2] == imu.angular_velocity.z

    contacts = ContactState()
    contacts.in_contact = [True, False, False, True]
    for i in range(4):
        contacts.force[i].x, contacts.force[i].y, contacts.force[i].z = rng.normal(size=3).tolist()
    view = view_of(contacts)
    assert view.array("in_contact").tolist() == [True, False, False, True]
    assert view.vectors("force").tolist() == [[f.x, f.y, f.z] for f in contacts.force]

    impedance = TerrainImpedance()
    impedance.stiffness_normal = rng.uniform(1e3, 1e5, 4).tolist()
    impedance.valid = [True, True, False, True]
    impedance.samples = [1, 2, 3, 250]
    view = view_of(impedance)
    assert view.array("stiffness_normal").tolist() == list(impedance.stiffness_normal)
    assert view.array("samples").tolist() == [1, 2, 3, 250] and view.array("valid").tolist() == list(impedance.valid)


def test_reader_learns_a_new_shape_and_keeps_the_old_one() -> None:
    rng = np.random.default_rng(4)
    reader = CdrReader(JointState)
    first, renamed = joint_state(rng), joint_state(rng, names=[n.upper() for n in NAMES])
    renamed.header.frame_id = "a_longer_frame_name"
    for msg in (first, renamed, first, renamed):
        view = reader.read(serialize_message(msg))
        assert view.array("position").tolist() == list(msg.position)
        assert view.array("effort").tolist() == list(msg.effort)
        assert list(view.message.name) == list(msg.name)
    assert reader.layouts_learnt == 2


def test_reader_refuses_bytes_it_cannot_read() -> None:
    data = serialize_message(joint_state(np.random.default_rng(5)))
    with pytest.raises(InputError):
        CdrReader(JointState).read(data[:3])
    with pytest.raises(Exception):  # noqa: B017 (rclpy's own deserialisation error, whatever its type)
        CdrReader(JointState).read(data[: len(data) // 2])


def test_joint_state_reader_checks_as_the_message_path() -> None:
    rng = np.random.default_rng(6)
    shuffled = [NAMES[i] for i in rng.permutation(len(NAMES))]
    msg = joint_state(rng, names=shuffled)
    q, qd, tau = JointStateReader(INDEX, efforts=True)(view_of(msg))
    q_ref, qd_ref, tau_ref = joint_state_arrays(msg, INDEX)
    assert np.array_equal(q, q_ref) and np.array_equal(qd, qd_ref) and np.array_equal(tau, tau_ref)
    q2, qd2, none = JointStateReader(INDEX)(view_of(msg))
    assert none is None and np.array_equal(q2, canonical_joint_state(msg, INDEX)[0])

    def errors(msg: JointState, **options) -> tuple[str, str]:
        with pytest.raises(InputError) as ours:
            JointStateReader(INDEX, efforts=True, **options)(view_of(msg))
        with pytest.raises(InputError) as theirs:
            joint_state_arrays(msg, INDEX, **options)
        return str(ours.value), str(theirs.value)

    unknown = joint_state(rng, names=NAMES[:11] + ["tail_joint"])
    missing = joint_state(rng, names=NAMES[:11])
    nan = joint_state(rng)
    nan.velocity[4] = float("nan")
    short = joint_state(rng)
    short.effort = short.effort[:5]
    for bad in (unknown, missing, nan, short):
        ours, theirs = errors(bad)
        assert ours == theirs
    no_velocities = joint_state(rng)
    no_velocities.velocity = []
    assert errors(no_velocities)[0] == errors(no_velocities)[1]
    q, qd, tau = JointStateReader(INDEX, efforts=True, velocities_optional=True)(view_of(no_velocities))
    assert qd is None and np.array_equal(q, joint_state_arrays(no_velocities, INDEX, velocities_optional=True)[0])


def test_odometry_view_gives_the_base_state_of_the_message() -> None:
    rng = np.random.default_rng(7)
    msg = Odometry(child_frame_id="base")
    msg.header.frame_id = "world"
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z = rng.normal(size=3).tolist()
    quat = rng.normal(size=4)
    o.x, o.y, o.z, o.w = (quat / np.linalg.norm(quat)).tolist()
    msg.twist.twist.linear.x, msg.twist.twist.angular.z = 0.3, -0.7
    ours, theirs = base_state_from_odometry_view(view_of(msg)), base_state_from_odometry(msg)
    for name in ("position", "quat_xyzw", "linear_velocity", "angular_velocity"):
        assert np.array_equal(getattr(ours, name), getattr(theirs, name)), name
    o.w = 3.0
    with pytest.raises(InputError, match="unit quaternion"):
        base_state_from_odometry_view(view_of(msg))
    p.x = float("nan")
    with pytest.raises(InputError, match="NaN"):
        base_state_from_odometry_view(view_of(msg))


def test_diagnostics_writer_writes_the_message_of_the_tick() -> None:
    model = RobotModel.from_name("hyq")
    controller = LocomotionController(model, TROT)
    q = np.asarray(model.description.nominal_joint_positions_rad, float)
    base = BaseState(position=np.array([0.0, 0.0, model.nominal_base_height_m]), quat_xyzw=np.array([0, 0, 0, 1.0]),
                     linear_velocity=np.zeros(3), angular_velocity=np.zeros(3))
    out = controller.tick(0.0, base, q, np.zeros(len(q)), (0.2, 0.0, 0.0))
    names = list(model.description.joint_names)
    writer = WbcDiagnosticsWriter(names)
    for mode in (WbcDiagnostics.MODE_NORMAL, WbcDiagnostics.MODE_FALLBACK):
        ours = deserialize_message(writer(4_000_000, mode, "rigid", 3, 1, out), WbcDiagnostics)
        theirs = wbc_diagnostics_message(stamp_from_ns(4_000_000), mode, "rigid", 3, 1, out=out, joint_names=names)
        assert ours == theirs


def test_cross_products_are_numpys() -> None:
    rng = np.random.default_rng(8)
    a, b = rng.normal(size=3), rng.normal(size=3)
    assert np.array_equal(cross3(a, b), np.cross(a, b))
    rows_a, rows_b = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    assert np.array_equal(cross_rows(rows_a, rows_b), np.cross(rows_a, rows_b))
    assert np.array_equal(cross_rows(a[None, :], rows_b), np.cross(a[None, :], rows_b))


def test_bridge_heightmap_bytes_are_the_message() -> None:
    from tal_core.heightmap import HeightMapGrid
    from tal_msgs.msg import HeightMap
    from tal_sim_bridge.sensor_messages import SensorWriters, heightmap_message

    writers = SensorWriters(NAMES, 0.0, 0.0)
    for rows, cols in ((5, 7), (3, 3), (5, 7)):
        heights = np.random.default_rng(rows).normal(size=(rows, cols)).astype(np.float32)
        heights[0, 1] = np.nan  # unknown cells stay NaN
        grid = HeightMapGrid(center_xy=(1.25, -0.5), yaw=0.3, resolution_m=0.02, heights=heights)
        ours = deserialize_message(writers.heightmap(1_050_000_000, grid), HeightMap)
        theirs = heightmap_message(stamp_from_ns(1_050_000_000), grid)
        assert np.array_equal(np.asarray(ours.heights), np.asarray(theirs.heights), equal_nan=True)
        ours.heights, theirs.heights = [], []
        assert ours == theirs


def test_bullet_client_keeps_its_functions_until_disconnected() -> None:
    from tal_sim_bridge._pybullet import BulletClient, pybullet

    client = BulletClient(connection_mode=pybullet.DIRECT)
    assert client.getNumBodies() == 0 and "getNumBodies" in client.__dict__
    client.disconnect()
    assert "getNumBodies" not in client.__dict__
    with pytest.raises(pybullet.error):
        client.getNumBodies()
