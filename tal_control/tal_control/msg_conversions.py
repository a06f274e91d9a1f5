"""ROS messages of tal_control's outputs (used by the wbc node only)."""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Point, Vector3

from tal_msgs.msg import GaitState

from .locomotion import TickOutput


def _point(xyz: np.ndarray) -> Point:
    return Point(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))


def gait_state_message(out: TickOutput, stamp) -> GaitState:
    """tal_msgs/GaitState of one tick."""
    targets, phase = out.targets, out.targets.gait
    msg = GaitState()
    msg.header.stamp = stamp
    msg.header.frame_id = "world"
    msg.gait = phase.gait.name
    msg.step_frequency = float(phase.gait.step_frequency_hz)
    msg.duty_factor = float(phase.gait.duty_factor)
    msg.step_height = float(phase.gait.step_height_m)
    msg.swing_duration = float(np.max(phase.swing_duration_s))
    velocity = targets.trunk.command_velocity_world
    yaw = float(targets.trunk.rpy[2])
    c, s = np.cos(yaw), np.sin(yaw)
    msg.base_twist.linear = Vector3(x=float(c * velocity[0] + s * velocity[1]),
                                    y=float(-s * velocity[0] + c * velocity[1]), z=0.0)
    msg.base_twist.angular = Vector3(x=0.0, y=0.0, z=float(targets.trunk.command_yaw_rate))
    for leg in range(4):
        msg.phase[leg] = float(phase.phase[leg])
        msg.swing[leg] = bool(phase.swing[leg])
        msg.swing_progress[leg] = float(phase.swing_progress[leg]) if phase.swing[leg] else 0.0
        msg.time_to_touchdown[leg] = float(phase.time_to_touchdown_s[leg])
        liftoff = float(phase.time_to_liftoff_s[leg])
        msg.time_to_liftoff[leg] = liftoff if np.isfinite(liftoff) else -1.0
        msg.step_count[leg] = int(phase.step_count[leg])
        msg.liftoff_position[leg] = _point(targets.liftoff_positions[leg])
        msg.nominal_foothold[leg] = _point(targets.nominal_footholds[leg])
        msg.target_foothold[leg] = _point(targets.target_footholds[leg])
        msg.hip_position[leg] = _point(targets.hip_positions[leg])
    for leg, velocity in enumerate(targets.hip_velocities()):
        msg.hip_velocity[leg] = Vector3(x=float(velocity[0]), y=float(velocity[1]), z=float(velocity[2]))
    return msg
