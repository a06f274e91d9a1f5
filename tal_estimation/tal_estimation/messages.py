"""Message conversions of the estimation nodes: joint states in (shared with the offline replay of a bag), and
their outputs written as serialised bytes (``tal_core.ros.cdr``: no Python message built per tick)."""

from __future__ import annotations

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import JointState

from tal_core.errors import InputError
from tal_core.ros.cdr import CdrTemplate
from tal_core.ros.conversions import canonical_joint_arrays, joint_layout
from tal_core.rotations import quat_xyzw_from_rotation
from tal_msgs.msg import ContactState, TerrainImpedance

from .state_estimator import StateEstimate
from .streaming import JointArrays
from .tce_driver import TceTick


def joint_state_arrays(msg: JointState, index: dict[str, int], *, velocities_optional: bool = False,
                       efforts_optional: bool = False) -> JointArrays:
    """Positions [rad], velocities [rad/s] and efforts (measured torques) [N m] of a joint state in canonical
    order; InputError when a joint is unknown or missing, a length differs from the names' or a value is not
    finite. A message without velocities (or efforts), an empty list, gives None for them when
    ``velocities_optional`` (``efforts_optional``): the estimator derives the velocities and, with a sensor
    contact source, needs no torques. Otherwise it is rejected."""
    targets, velocities, efforts = joint_layout(msg, index, velocities_optional=velocities_optional, efforts=True,
                                                efforts_optional=efforts_optional)
    return canonical_joint_arrays(len(index), targets, msg.position, msg.velocity if velocities else None,
                                  msg.effort if efforts else None)


def foot_contact_values(msg: ContactState, contact_source: str) -> np.ndarray:
    """The feet's sensor values (LF, RF, LH, RH) a sensor contact source reads from a tal_msgs/ContactState:
    ``force_sensor``: the norm of each ``force`` vector (a scalar sensor reading, raw counts or [N], put in
    the vector); ``contact_flags``: ``in_contact`` as 0/1. InputError for another source or non-finite forces."""
    if contact_source == "contact_flags":
        return np.array(msg.in_contact, dtype=float)
    if contact_source != "force_sensor":
        raise InputError(f"contact_source {contact_source!r} reads no foot contact messages")
    force = np.array([[f.x, f.y, f.z] for f in msg.force], dtype=float)
    if not np.all(np.isfinite(force)):
        raise InputError("foot contact forces have NaN/inf")
    return np.linalg.norm(force, axis=1)


class EstimateWriters:
    """The estimator's 333 Hz outputs as serialised bytes (``tal_core.ros.cdr`` templates): state_estimate
    (nav_msgs/Odometry: pose in world, twist in base as ROS has it, covariances) and contact_estimate
    (tal_msgs/ContactState)."""

    def __init__(self, gyro_variance_rad2_s2: float) -> None:
        odometry = Odometry(child_frame_id="base")
        odometry.header.frame_id = "world"
        self._odometry = CdrTemplate(odometry)
        self._gyro_variance = gyro_variance_rad2_s2
        contacts = ContactState()
        contacts.header.frame_id = "world"
        self._contacts = CdrTemplate(contacts)

    def odometry(self, stamp_ns: int, position: np.ndarray, world_R_base: np.ndarray, velocity: np.ndarray,
                 angular_velocity_base: np.ndarray, position_cov: np.ndarray, velocity_cov: np.ndarray,
                 attitude_cov: np.ndarray) -> bytes:
        t = self._odometry
        t.set_stamp(stamp_ns)
        quat = quat_xyzw_from_rotation(world_R_base)
        t.set_xyz("pose.pose.position", position)
        t.set_xyz("twist.twist.linear", world_R_base.T @ velocity)
        t.set_xyz("twist.twist.angular", angular_velocity_base)
        for axis, q in zip("xyzw", quat):
            t.field(f"pose.pose.orientation.{axis}")[0] = q
        pose_cov = t.field("pose.covariance").reshape(6, 6)
        pose_cov[:3, :3] = position_cov
        pose_cov[3:, 3:] = attitude_cov
        twist_cov = t.field("twist.covariance").reshape(6, 6)
        twist_cov[:3, :3] = world_R_base.T @ velocity_cov @ world_R_base
        twist_cov[3:, 3:] = np.eye(3) * self._gyro_variance
        return t.data()

    def contacts(self, stamp_ns: int, e: StateEstimate, normals: np.ndarray, terrain_aware: bool) -> bytes:
        legs, t = e.legs, self._contacts
        t.set_stamp(stamp_ns)
        t.field("in_contact")[:] = legs.in_contact
        t.field("probability")[:] = legs.probability
        t.field("force")[:] = legs.force
        t.field("foot_position")[:] = e.position + legs.foot_offset
        t.field("foot_velocity")[:] = e.linear_velocity - legs.leg_velocity + legs.foot_velocity
        t.field("normal")[:] = normals
        t.field("penetration")[:] = legs.penetration if terrain_aware else np.nan
        t.field("penetration_rate")[:] = (-np.einsum("ij,ij->i", legs.foot_velocity, normals) if terrain_aware
                                          else np.nan)
        return t.data()


class ImpedanceWriter:
    """The TCE's 250 Hz terrain_impedance (tal_msgs/TerrainImpedance) as serialised bytes."""

    def __init__(self) -> None:
        msg = TerrainImpedance()
        msg.header.frame_id = "world"
        self._template = CdrTemplate(msg)

    def __call__(self, stamp_ns: int, tick: TceTick) -> bytes:
        t = self._template
        t.set_stamp(stamp_ns)
        est, tangential = tick.estimates, tick.tangential
        t.field("stiffness_normal")[:] = [e.stiffness_n_per_m for e in est]
        t.field("damping_normal")[:] = [e.damping_ns_per_m for e in est]
        t.field("stiffness_tangential")[:] = ([e.stiffness_n_per_m for e in tangential] if tangential
                                              else np.nan)
        t.field("damping_tangential")[:] = [e.damping_ns_per_m for e in tangential] if tangential else np.nan
        t.field("normal")[:] = [s.normal for s in tick.samples]
        t.field("confidence")[:] = [e.confidence for e in est]
        t.field("samples")[:] = [e.samples for e in est]
        t.field("valid")[:] = [e.valid for e in est]
        t.field("rigid")[:] = [e.rigid for e in est]
        return t.data()
