"""ROS messages of the simulated robot's outputs (no rclpy: message classes only).

Shared by the ``sim_bridge`` node and the offline dataset generator, so a dataset bag carries exactly what
the live bridge publishes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Twist, Vector3
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState

from tal_core.heightmap import HeightMapGrid
from tal_core.ros.cdr import CdrTemplate
from tal_core.rotations import rotation_from_quat_xyzw
from tal_msgs.msg import ContactState, HeightMap, JointCommand

from .physics import FootContact, RobotState


def joint_state_message(stamp: Time, joint_names: Sequence[str], state: RobotState) -> JointState:
    """Joint positions [rad], velocities [rad/s] and measured torques [N m] in the robot's joint order."""
    msg = JointState()
    msg.header.stamp = stamp
    msg.header.frame_id = "base"
    msg.name = list(joint_names)
    msg.position = state.joint_position_rad.tolist()
    msg.velocity = state.joint_velocity_rad_s.tolist()
    msg.effort = state.joint_torque_nm.tolist()
    return msg


def imu_message(stamp: Time, specific_force_m_s2: np.ndarray, angular_rate_rad_s: np.ndarray,
                gyro_noise_std_rad_s: float, accel_noise_std_m_s2: float) -> Imu:
    """IMU sample in the base frame; no orientation (covariance[0] = -1, the REP 145 convention)."""
    f, w = specific_force_m_s2, angular_rate_rad_s
    msg = Imu()
    msg.header.stamp = stamp
    msg.header.frame_id = "base"
    msg.orientation_covariance[0] = -1.0
    msg.angular_velocity = Vector3(x=float(w[0]), y=float(w[1]), z=float(w[2]))
    msg.linear_acceleration = Vector3(x=float(f[0]), y=float(f[1]), z=float(f[2]))
    for i in (0, 4, 8):
        msg.angular_velocity_covariance[i] = gyro_noise_std_rad_s ** 2
        msg.linear_acceleration_covariance[i] = accel_noise_std_m_s2 ** 2
    return msg


def odometry_message(stamp: Time, state: RobotState) -> Odometry:
    """Ground-truth base pose (world frame) and twist (base frame, the ROS convention for child_frame_id)."""
    msg = Odometry()
    msg.header.stamp = stamp
    msg.header.frame_id = "world"
    msg.child_frame_id = "base"
    pos, quat = state.base_position_m, state.base_quat_xyzw
    msg.pose.pose.position = Point(x=float(pos[0]), y=float(pos[1]), z=float(pos[2]))
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in quat)
    base_R_world = rotation_from_quat_xyzw(quat).T
    lin = base_R_world @ state.base_lin_vel_m_s
    ang = base_R_world @ state.base_ang_vel_rad_s
    msg.twist.twist.linear = Vector3(x=float(lin[0]), y=float(lin[1]), z=float(lin[2]))
    msg.twist.twist.angular = Vector3(x=float(ang[0]), y=float(ang[1]), z=float(ang[2]))
    return msg


def contact_state_message(stamp: Time, contacts: Sequence[FootContact]) -> ContactState:
    """True foot contacts (world frame) in the leg order LF, RF, LH, RH."""
    msg = ContactState()
    msg.header.stamp = stamp
    msg.header.frame_id = "world"
    for i, c in enumerate(contacts):
        msg.in_contact[i] = c.in_contact
        msg.probability[i] = 1.0 if c.in_contact else 0.0
        msg.force[i] = Vector3(x=float(c.force_n[0]), y=float(c.force_n[1]), z=float(c.force_n[2]))
        msg.foot_position[i] = Point(x=float(c.position_m[0]), y=float(c.position_m[1]), z=float(c.position_m[2]))
        msg.foot_velocity[i] = Vector3(x=float(c.velocity_m_s[0]), y=float(c.velocity_m_s[1]),
                                       z=float(c.velocity_m_s[2]))
        msg.normal[i] = Vector3(x=float(c.normal[0]), y=float(c.normal[1]), z=float(c.normal[2]))
        msg.penetration[i] = c.penetration_m
        msg.penetration_rate[i] = float(-(c.velocity_m_s @ c.normal)) if c.in_contact else 0.0
    return msg


def heightmap_message(stamp: Time, grid: HeightMapGrid) -> HeightMap:
    """Robot-centric heightmap (world z [m], NaN unknown) in the tal_msgs/HeightMap layout."""
    msg = HeightMap()
    msg.header.stamp = stamp
    msg.header.frame_id = "world"
    msg.center = Point(x=grid.center_xy[0], y=grid.center_xy[1], z=0.0)
    msg.yaw = grid.yaw
    msg.resolution = grid.resolution_m
    msg.rows, msg.cols = grid.rows, grid.cols
    msg.heights = np.ascontiguousarray(grid.heights, dtype=np.float32).ravel()
    return msg


def joint_command_message(stamp: Time, joint_names: Sequence[str], effort_nm: np.ndarray) -> JointCommand:
    """A torque-only joint command [N m] (what the wbc sends in normal mode)."""
    msg = JointCommand()
    msg.header.stamp = stamp
    msg.name = list(joint_names)
    msg.effort = np.asarray(effort_nm, dtype=float).tolist()
    return msg


def twist_message(vx_m_s: float, vy_m_s: float, yaw_rate_rad_s: float) -> Twist:
    """A velocity command (horizontal frame: x forward, y left; yaw rate about z)."""
    return Twist(linear=Vector3(x=float(vx_m_s), y=float(vy_m_s), z=0.0),
                 angular=Vector3(x=0.0, y=0.0, z=float(yaw_rate_rad_s)))


