"""ROS messages of tal_control's outputs (used by the wbc node only)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from geometry_msgs.msg import Point, Vector3

from tal_msgs.msg import GaitState, WbcDiagnostics

from .locomotion import TickOutput
from .wbc.tasks import orientation_error


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


def wbc_diagnostics_message(stamp, mode: int, contact_model: str, rejected_inputs: int, failed_qps: int,
                            out: TickOutput | None = None, joint_names: Sequence[str] = (),
                            reason: str = "") -> WbcDiagnostics:
    """tal_msgs/WbcDiagnostics of one tick: with ``out`` the QP's solution (torques in the order of
    ``joint_names``) and tracking errors, without it (a safe-mode command) only the mode and ``reason``."""
    diag = WbcDiagnostics()
    diag.header.stamp = stamp
    diag.header.frame_id = "world"
    diag.mode = mode
    diag.contact_model = contact_model
    diag.rejected_inputs = rejected_inputs
    diag.failed_qps = failed_qps
    if out is None:
        diag.qp_status_text = reason
        return diag
    sol = out.solution
    diag.qp_status = sol.status_val
    diag.qp_status_text = sol.status
    diag.qp_iterations = sol.iterations
    diag.qp_solve_time = sol.solve_time_s
    diag.cycle_time = sol.cycle_time_s
    diag.slack_norm = sol.slack_norm
    for leg in range(4):
        diag.stance[leg] = bool(out.targets.stance[leg])
        f = sol.forces[leg]
        diag.desired_force[leg] = Vector3(x=float(f[0]), y=float(f[1]), z=float(f[2]))
        if "penetration" in sol.extras:
            diag.desired_penetration[leg] = float(out.targets.normals[leg] @ sol.extras["penetration"][leg])
    w = sol.desired_wrench
    diag.desired_com_wrench.force = Vector3(x=float(w[0]), y=float(w[1]), z=float(w[2]))
    diag.desired_com_wrench.torque = Vector3(x=float(w[3]), y=float(w[4]), z=float(w[5]))
    e = out.targets.trunk.com_position - out.measured.com
    diag.com_position_error = Vector3(x=float(e[0]), y=float(e[1]), z=float(e[2]))
    r = orientation_error(out.targets.trunk.world_R_base, out.measured.world_R_base())
    diag.orientation_error = Vector3(x=float(r[0]), y=float(r[1]), z=float(r[2]))
    diag.joint_names = list(joint_names)
    diag.desired_torque = sol.tau.tolist()
    return diag
