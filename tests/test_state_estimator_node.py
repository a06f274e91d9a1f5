"""The state_estimator node in a real rclpy graph: it ticks at 333 Hz on the sample stamps, publishes
Odometry and ContactState, and rejects (and counts) bad input without stopping: NaN and saturated IMU
samples, missing and unknown joints, stamps going backwards; a long gap re-initialises the velocity."""

from __future__ import annotations

import math
from contextlib import contextmanager

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu, JointState

from tal_core.robot_model import RobotModel
from tal_core.ros.node_utils import ns_from_stamp, stamp_from_ns
from tal_estimation.state_estimator_node import StateEstimatorNode
from tal_msgs.msg import ContactState

pytestmark = pytest.mark.ros

MS = 1_000_000  # [ns]


class FakeRobot:
    """A standing HyQ: joint states (torques holding its weight), IMU at rest, one ground-truth pose."""

    def __init__(self, context) -> None:
        self.node = rclpy.create_node("fake_robot", context=context)
        self.model = RobotModel.from_name("hyq")
        self.joints = self.node.create_publisher(JointState, "joint_states", 100)
        self.imu = self.node.create_publisher(Imu, "imu", 100)
        self.truth = self.node.create_publisher(Odometry, "ground_truth/odom", 10)
        self.estimates: list[Odometry] = []
        self.contacts: list[ContactState] = []
        self.diagnostics: list[DiagnosticArray] = []
        self.node.create_subscription(Odometry, "state_estimate", self.estimates.append, 100)
        self.node.create_subscription(ContactState, "contact_estimate", self.contacts.append, 100)
        self.node.create_subscription(DiagnosticArray, "state_estimator/diagnostics", self.diagnostics.append, 10)
        self.names = list(self.model.description.joint_names)
        self.q = self.model.description.nominal_joint_positions_rad.copy()
        self.base_z = float(self.model.neutral_q()[2])
        self.model.update(self.model.neutral_q(), np.zeros(self.model.nv))
        h = self.model.nonlinear_effects()
        weight = np.array([0.0, 0.0, self.model.total_mass_kg * 9.81 / 4.0])
        self.tau = np.concatenate([h[self.model.leg_joint_v_indices(leg)]
                                   + self.model.leg_torques_for_foot_force(leg, weight) for leg in range(4)])

    def matched(self) -> bool:
        return (self.joints.get_subscription_count() >= 1 and self.imu.get_subscription_count() >= 1
                and self.node.count_publishers("state_estimate") >= 1)

    def publish_truth(self, stamp_ns: int) -> None:
        msg = Odometry()
        msg.header.stamp = stamp_from_ns(stamp_ns)
        msg.pose.pose.position.z = self.base_z
        msg.pose.pose.orientation.w = 1.0
        self.truth.publish(msg)

    def publish_joints(self, stamp_ns: int, names: list[str] | None = None) -> None:
        names = self.names if names is None else names
        msg = JointState(name=names, position=[float(v) for v in self.q[:len(names)]],
                         velocity=[0.0] * len(names), effort=[float(v) for v in self.tau[:len(names)]])
        msg.header.stamp = stamp_from_ns(stamp_ns)
        self.joints.publish(msg)

    def publish_imu(self, stamp_ns: int, specific_force=(0.0, 0.0, 9.81)) -> None:
        msg = Imu()
        msg.header.stamp = stamp_from_ns(stamp_ns)
        msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = specific_force
        self.imu.publish(msg)

    def sample(self, stamp_ns: int) -> None:
        self.publish_joints(stamp_ns)
        self.publish_imu(stamp_ns)


