"""The robot-driver side of the bridge without ROS: commands in, physics stepped, sensors out.

``BridgeCore`` owns a ``Simulation``, the zero-order hold of joint commands, the IMU model, the fall detector
and the statistics for the end-of-run summary. The ROS node converts messages and decides *when* to step
(lockstep or real time); everything that decides *what* happens in a step lives here and is testable
without a ROS graph.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from tal_core.legs import LEG_NAMES
from tal_core.rotations import rotation_from_quat_xyzw

from .command_hold import JointCommandHold
from .effects import ModelEffects
from .fall import Fall, FallDetector
from .physics import GRAVITY_M_S2, FootContact, RobotState, Simulation


@dataclass
class ImuModel:
    """IMU at the base origin, axes aligned with the base frame.

    Specific force f = base_R_world (a - g) [m/s^2] and angular rate base_R_world omega [rad/s], plus the
    constant biases of ``ModelEffects`` and white noise with the given standard deviations.
    """

    effects: ModelEffects
    gyro_noise_std_rad_s: float = 0.0
    accel_noise_std_m_s2: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def measure(self, state: RobotState) -> tuple[np.ndarray, np.ndarray]:
        """Return (specific_force_base [m/s^2], angular_rate_base [rad/s])."""
        base_R_world = rotation_from_quat_xyzw(state.base_quat_xyzw).T
        gravity = np.array([0.0, 0.0, -GRAVITY_M_S2])
        specific_force = base_R_world @ (state.base_lin_acc_m_s2 - gravity)
        angular_rate = base_R_world @ state.base_ang_vel_rad_s
        specific_force = specific_force + np.asarray(self.effects.imu_accel_bias_m_s2)
        angular_rate = angular_rate + np.asarray(self.effects.imu_gyro_bias_rad_s)
        if self.accel_noise_std_m_s2 > 0.0:
            specific_force = specific_force + self._rng.normal(0.0, self.accel_noise_std_m_s2, 3)
        if self.gyro_noise_std_rad_s > 0.0:
            angular_rate = angular_rate + self._rng.normal(0.0, self.gyro_noise_std_rad_s, 3)
        return specific_force, angular_rate


class TrailingStatistics:
    """Means over the last ``window`` samples of base height, foot forces and penetrations (summary)."""

    def __init__(self, window: int) -> None:
        self.base_height: deque[float] = deque(maxlen=window)
        self.normal_force: deque[np.ndarray] = deque(maxlen=window)
        self.penetration: deque[np.ndarray] = deque(maxlen=window)
        self.stiffness: deque[np.ndarray] = deque(maxlen=window)

    def add(self, base_height_m: float, contacts: list[FootContact], stiffness_n_per_m: np.ndarray) -> None:
        self.base_height.append(base_height_m)
        self.normal_force.append(np.array([float(c.force_n @ c.normal) for c in contacts]))
        self.penetration.append(np.array([c.penetration_m for c in contacts]))
        self.stiffness.append(stiffness_n_per_m)


class BridgeCore:
    """Applies held commands to the simulation, one physics step at a time, and reports on the run."""

    def __init__(self, simulation: Simulation, *, imu: ImuModel | None = None,
                 safe_damping_nms_per_rad: float = 5.0, summary_window_steps: int = 1000,
                 fall_detector: FallDetector | None = None) -> None:
        self.sim = simulation
        self.commands = JointCommandHold(simulation.description.joint_names, safe_damping_nms_per_rad)
        self.imu = imu or ImuModel(simulation.effects)
        self.stats = TrailingStatistics(summary_window_steps)
        self.max_body_contacts: set[str] = set()
        self.fall_detector = fall_detector or FallDetector.for_robot(simulation.nominal_base_height_m)

    def step(self) -> RobotState:
        """One physics step with the held command (or joint damping if none arrived yet)."""
        q, qd = self.sim.joint_state()
        self.sim.step(self.commands.torque(q, qd), joint_state=(q, qd))
        return self.sim.robot_state()

    def record_statistics(self, state: RobotState, contacts: list[FootContact]) -> None:
        """Feed the summary statistics and the fall detector (called at the contact publishing rate)."""
        feet = np.array([c.position_m for c in contacts])
        course = self.sim.course
        stiffness = np.asarray(course.properties_array(feet[:, 0], feet[:, 1]).stiffness_n_per_m)
        base = state.base_position_m
        self.stats.add(float(base[2]), contacts, stiffness)
        body = self.sim.body_ground_contact()
        self.max_body_contacts.update(body)
        self.fall_detector.update(self.sim.time_s, base, course.height(base[0], base[1]), body)

    @property
    def fall(self) -> Fall | None:
        """The run's first confirmed fall (None: the robot is up)."""
        return self.fall_detector.fall

    def summary(self, wall_time_s: float) -> dict[str, object]:
        """End-of-run figures: base height, per-foot penetration vs the static expectation, RTF, the fall."""
        stats = self.stats
        mass = self.sim.total_mass_kg
        result: dict[str, object] = {
            "sim_time_s": round(self.sim.time_s, 6),
            "wall_time_s": round(wall_time_s, 3),
            "real_time_factor": round(self.sim.time_s / wall_time_s, 3) if wall_time_s > 0 else None,
            "course": self.sim.course.name,
            "robot": self.sim.description.name,
            "robot_mass_kg": round(mass, 3),
            "commands_accepted": self.commands.accepted,
            "commands_rejected": dict(self.commands.rejections),
            "body_ground_contact": sorted(self.max_body_contacts),
            **self.fall_detector.summary(),
        }
        if stats.base_height:
            force = np.mean(stats.normal_force, axis=0)
            penetration = np.mean(stats.penetration, axis=0)
            stiffness = np.mean(stats.stiffness, axis=0)
            in_contact = force > 1.0
            n_feet = max(int(np.sum(in_contact)), 1)
            static = mass * GRAVITY_M_S2 / (n_feet * stiffness)
            per_foot = {}
            for i, leg in enumerate(LEG_NAMES):
                from_force = force[i] / stiffness[i]
                per_foot[leg] = {
                    "normal_force_n": round(float(force[i]), 2),
                    "stiffness_n_per_m": float(stiffness[i]),
                    "penetration_m": float(penetration[i]),
                    "expected_from_force_m": float(from_force),
                    "expected_static_mg_over_nk_m": float(static[i]),
                    "error_vs_force_pct": (round(100.0 * (penetration[i] - from_force) / from_force, 3)
                                           if from_force > 0 else None),
                }
            result["base_height_m"] = round(float(np.mean(stats.base_height)), 5)
            result["feet"] = per_foot
        return result
