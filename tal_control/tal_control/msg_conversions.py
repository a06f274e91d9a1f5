"""ROS messages of tal_control's outputs (used by the wbc node only).

The 250 Hz outputs (GaitState, JointCommand) are written into serialised templates (``tal_core.ros.cdr``):
building and converting the Python messages was about a third of the wbc's CPU in the lockstep tour
(py-spy: ``Publisher.publish`` 26 % self, ``gait_state_message`` 7.6 %).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from geometry_msgs.msg import Vector3

from tal_core.ros.cdr import CdrTemplate
from tal_msgs.msg import GaitState, JointCommand, WbcDiagnostics

from .locomotion import TickOutput
from .wbc.tasks import orientation_error


class GaitStateWriter:
    """tal_msgs/GaitState of a tick as serialised bytes: one ``CdrTemplate`` per gait name (the only string
    that changes), the tick's numbers written into it."""

    def __init__(self) -> None:
        self._templates: dict[str, CdrTemplate] = {}

    def __call__(self, out: TickOutput, stamp_ns: int) -> bytes:
        targets, phase = out.targets, out.targets.gait
        name = phase.gait.name
        t = self._templates.get(name)
        if t is None:
            msg = GaitState(gait=name)
            msg.header.frame_id = "world"
            t = self._templates[name] = CdrTemplate(msg)
        t.set_stamp(stamp_ns)
        t.field("step_frequency")[0] = phase.gait.step_frequency_hz
        t.field("duty_factor")[0] = phase.gait.duty_factor
        t.field("step_height")[0] = phase.gait.step_height_m
        t.field("swing_duration")[0] = np.max(phase.swing_duration_s)
        velocity = targets.trunk.command_velocity_world
        yaw = float(targets.trunk.rpy[2])
        c, s = np.cos(yaw), np.sin(yaw)
        t.field("base_twist.linear.x")[0] = c * velocity[0] + s * velocity[1]
        t.field("base_twist.linear.y")[0] = -s * velocity[0] + c * velocity[1]
        t.field("base_twist.angular.z")[0] = targets.trunk.command_yaw_rate
        swing = np.asarray(phase.swing, bool)
        t.field("phase")[:] = phase.phase
        t.field("swing")[:] = swing
        t.field("swing_progress")[:] = np.where(swing, phase.swing_progress, 0.0)
        t.field("time_to_touchdown")[:] = phase.time_to_touchdown_s
        liftoff = np.asarray(phase.time_to_liftoff_s, float)
        t.field("time_to_liftoff")[:] = np.where(np.isfinite(liftoff), liftoff, -1.0)
        t.field("step_count")[:] = phase.step_count
        t.field("liftoff_position")[:] = targets.liftoff_positions
        t.field("nominal_foothold")[:] = targets.nominal_footholds
        t.field("target_foothold")[:] = targets.target_footholds
        t.field("hip_position")[:] = targets.hip_positions
        t.field("hip_velocity")[:] = targets.hip_velocities()
        return t.data()


class JointCommandWriter:
    """tal_msgs/JointCommand as serialised bytes for fixed joint names: a torque-only template and one with
    velocity targets and damping (safe mode)."""

    def __init__(self, joint_names: Sequence[str]) -> None:
        n = len(joint_names)
        names = list(joint_names)
        self._effort = CdrTemplate(JointCommand(name=names, effort=[0.0] * n))
        self._damped = CdrTemplate(JointCommand(name=names, effort=[0.0] * n, velocity=[0.0] * n, kd=[0.0] * n))

    def __call__(self, stamp_ns: int, effort: np.ndarray, velocity: np.ndarray | None = None,
                 kd: np.ndarray | None = None) -> bytes:
        t = self._effort if kd is None else self._damped
        t.set_stamp(stamp_ns)
        t.field("effort")[:] = effort
        if kd is not None:
            t.field("velocity")[:] = 0.0 if velocity is None else velocity
            t.field("kd")[:] = kd
        return t.data()


class WbcDiagnosticsWriter:
    """tal_msgs/WbcDiagnostics of a solved tick as serialised bytes, the same content as
    ``wbc_diagnostics_message(..., out=out)``: one ``CdrTemplate`` per (solver status text, contact model), the
    only strings that change for fixed joint names."""

    def __init__(self, joint_names: Sequence[str]) -> None:
        self.joint_names = list(joint_names)
        self._templates: dict[tuple[str, str], CdrTemplate] = {}

    def __call__(self, stamp_ns: int, mode: int, contact_model: str, rejected_inputs: int, failed_qps: int,
                 out: TickOutput) -> bytes:
        sol = out.solution
        key = (sol.status, contact_model)
        t = self._templates.get(key)
        if t is None:
            msg = WbcDiagnostics(contact_model=contact_model, qp_status_text=sol.status,
                                 joint_names=self.joint_names, desired_torque=[0.0] * len(self.joint_names))
            msg.header.frame_id = "world"
            t = self._templates[key] = CdrTemplate(msg)
        t.set_stamp(stamp_ns)
        t.field("mode")[0] = mode
        t.field("rejected_inputs")[0] = rejected_inputs
        t.field("failed_qps")[0] = failed_qps
        t.field("qp_status")[0] = sol.status_val
        t.field("qp_iterations")[0] = sol.iterations
        t.field("qp_solve_time")[0] = sol.solve_time_s
        t.field("cycle_time")[0] = sol.cycle_time_s
        t.field("slack_norm")[0] = sol.slack_norm
        t.field("stance")[:] = np.asarray(out.targets.stance, bool)
        t.field("desired_force")[:] = sol.forces
        penetration = t.field("desired_penetration")
        if "penetration" in sol.extras:
            penetration[:] = [float(out.targets.normals[leg] @ sol.extras["penetration"][leg]) for leg in range(4)]
        else:
            penetration[:] = 0.0
        w = sol.desired_wrench
        t.set_xyz("desired_com_wrench.force", w[:3])
        t.set_xyz("desired_com_wrench.torque", w[3:6])
        t.set_xyz("com_position_error", out.targets.trunk.com_position - out.measured.com)
        t.set_xyz("orientation_error", orientation_error(out.targets.trunk.world_R_base, out.measured.world_R_base()))
        t.field("desired_torque")[:] = sol.tau
        return t.data()


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