def test_ticks_at_333_hz_and_survives_bad_input(context, spin_until) -> None:
    estimator = StateEstimatorNode(context=context, parameter_overrides=[Parameter("max_gap_periods", value=10)])
    robot = FakeRobot(context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(estimator)
    executor.add_node(robot.node)

    def stamps() -> list[int]:
        return [ns_from_stamp(m.header.stamp) for m in robot.estimates]

    try:
        assert spin_until(executor, robot.matched, 20.0)
        robot.publish_truth(0)
        spin_until(executor, lambda: estimator.stream.has_initial_pose, 5.0)
        for k in range(0, 7):  # 0..6 ms: the initial estimate at 0, ticks at 3 and 6 ms
            robot.sample(k * MS)
        assert spin_until(executor, lambda: stamps()[-1:] == [6 * MS] and len(robot.contacts) == 2, 10.0), stamps()
        assert stamps() == [0, 3 * MS, 6 * MS]
        assert [ns_from_stamp(c.header.stamp) for c in robot.contacts] == [3 * MS, 6 * MS]
        assert all(robot.contacts[-1].in_contact)  # standing: every foot carries a quarter of the weight
        assert sum(f.z for f in robot.contacts[-1].force) == pytest.approx(86.77 * 9.81, rel=0.02)
        assert robot.estimates[-1].pose.pose.position.z == pytest.approx(robot.base_z, abs=1e-3)

        # Bad IMU samples at 7 and 8 ms (NaN, saturated), a good one at 9 ms: the tick at 9 ms runs on it.
        robot.publish_joints(7 * MS)
        robot.publish_imu(7 * MS, (math.nan, 0.0, 9.81))
        robot.publish_joints(8 * MS)
        robot.publish_imu(8 * MS, (0.0, 0.0, 500.0))
        robot.sample(9 * MS)
        assert spin_until(executor, lambda: stamps()[-1] == 9 * MS, 10.0)
        assert estimator.rejections["imu_nan"] == 1 and estimator.rejections["imu_saturated"] == 1

        # A joint state without one joint, one with an unknown joint, then the IMU sample going backwards.
        robot.publish_joints(12 * MS, names=robot.names[:11])
        robot.publish_joints(12 * MS, names=robot.names[:11] + ["no_such_joint"])
        robot.publish_imu(12 * MS)
        robot.publish_imu(11 * MS)
        assert spin_until(executor, lambda: estimator.rejections["joints"] == 2
                          and estimator.rejections["imu_out_of_order"] == 1, 10.0), estimator.rejections
        robot.sample(13 * MS)
        robot.sample(14 * MS)
        robot.sample(15 * MS)
        assert spin_until(executor, lambda: stamps()[-1] == 15 * MS, 10.0), stamps()
        # The 12 ms grid point had no valid joint state: the next sample (13 ms) took it, then 15 ms.
        assert stamps()[-3:] == [9 * MS, 13 * MS, 15 * MS]

        # A gap of 50 ms (> 10 periods of 3 ms): the velocity filter re-initialises, estimates stay finite.
        for k in range(65, 70):
            robot.sample(k * MS)
        assert spin_until(executor, lambda: stamps()[-1] == 69 * MS, 10.0), stamps()
        assert stamps()[-3:] == [65 * MS, 66 * MS, 69 * MS]  # back on the grid k * 3 ms after the gap
        assert estimator.estimator.reinitialisations == 1
        last = robot.estimates[-1]
        values = [last.pose.pose.position.x, last.pose.pose.position.y, last.pose.pose.position.z,
                  last.twist.twist.linear.x, last.twist.twist.linear.y, last.twist.twist.linear.z]
        assert all(math.isfinite(v) for v in values)
        assert abs(last.pose.pose.position.z - robot.base_z) < 0.01
        summary = estimator.summary()
        assert summary["rejected"] == {"imu_nan": 1, "imu_saturated": 1, "joints": 2, "imu_out_of_order": 1}
        assert summary["reinitialisations"] == 1 and summary["restarts"] == 0
    finally:
        executor.shutdown()
        estimator.destroy_node()
        robot.node.destroy_node()


@contextmanager
def standing_graph(context, spin_until, *overrides: Parameter):
    """A state_estimator (standing start, ``overrides``) and a FakeRobot on one executor, matched; yields
    (estimator, robot, executor) and tears them down."""
    estimator = StateEstimatorNode(context=context, parameter_overrides=[
        Parameter("initial_pose_source", value="standing"), *overrides])
    robot = FakeRobot(context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(estimator)
    executor.add_node(robot.node)
    try:
        assert spin_until(executor, robot.matched, 20.0)
        yield estimator, robot, executor
    finally:
        executor.shutdown()
        estimator.destroy_node()
        robot.node.destroy_node()


def test_clock_jumping_back_restarts_the_estimator(context, spin_until) -> None:
    with standing_graph(context, spin_until) as (estimator, robot, executor):
        for k in range(2000, 2007):
            robot.sample(k * MS)
        assert spin_until(executor, lambda: len(robot.estimates) >= 3, 10.0)
        # Standing start: the height comes from the legs, feet on z = 0.
        assert robot.estimates[0].pose.pose.position.z == pytest.approx(robot.base_z, abs=1e-6)
        for k in range(0, 4):  # the simulation restarted at t = 0
            robot.sample(k * MS)
        assert spin_until(executor, lambda: ns_from_stamp(robot.estimates[-1].header.stamp) == 3 * MS, 10.0)
        assert estimator.restarts == 1


def test_the_rigid_odometry_does_not_wait_for_an_impedance_it_does_not_read(context, spin_until) -> None:
    """make run sets impedance_period_s for the lockstep tour; with the rigid odometry (LEG_ODOMETRY=rigid) the
    node does not subscribe to terrain_impedance, so no tick may wait for it (a tour on the estimate stalled at
    1.1 s, a lockstep timeout per tick, when each tick waited for the next grid sample)."""
    with standing_graph(context, spin_until, Parameter("leg_odometry", value="rigid"),
                        Parameter("impedance_period_s", value=0.004),
                        Parameter("impedance_max_defer_s", value=0.004)) as (estimator, robot, executor):
        for k in range(2000, 2020):
            robot.sample(k * MS)
        # The last grid sample's tick (2019 ms) is published without a later sample to release it.
        assert spin_until(executor, lambda: robot.estimates and ns_from_stamp(robot.estimates[-1].header.stamp)
                          == 2019 * MS, 10.0), [ns_from_stamp(e.header.stamp) for e in robot.estimates]
        assert estimator.stream.late_impedance_ticks == 0


def test_invalid_parameters_are_refused_at_start_up(context) -> None:
    with pytest.raises(ValueError, match="leg_odometry"):
        StateEstimatorNode(context=context, parameter_overrides=[Parameter("leg_odometry", value="magic")])
    with pytest.raises(ValueError, match="period_s"):
        StateEstimatorNode(context=context, parameter_overrides=[Parameter("period_s", value=-1.0)])


def test_a_robot_with_foot_force_sensors_and_no_joint_velocities_or_efforts(context, spin_until) -> None:
    """contact_source force_sensor: joint states with positions only, foot forces on foot_contacts (raw counts,
    calibrated per leg): the node ticks, derives the velocities, rejects nothing and reports the feet in
    contact. With the defaults such joint states are rejected."""
    weight_share = RobotModel.from_name("hyq").total_mass_kg * 9.81 / 4.0
    estimator = StateEstimatorNode(context=context, parameter_overrides=[
        Parameter("initial_pose_source", value="standing"), Parameter("contact_source", value="force_sensor"),
        Parameter("joint_velocities_optional", value=True),
        Parameter("foot_force_scale", value=[0.5, 0.5, 0.5, 0.5]),
        Parameter("foot_force_offset", value=[30.0, 30.0, 30.0, 30.0])])
    robot = FakeRobot(context)
    feet = robot.node.create_publisher(ContactState, "foot_contacts", 100)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(estimator)
    executor.add_node(robot.node)
    try:
        assert spin_until(executor, lambda: robot.matched() and feet.get_subscription_count() >= 1, 20.0)
        for k in range(0, 20):
            stamp = k * 2 * MS
            joints = JointState(name=robot.names, position=[float(v) for v in robot.q])
            joints.header.stamp = stamp_from_ns(stamp)
            robot.joints.publish(joints)
            robot.publish_imu(stamp)
            contact = ContactState()
            contact.header.stamp = stamp_from_ns(stamp)
            for force in contact.force:
                force.z = weight_share / 0.5 + 30.0
            feet.publish(contact)
        assert spin_until(executor, lambda: estimator.ticks >= 10 and len(robot.contacts) >= 5, 10.0)
        assert not estimator.rejections and estimator.stream.deriving_velocities
        assert all(robot.contacts[-1].in_contact)
    finally:
        executor.shutdown()
        estimator.destroy_node()
        robot.node.destroy_node()