class SensorWriters:
    """The bridge's sensor outputs as serialised bytes, written into ``tal_core.ros.cdr`` templates: the same
    content as the message functions above (which stay for bags and tests), without building a Python
    message per sample (four messages per millisecond at 1 kHz)."""

    def __init__(self, joint_names: Sequence[str], gyro_noise_std_rad_s: float, accel_noise_std_m_s2: float) -> None:
        n = len(joint_names)
        joints = JointState(name=list(joint_names), position=[0.0] * n, velocity=[0.0] * n, effort=[0.0] * n)
        joints.header.frame_id = "base"
        self._joints = CdrTemplate(joints)
        zero = np.zeros(3)
        self._imu = CdrTemplate(imu_message(Time(), zero, zero, gyro_noise_std_rad_s, accel_noise_std_m_s2))
        odometry = Odometry(child_frame_id="base")
        odometry.header.frame_id = "world"
        self._odometry = CdrTemplate(odometry)
        contacts = ContactState()
        contacts.header.frame_id = "world"
        self._contacts = CdrTemplate(contacts)
        sensors = ContactState()
        sensors.header.frame_id = "feet"
        for field in ("foot_position", "foot_velocity", "normal"):
            for vector in getattr(sensors, field):
                vector.x = vector.y = vector.z = math.nan
        sensors.penetration = [math.nan] * 4
        sensors.penetration_rate = [math.nan] * 4
        self._foot_sensors = CdrTemplate(sensors)
        self._clock = CdrTemplate(Clock())
        self._heightmaps: dict[tuple[int, int], CdrTemplate] = {}

    def joint_state(self, stamp_ns: int, state: RobotState) -> bytes:
        t = self._joints
        t.set_stamp(stamp_ns)
        t.field("position")[:] = state.joint_position_rad
        t.field("velocity")[:] = state.joint_velocity_rad_s
        t.field("effort")[:] = state.joint_torque_nm
        return t.data()

    def imu(self, stamp_ns: int, specific_force_m_s2: np.ndarray, angular_rate_rad_s: np.ndarray) -> bytes:
        t = self._imu
        t.set_stamp(stamp_ns)
        t.set_xyz("angular_velocity", angular_rate_rad_s)
        t.set_xyz("linear_acceleration", specific_force_m_s2)
        return t.data()

    def odometry(self, stamp_ns: int, state: RobotState) -> bytes:
        t = self._odometry
        t.set_stamp(stamp_ns)
        t.set_xyz("pose.pose.position", state.base_position_m)
        for name, value in zip("xyzw", state.base_quat_xyzw):
            t.field(f"pose.pose.orientation.{name}")[0] = value
        base_R_world = rotation_from_quat_xyzw(state.base_quat_xyzw).T
        t.set_xyz("twist.twist.linear", base_R_world @ state.base_lin_vel_m_s)
        t.set_xyz("twist.twist.angular", base_R_world @ state.base_ang_vel_rad_s)
        return t.data()

    def contact_state(self, stamp_ns: int, contacts: Sequence[FootContact]) -> bytes:
        t = self._contacts
        t.set_stamp(stamp_ns)
        in_contact = np.array([c.in_contact for c in contacts], bool)
        t.field("in_contact")[:] = in_contact
        t.field("probability")[:] = in_contact
        t.field("force")[:] = [c.force_n for c in contacts]
        t.field("foot_position")[:] = [c.position_m for c in contacts]
        t.field("foot_velocity")[:] = [c.velocity_m_s for c in contacts]
        t.field("normal")[:] = [c.normal for c in contacts]
        t.field("penetration")[:] = [c.penetration_m for c in contacts]
        t.field("penetration_rate")[:] = [float(-(c.velocity_m_s @ c.normal)) if c.in_contact else 0.0
                                          for c in contacts]
        return t.data()

    def foot_sensors(self, stamp_ns: int, readings_n: np.ndarray, in_contact: np.ndarray) -> bytes:
        """Foot contact sensors (``foot_sensor.FootForceSensor``) as a ContactState: each foot's reading [N] as
        the force's z (its norm is the reading), the flags as in_contact and probability; a sensor knows no
        foot position, velocity, normal or penetration (NaN)."""
        t = self._foot_sensors
        t.set_stamp(stamp_ns)
        flags = np.asarray(in_contact, bool)
        t.field("in_contact")[:] = flags
        t.field("probability")[:] = flags
        force = np.zeros((len(flags), 3))
        force[:, 2] = readings_n
        t.field("force")[:] = force
        return t.data()

    def heightmap(self, stamp_ns: int, grid: HeightMapGrid) -> bytes:
        """``heightmap_message`` as bytes: one template per grid size (the map's shape fixes its layout)."""
        key = (grid.rows, grid.cols)
        t = self._heightmaps.get(key)
        if t is None:
            msg = HeightMap(rows=grid.rows, cols=grid.cols, heights=np.zeros(grid.rows * grid.cols, np.float32))
            msg.header.frame_id = "world"
            t = self._heightmaps[key] = CdrTemplate(msg)
        t.set_stamp(stamp_ns)
        t.field("center.x")[0], t.field("center.y")[0] = grid.center_xy
        t.field("yaw")[0] = grid.yaw
        t.field("resolution")[0] = grid.resolution_m
        t.field("heights")[:] = np.asarray(grid.heights, dtype=np.float32).ravel()
        return t.data()

    def clock(self, stamp_ns: int) -> bytes:
        t = self._clock
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        t.field("clock.sec")[0] = sec
        t.field("clock.nanosec")[0] = nanosec
        return t.data()

