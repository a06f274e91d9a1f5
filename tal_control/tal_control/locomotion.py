"""One control tick of the locomotion stack without ROS: motion generation, then the sWBC, then torques.

``LocomotionController.tick`` is what the ``wbc`` node calls at 250 Hz and what the offline experiments
call in a closed loop with the simulator. Its inputs are the base state (world frame) and the joint
state in the robot's canonical order; its output the joint torques plus everything the diagnostics and
the gait_state message report.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from tal_core.errors import InputError
from tal_core.robot_model import RobotModel

from .motion.gait import GaitParameters
from .motion.generator import MeasuredState, MotionGenerator, MotionTargets
from .wbc import StandardWbc, WbcGains, WbcReferences, WbcSettings, WbcSolution

HeightFunction = Callable[[float, float], float]


@dataclass(frozen=True)
class BaseState:
    """Floating-base state: position [m], orientation (x, y, z, w), linear [m/s] and angular [rad/s]
    velocity, all in the world frame."""

    position: np.ndarray
    quat_xyzw: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity: np.ndarray


@dataclass(frozen=True)
class TickOutput:
    tau: np.ndarray                 # (12,) [N m] canonical joint order
    targets: MotionTargets
    solution: WbcSolution
    measured: MeasuredState


class LocomotionController:
    """Motion generator + sWBC for one robot."""

    def __init__(self, model: RobotModel, gait: GaitParameters, gains: WbcGains | None = None,
                 settings: WbcSettings | None = None, nominal_height_m: float | None = None) -> None:
        self.model = model
        self.motion = MotionGenerator(model.description, gait, nominal_height_m=nominal_height_m)
        self.wbc = StandardWbc(model, gains, settings)
        self.ticks = 0

    def tick(self, t_s: float, base: BaseState, joint_position: np.ndarray, joint_velocity: np.ndarray,
             cmd_vel: Sequence[float], terrain_height: HeightFunction | None = None,
             terrain_normal: Callable[[float, float], np.ndarray] | None = None) -> TickOutput:
        """Compute joint torques for the state at sim time ``t_s`` [s]. Raises InputError on bad input."""
        for name, value in (("joint_position", joint_position), ("joint_velocity", joint_velocity)):
            if np.shape(value) != (self.model.nv - 6,) or not np.all(np.isfinite(value)):
                raise InputError(f"{name} must be {self.model.nv - 6} finite values, got {value!r}")
        q = self.model.make_q(base.position, base.quat_xyzw, joint_position)
        v = self.model.make_v(base.linear_velocity, base.angular_velocity, joint_velocity, base.quat_xyzw)
        self.model.update(q, v)
        measured = MeasuredState(base_position=base.position, base_quat_xyzw=base.quat_xyzw,
                                 base_lin_vel=base.linear_velocity, base_ang_vel=base.angular_velocity,
                                 foot_positions=self.model.foot_positions(),
                                 foot_velocities=self.model.foot_velocities(), com=self.model.com(),
                                 com_velocity=self.model.com_velocity())
        targets = self.motion.update(t_s, measured, cmd_vel, terrain_height, terrain_normal_fn=terrain_normal)
        trunk = targets.trunk
        refs = WbcReferences(
            com_position=trunk.com_position, com_velocity=trunk.com_velocity,
            com_acceleration=trunk.com_acceleration, world_R_base=trunk.world_R_base,
            angular_velocity=trunk.angular_velocity, angular_acceleration=trunk.angular_acceleration,
            foot_position=targets.foot_position, foot_velocity=targets.foot_velocity,
            foot_acceleration=targets.foot_acceleration, stance=targets.stance,
            load_factor=targets.load_factor, touchdown_position=targets.touchdown_positions,
            normals=targets.normals)
        solution = self.wbc.solve(q, v, refs)
        self.ticks += 1
        return TickOutput(tau=solution.tau, targets=targets, solution=solution, measured=measured)
