"""Control tasks of the whole-body controller: trunk (CoM wrench) and swing/stance feet accelerations.

All vectors in the world frame. Gains are the thesis' (Fahmi 2021, sWBC results section).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from tal_core.errors import InputError
from tal_core.legs import NUM_LEGS
from tal_core.rotations import cross3

GRAVITY_M_S2 = 9.81


@dataclass(frozen=True)
class WbcGains:
    """Task gains (diagonal, same value per axis).

    Trunk task (force level): K_x [N/m], D_x [N s/m], K_theta [N m/rad], D_theta [N m s/rad].
    Swing task (acceleration level): K_sw [1/s^2], D_sw [1/s].
    Stance task (acceleration level, pulls stance feet back to their touchdown sample): K_st [1/s^2],
    D_st [1/s]; zero gains make it the plain rigid stance condition J qdd + dJ v = 0.
    """

    K_x: float = 2000.0
    D_x: float = 400.0
    K_theta: float = 1000.0
    D_theta: float = 200.0
    K_sw: float = 2000.0
    D_sw: float = 20.0
    K_st: float = 0.0
    D_st: float = 0.0

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not np.isfinite(value) or value < 0.0:
                raise InputError(f"WBC gain {name} must be a finite number >= 0, got {value!r}")


_REFERENCE_SHAPES = {
    "com_position": (3,), "com_velocity": (3,), "com_acceleration": (3,), "world_R_base": (3, 3),
    "angular_velocity": (3,), "angular_acceleration": (3,), "foot_position": (NUM_LEGS, 3),
    "foot_velocity": (NUM_LEGS, 3), "foot_acceleration": (NUM_LEGS, 3), "stance": (NUM_LEGS,),
    "load_factor": (NUM_LEGS,), "touchdown_position": (NUM_LEGS, 3), "normals": (NUM_LEGS, 3)}


@dataclass(frozen=True)
class WbcReferences:
    """What the motion generator asks of the WBC for one cycle (world frame, per-leg arrays (4, 3))."""

    com_position: np.ndarray          # [m]
    com_velocity: np.ndarray          # [m/s]
    com_acceleration: np.ndarray      # [m/s^2]
    world_R_base: np.ndarray          # (3, 3) desired trunk orientation
    angular_velocity: np.ndarray      # [rad/s]
    angular_acceleration: np.ndarray  # [rad/s^2]
    foot_position: np.ndarray         # (4, 3) [m] swing targets (stance legs: ignored)
    foot_velocity: np.ndarray         # (4, 3) [m/s]
    foot_acceleration: np.ndarray     # (4, 3) [m/s^2]
    stance: np.ndarray                # (4,) bool
    load_factor: np.ndarray           # (4,) [0, 1] scales the normal-force upper bound
    touchdown_position: np.ndarray    # (4, 3) [m] stance feet samples at touchdown (stance task)
    normals: np.ndarray               # (4, 3) unit terrain normals
    # c3WBC only: terrain impedance per leg in the contact frame (normal, tangential) [N/m], [N s/m].
    stiffness_normal: np.ndarray | None = None       # (4,)
    stiffness_tangential: np.ndarray | None = None   # (4,)
    damping_normal: np.ndarray | None = None         # (4,)
    damping_tangential: np.ndarray | None = None     # (4,)

    def __post_init__(self) -> None:
        floats = []
        for name, shape in _REFERENCE_SHAPES.items():
            value = np.asarray(getattr(self, name), dtype=bool if name == "stance" else float)
            if value.shape != shape:
                raise InputError(f"WBC reference '{name}' must have shape {shape}, got {value.shape}")
            if name != "stance":
                floats.append(value.reshape(-1))
            object.__setattr__(self, name, value)
        if not np.isfinite(np.concatenate(floats)).all():   # one check a cycle; the culprit only on failure
            bad = next(name for name in _REFERENCE_SHAPES
                       if name != "stance" and not np.all(np.isfinite(getattr(self, name))))
            raise InputError(f"WBC reference '{bad}' has NaN or inf")
        for name in ("stiffness_normal", "stiffness_tangential", "damping_normal", "damping_tangential"):
            value = getattr(self, name)
            if value is None:
                continue
            value = np.asarray(value, dtype=float)
            if value.shape != (NUM_LEGS,) or not np.all(np.isfinite(value)) or np.any(value < 0.0):
                raise InputError(f"WBC reference '{name}' must be {NUM_LEGS} finite values >= 0, got {value!r}")
            object.__setattr__(self, name, value)


def skew(vector: np.ndarray) -> np.ndarray:
    """Cross-product matrix: skew(a) @ b == cross(a, b)."""
    x, y, z = vector
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def tangent_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (t1, t2) with (t1, t2, n) right-handed; t1 follows world x where possible."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = helper - (helper @ normal) * normal
    t1 /= np.linalg.norm(t1)
    return t1, cross3(normal, t1)


def orientation_error(world_R_desired: np.ndarray, world_R_base: np.ndarray) -> np.ndarray:
    """Axis-angle error [rad], world frame, rotating the actual trunk onto the desired one."""
    return np.asarray(pin.log3(world_R_desired @ world_R_base.T))


def centroidal_wrench_map(contact_points: np.ndarray, com: np.ndarray) -> np.ndarray:
    """(6, 12) A_F with W = A_F F: the sum of the feet's forces F (4 x 3 stacked, world frame) [N] and their
    moment [N m] about ``com`` (3,) [m], applied at ``contact_points`` (4, 3) [m] (world)."""
    points = np.asarray(contact_points, dtype=float)
    if points.shape != (NUM_LEGS, 3):
        raise InputError(f"centroidal_wrench_map: contact points must be (4, 3), got {points.shape}")
    r = points - np.asarray(com, dtype=float)
    A_F = np.zeros((6, 3 * NUM_LEGS))
    A_F[0:3] = np.tile(np.eye(3), NUM_LEGS)
    zeros = np.zeros(NUM_LEGS)
    skews = np.array([[zeros, -r[:, 2], r[:, 1]], [r[:, 2], zeros, -r[:, 0]], [-r[:, 1], r[:, 0], zeros]])
    A_F[3:6] = skews.transpose(0, 2, 1).reshape(3, 3 * NUM_LEGS)
    return A_F


def desired_com_wrench(mass_kg: float, inertia_com: np.ndarray, com: np.ndarray, com_velocity: np.ndarray,
                       world_R_base: np.ndarray, angular_velocity: np.ndarray, refs: WbcReferences,
                       gains: WbcGains) -> np.ndarray:
    """W_com,d = Cartesian impedance + gravity compensation + feed-forward, [N, N m] about the CoM."""
    force = (gains.K_x * (refs.com_position - com) + gains.D_x * (refs.com_velocity - com_velocity)
             + mass_kg * np.array([0.0, 0.0, GRAVITY_M_S2]) + mass_kg * refs.com_acceleration)
    torque = (gains.K_theta * orientation_error(refs.world_R_base, world_R_base)
              + gains.D_theta * (refs.angular_velocity - angular_velocity)
              + inertia_com @ refs.angular_acceleration)
    return np.concatenate([force, torque])


def swing_accelerations(foot_position: np.ndarray, foot_velocity: np.ndarray, refs: WbcReferences,
                        gains: WbcGains) -> np.ndarray:
    """Desired foot accelerations (4, 3) [m/s^2]: swing impedance for swing legs, stance task otherwise."""
    swing = (refs.foot_acceleration + gains.K_sw * (refs.foot_position - foot_position)
             + gains.D_sw * (refs.foot_velocity - foot_velocity))
    stance = gains.K_st * (refs.touchdown_position - foot_position) - gains.D_st * foot_velocity
    return np.where(refs.stance[:, None], stance, swing)
