"""Joint PD hold of the nominal standing pose with gravity-compensating feed-forward torques.

The simplest controller that makes a quadruped stand: it is what ``make run`` uses before the
whole-body controller exists, and the trivial controller of the bridge benchmarks. The feed-forward
torque assumes a level trunk at the measured joint angles with all feet on the ground and the weight
shared so that the centre of mass is balanced (no moment about it):
    tau_ff = h_j - sum_i J_i,j^T F_i    (actuated rows of M qdd + h = S^T tau + J^T F at rest)
"""

from __future__ import annotations

import numpy as np

from tal_core.errors import InputError
from tal_core.legs import LEGS, NUM_LEGS
from tal_core.robot_model import RobotModel

GRAVITY_M_S2 = 9.81


def balanced_vertical_forces(foot_xy: np.ndarray, com_xy: np.ndarray, weight_n: float) -> np.ndarray:
    """Minimum-norm vertical foot forces [N] (4,) that carry ``weight_n`` with zero moment about the CoM.

    foot_xy (4, 2) and com_xy (2,) in the world frame [m]. Solves sum f = W, sum f (p - c) = 0.
    """
    relative = np.asarray(foot_xy, dtype=float) - np.asarray(com_xy, dtype=float)
    A = np.vstack([np.ones(NUM_LEGS), relative[:, 0], relative[:, 1]])
    b = np.array([weight_n, 0.0, 0.0])
    forces, *_ = np.linalg.lstsq(A, b, rcond=None)
    return forces


class StandHold:
    """Computes joint torques that hold the nominal standing pose."""

    def __init__(self, model: RobotModel, kp_nm_per_rad: float, kd_nms_per_rad: float,
                 base_height_m: float | None = None) -> None:
        if kp_nm_per_rad < 0.0 or kd_nms_per_rad < 0.0:
            raise InputError(f"PD gains must be >= 0, got kp={kp_nm_per_rad}, kd={kd_nms_per_rad}")
        self.model = model
        self.kp = float(kp_nm_per_rad)
        self.kd = float(kd_nms_per_rad)
        self.target_rad = model.description.nominal_joint_positions_rad.copy()
        self.base_height_m = float(model.neutral_q()[2] if base_height_m is None else base_height_m)
        self._joint_v = model.canonical_joint_v_indices()
        self.weight_n = model.total_mass_kg * GRAVITY_M_S2

    def feed_forward(self, joint_positions_rad: np.ndarray) -> np.ndarray:
        """Gravity-compensating torques [N m] (12,) at the given joint angles, level trunk, 4 feet down."""
        q = self.model.make_q([0.0, 0.0, self.base_height_m], [0.0, 0.0, 0.0, 1.0], joint_positions_rad)
        v = np.zeros(self.model.nv)
        self.model.update(q, v)
        feet = self.model.foot_positions()
        vertical = balanced_vertical_forces(feet[:, :2], self.model.com()[:2], self.weight_n)
        tau_v = self.model.nonlinear_effects().copy()
        for leg, f_z in zip(LEGS, vertical):
            tau_v -= self.model.foot_jacobian(leg).T @ np.array([0.0, 0.0, f_z])
        return tau_v[self._joint_v]

    def command(self, joint_positions_rad: np.ndarray) -> dict[str, np.ndarray]:
        """Joint command fields in canonical order: effort [N m], position [rad], velocity, kp, kd."""
        q = np.asarray(joint_positions_rad, dtype=float)
        if q.shape != self.target_rad.shape or not np.all(np.isfinite(q)):
            raise InputError(f"expected {self.target_rad.size} finite joint positions, got {q}")
        n = self.target_rad.size
        return {
            "effort": self.feed_forward(q),
            "position": self.target_rad.copy(),
            "velocity": np.zeros(n),
            "kp": np.full(n, self.kp),
            "kd": np.full(n, self.kd),
        }
