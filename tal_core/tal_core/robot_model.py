"""Pinocchio-backed kinematics and dynamics of a quadruped described by a ``RobotDescription``.

Conventions (see DESIGN.md section 4):

* Configuration ``q`` (nq = 19 for a 12-joint quadruped) is Pinocchio's free-flyer layout
  ``[x, y, z, qx, qy, qz, qw, joints...]``: base position [m] in the world frame, base orientation
  ``world_R_base`` as a unit quaternion in ROS order (x, y, z, w), then joint positions [rad] in
  Pinocchio's (URDF tree) order, which may differ from ours.
* Velocity ``v`` (nv = 18) is Pinocchio's ``[base linear velocity [m/s], base angular velocity
  [rad/s], joint velocities [rad/s]]`` where BOTH base parts are expressed in the BASE frame
  (the linear part is the velocity of the base origin). ``make_v``/``split_v`` convert from/to the
  world-frame base velocities the rest of tal uses.
* Our "canonical" joint order is LF, RF, LH, RH x HAA, HFE, KFE (12 joints). Use
  ``canonical_joint_v_indices()`` / ``leg_joint_v_indices(leg)`` to pick them out of v-sized vectors
  (M, h, Jacobian columns) and ``make_q``/``split_q`` for configurations.
* Every foot/hip/CoM quantity is in the WORLD frame: positions [m] of frame origins, linear
  velocities [m/s], Jacobians and dJ*v in ``pin.LOCAL_WORLD_ALIGNED`` (world axes, taken at the foot).

``model`` (constant) and ``data`` (workspace) are kept apart as in Pinocchio; ``update(q, v)`` runs the
algorithms once and caches the results, the accessors only read the cache.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from tal_core.errors import InputError, RobotConfigError
from tal_core.legs import JOINTS_PER_LEG, LEG_NAMES, NUM_LEGS, Leg, leg_from_name
from tal_core.robot_description import NUM_JOINTS, RobotDescription, load_robot_description
from tal_core.rotations import quat_xyzw_from_rotation as _quat_xyzw_from_rotation
from tal_core.rotations import rotation_from_quat_xyzw as _rotation_from_quat_xyzw

ArrayLike = Sequence[float] | np.ndarray
QUATERNION_NORM_TOLERANCE = 1e-3  # |norm - 1| above this is an error, below it we normalise
_BASE_PLACEMENT_TOLERANCE = 1e-9  # [m] / [-] the base frame must coincide with the free-flyer joint
_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED


@dataclass(frozen=True)
class FootDynamics:
    """What leg odometry and contact-force estimation need at one (q, v), world frame: foot positions
    (4, 3) [m], foot Jacobians (12, nv), foot velocities (4, 3) [m/s], foot angular velocities (4, 3)
    [rad/s] (of the link carrying the foot: its rolling), h (nv,) and optionally M (nv, nv)."""

    foot_positions: np.ndarray
    foot_jacobians: np.ndarray
    foot_velocities: np.ndarray
    foot_angular_velocities: np.ndarray
    nonlinear_effects: np.ndarray
    mass_matrix: np.ndarray | None


class RobotModel:
    """Rigid-body model of a floating-base quadruped (Pinocchio) with tal's leg and frame conventions."""

    def __init__(self, description: RobotDescription) -> None:
        self.description = description
        self.model: pin.Model = pin.buildModelFromUrdf(str(description.urdf_path), pin.JointModelFreeFlyer())
        self.data: pin.Data = self.model.createData()
        self._scratch_data: pin.Data = self.model.createData()  # for queries that must not touch the cache
        self._feet_data: pin.Data = self.model.createData()  # for foot_dynamics (leaves the cache alone)
        self.nq: int = self.model.nq
        self.nv: int = self.model.nv
        self.total_mass_kg: float = float(pin.computeTotalMass(self.model))

        joint_ids = [self._joint_id(name) for name in description.joint_names]
        self._joint_q_indices = np.array([self.model.joints[j].idx_q for j in joint_ids], dtype=int)
        self._joint_v_indices = np.array([self.model.joints[j].idx_v for j in joint_ids], dtype=int)
        self._joint_v_indices.setflags(write=False)
        # Index arrays of the four legs' 3 x 3 foot-Jacobian blocks over their own joints (batched statics).
        self._leg_block_rows = np.arange(NUM_LEGS * 3).reshape(NUM_LEGS, 3, 1)
        self._leg_block_cols = self._joint_v_indices.reshape(NUM_LEGS, 1, JOINTS_PER_LEG)
        self._check_base_frame()
        self._foot_frame_ids = tuple(self._frame_id(name, "foot_frames") for name in description.foot_frames)
        self._hip_frame_ids = tuple(self._frame_id(name, "hip_frames") for name in description.hip_frames)
        self.nominal_base_height_m: float = self._nominal_base_height()
        self._upper_triangle = np.triu(np.ones((self.nv, self.nv), dtype=bool))
        self._hip_positions: np.ndarray | None = None
        self._updated = False

    @classmethod
    def from_name(cls, path_or_name: str = "hyq") -> RobotModel:
        """Build from a shipped robot name or a robot YAML path (see ``load_robot_description``)."""
        return cls(load_robot_description(path_or_name))

    # ------------------------------------------------------------------------------------------------
    # Construction checks
    # ------------------------------------------------------------------------------------------------
    def _joint_id(self, name: str) -> int:
        joint_id = self.model.getJointId(name)
        if joint_id >= self.model.njoints:
            raise RobotConfigError(
                f"{self.description.source}: joint {name!r} is not a joint of the Pinocchio "
                f"model built from {self.description.urdf_path}"
            )
        joint = self.model.joints[joint_id]
        if joint.nq != 1 or joint.nv != 1:
            raise RobotConfigError(
                f"{self.description.source}: joint {name!r} must have one degree of "
                f"freedom, Pinocchio gives nq={joint.nq}, nv={joint.nv}"
            )
        return joint_id

    def _frame_id(self, name: str, field: str) -> int:
        if not self.model.existFrame(name):
            raise RobotConfigError(
                f"{self.description.source}: field '{field}': frame {name!r} is not in the "
                f"Pinocchio model built from {self.description.urdf_path}"
            )
        return self.model.getFrameId(name)

    def _check_base_frame(self) -> None:
        """The base frame must sit exactly at the free-flyer joint, else q's base pose would not be it."""
        frame = self.model.frames[self._frame_id(self.description.base_frame, "base_frame")]
        root_joint_id = 1
        if frame.parentJoint != root_joint_id or not frame.placement.isIdentity(_BASE_PLACEMENT_TOLERANCE):
            raise RobotConfigError(
                f"{self.description.source}: field 'base_frame': frame "
                f"{self.description.base_frame!r} does not coincide with the floating "
                f"base joint; name the URDF root link"
            )

    def _nominal_base_height(self) -> float:
        """Base height [m] at which, in the nominal pose with a level base, the lowest foot sphere
        touches z = 0 (its centre is one foot radius above the ground)."""
        q = self.make_q(
            np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), self.description.nominal_joint_positions_rad
        )
        pin.framesForwardKinematics(self.model, self._scratch_data, q)
        lowest_foot_z = min(self._scratch_data.oMf[fid].translation[2] for fid in self._foot_frame_ids)
        return float(-lowest_foot_z + self.description.foot_radius_m)

    # ------------------------------------------------------------------------------------------------
    # Index helpers
    # ------------------------------------------------------------------------------------------------
    def canonical_joint_v_indices(self) -> np.ndarray:
        """(12,) indices into v (and M, h, Jacobian columns) of the joints in canonical order."""
        return self._joint_v_indices

    def leg_joint_v_indices(self, leg: Leg | int | str) -> np.ndarray:
        """(3,) indices into v of the leg's HAA, HFE, KFE joints."""
        return self._joint_v_indices[RobotDescription.leg_joint_slice(_to_leg(leg))]

    # ------------------------------------------------------------------------------------------------
    # Building and splitting q and v
    # ------------------------------------------------------------------------------------------------
    def make_q(
        self, base_position_world: ArrayLike, base_quat_xyzw: ArrayLike, joint_positions: ArrayLike
    ) -> np.ndarray:
        """Pinocchio configuration (nq,) from the base position [m] (world), ``world_R_base`` as a
        quaternion (x, y, z, w) and the 12 joint positions [rad] in canonical order."""
        q = np.empty(self.nq)
        q[0:3] = _checked_vector(base_position_world, 3, "base_position_world")
        q[3:7] = _checked_unit_quaternion(base_quat_xyzw, "base_quat_xyzw")
        q[self._joint_q_indices] = _checked_vector(joint_positions, NUM_JOINTS, "joint_positions")
        return q

    def split_q(self, q: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inverse of ``make_q``: (base position [m] world, quaternion xyzw, 12 canonical joints [rad])."""
        q = self._checked_q(q)
        return q[0:3].copy(), q[3:7].copy(), q[self._joint_q_indices]

    def make_v(
        self,
        base_lin_vel_world: ArrayLike,
        base_ang_vel_world: ArrayLike,
        joint_velocities: ArrayLike,
        base_quat_xyzw: ArrayLike,
    ) -> np.ndarray:
        """Pinocchio velocity (nv,) from world-frame base velocities and canonical joint velocities.

        ``base_lin_vel_world`` [m/s] is the velocity of the base origin and ``base_ang_vel_world``
        [rad/s] the base angular velocity, both in world coordinates; Pinocchio wants them in the base
        frame, so they are rotated by ``world_R_base^T`` (``base_quat_xyzw`` is ``world_R_base``).
        """
        world_R_base = _rotation_from_quat_xyzw(_checked_unit_quaternion(base_quat_xyzw, "base_quat_xyzw"))
        v = np.empty(self.nv)
        v[0:3] = world_R_base.T @ _checked_vector(base_lin_vel_world, 3, "base_lin_vel_world")
        v[3:6] = world_R_base.T @ _checked_vector(base_ang_vel_world, 3, "base_ang_vel_world")
        v[self._joint_v_indices] = _checked_vector(joint_velocities, NUM_JOINTS, "joint_velocities")
        return v

    def make_q_v(self, base_position_world: ArrayLike, world_R_base: np.ndarray, joint_positions: ArrayLike,
                 base_lin_vel_world: ArrayLike, base_ang_vel_world: ArrayLike,
                 joint_velocities: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """``make_q`` and ``make_v`` in one, from the rotation matrix ``world_R_base`` instead of a quaternion
        (what an estimator holds; the conversion back and forth is left out)."""
        rotation = np.asarray(world_R_base, dtype=float)
        if rotation.shape != (3, 3) or not np.isfinite(rotation).all():
            raise InputError(f"world_R_base: expected a finite (3, 3) rotation, got shape {rotation.shape}")
        q = np.empty(self.nq)
        q[0:3] = _checked_vector(base_position_world, 3, "base_position_world")
        q[3:7] = _quat_xyzw_from_rotation(rotation)
        q[self._joint_q_indices] = _checked_vector(joint_positions, NUM_JOINTS, "joint_positions")
        v = np.empty(self.nv)
        v[0:3] = rotation.T @ _checked_vector(base_lin_vel_world, 3, "base_lin_vel_world")
        v[3:6] = rotation.T @ _checked_vector(base_ang_vel_world, 3, "base_ang_vel_world")
        v[self._joint_v_indices] = _checked_vector(joint_velocities, NUM_JOINTS, "joint_velocities")
        return q, v

    def split_v(self, v: ArrayLike, base_quat_xyzw: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inverse of ``make_v``: (base linear velocity [m/s] world, base angular velocity [rad/s] world,
        12 canonical joint velocities [rad/s])."""
        v = _checked_vector(v, self.nv, "v")
        world_R_base = _rotation_from_quat_xyzw(_checked_unit_quaternion(base_quat_xyzw, "base_quat_xyzw"))
        return world_R_base @ v[0:3], world_R_base @ v[3:6], v[self._joint_v_indices]

    def neutral_q(self, base_height: float | None = None) -> np.ndarray:
        """Nominal standing configuration: level base at (0, 0, ``base_height`` [m]); by default the
        height at which the nominal-pose feet touch flat ground at z = 0."""
        height = self.nominal_base_height_m if base_height is None else float(base_height)
        if not np.isfinite(height):
            raise InputError(f"base_height must be finite, got {base_height!r}")
        return self.make_q(
            [0.0, 0.0, height], [0.0, 0.0, 0.0, 1.0], self.description.nominal_joint_positions_rad
        )

    # ------------------------------------------------------------------------------------------------
    # The per-tick update
    # ------------------------------------------------------------------------------------------------
    def update(self, q: ArrayLike, v: ArrayLike) -> None:
        """Run kinematics and dynamics once for (q, v) and cache every quantity the accessors return.

        computeAllTerms gives M (upper triangle), h, CoM, joint Jacobians and, in ``data.a``, the
        joint accelerations for zero qdd (what dJ*v needs); frame placements are one extra pass.
        """
        q = self._checked_q(q)
        v = _checked_vector(v, self.nv, "v")
        model, data = self.model, self.data
        pin.computeAllTerms(model, data, q, v)
        pin.updateFramePlacements(model, data)

        self._mass_matrix = np.where(self._upper_triangle, data.M, data.M.T)  # crba fills the upper half
        self._nonlinear_effects = data.nle.copy()
        self._com = data.com[0].copy()
        self._com_velocity = data.vcom[0].copy()
        oMf, feet = data.oMf, self._foot_frame_ids
        self._foot_jacobians = np.vstack([pin.getFrameJacobian(model, data, fid, _LWA)[:3] for fid in feet])
        self._foot_positions = np.array([oMf[fid].translation for fid in feet])
        self._foot_velocities = (self._foot_jacobians @ v).reshape(NUM_LEGS, 3)
        self._foot_djdqs = np.array(
            [pin.getFrameClassicalAcceleration(model, data, fid, _LWA).linear for fid in feet]
        )
        self._hip_positions = None  # computed on first request: few consumers need it every tick
        self._updated = True

    def foot_dynamics(self, q: ArrayLike, v: ArrayLike, with_mass_matrix: bool = False) -> FootDynamics:
        """Foot kinematics and h (optionally M) for (q, v), about 4x cheaper than ``update`` (no CoM, no
        dJ v, no full-model terms) and independent of its cache."""
        q = self._checked_q(q)
        v = _checked_vector(v, self.nv, "v")
        model, data = self.model, self._feet_data
        pin.computeJointJacobians(model, data, q)
        pin.updateFramePlacements(model, data)
        nle = pin.nonLinearEffects(model, data, q, v).copy()
        mass = None
        if with_mass_matrix:
            upper = pin.crba(model, data, q)
            mass = np.where(self._upper_triangle, upper, upper.T)
        feet = self._foot_frame_ids
        full = np.array([pin.getFrameJacobian(model, data, fid, _LWA) for fid in feet])   # (4, 6, nv)
        jacobians = full[:, :3].reshape(NUM_LEGS * 3, self.nv)
        angular = full[:, 3:] @ v
        positions = np.array([data.oMf[fid].translation for fid in feet])
        return FootDynamics(positions, jacobians, (jacobians @ v).reshape(NUM_LEGS, 3), angular, nle, mass)

    # ------------------------------------------------------------------------------------------------
    # Accessors (valid after update; arrays are replaced, never modified, by the next update)
    # ------------------------------------------------------------------------------------------------
    def mass_matrix(self) -> np.ndarray:
        """(nv, nv) joint-space inertia matrix M(q), full and symmetric [kg, kg m, kg m^2]."""
        self._require_update()
        return self._mass_matrix

    def nonlinear_effects(self) -> np.ndarray:
        """(nv,) h(q, v) = Coriolis/centrifugal + gravity terms [N, N m], so M qdd + h = S^T tau + J^T f."""
        self._require_update()
        return self._nonlinear_effects

    def com(self) -> np.ndarray:
        """(3,) centre of mass position [m], world frame."""
        self._require_update()
        return self._com

    def com_velocity(self) -> np.ndarray:
        """(3,) centre of mass velocity [m/s], world frame."""
        self._require_update()
        return self._com_velocity

    def foot_positions(self) -> np.ndarray:
        """(4, 3) foot frame origins (foot sphere centres) [m], world frame, rows LF, RF, LH, RH."""
        self._require_update()
        return self._foot_positions

    def foot_velocities(self) -> np.ndarray:
        """(4, 3) foot linear velocities [m/s], world frame, rows LF, RF, LH, RH."""
        self._require_update()
        return self._foot_velocities

    def foot_jacobian(self, leg: Leg | int | str) -> np.ndarray:
        """(3, nv) linear Jacobian of the foot, LOCAL_WORLD_ALIGNED: foot velocity (world) = J v."""
        self._require_update()
        return self._foot_jacobians[_leg_rows(_to_leg(leg))]

    def foot_jacobians(self) -> np.ndarray:
        """(12, nv) foot Jacobians stacked in leg order LF, RF, LH, RH (3 rows each)."""
        self._require_update()
        return self._foot_jacobians

    def foot_djdq(self, leg: Leg | int | str) -> np.ndarray:
        """(3,) dJ/dt v of the foot [m/s^2]: its classical acceleration at qdd = 0, world frame, so that
        foot acceleration = J qdd + dJ v."""
        self._require_update()
        return self._foot_djdqs[_to_leg(leg)]

    def foot_djdqs(self) -> np.ndarray:
        """(4, 3) dJ/dt v of every foot [m/s^2], world frame, rows LF, RF, LH, RH."""
        self._require_update()
        return self._foot_djdqs

    def hip_positions(self) -> np.ndarray:
        """(4, 3) hip (HAA joint) frame origins [m], world frame, rows LF, RF, LH, RH.

        Read from ``data`` on first request after an update (not every consumer needs it every tick).
        """
        self._require_update()
        if self._hip_positions is None:
            self._hip_positions = np.array([self.data.oMf[fid].translation for fid in self._hip_frame_ids])
        return self._hip_positions

    def leg_jacobian(self, leg: Leg | int | str) -> np.ndarray:
        """(3, 3) block of the foot Jacobian over the leg's own HAA, HFE, KFE velocities, world frame."""
        leg = _to_leg(leg)
        return self.foot_jacobian(leg)[:, self.leg_joint_v_indices(leg)]

    # ------------------------------------------------------------------------------------------------
    # Per-leg statics
    # ------------------------------------------------------------------------------------------------
    def leg_torques_for_foot_force(self, leg: Leg | int | str, grf_world: ArrayLike) -> np.ndarray:
        """Joint torques [N m] (HAA, HFE, KFE) that balance a ground reaction force at the foot.

        ``grf_world`` [N], world frame, is the force the GROUND exerts ON the foot (points up when
        standing); the foot then pushes on the ground with ``-grf_world``. With the leg's joint rows of
        M qdd + h = tau + J^T grf at rest and the leg's own weight neglected, ``tau = -J_leg^T grf``.
        """
        grf = _checked_vector(grf_world, 3, "grf_world")
        return -self.leg_jacobian(leg).T @ grf

    def foot_force_from_leg_torques(
        self, leg: Leg | int | str, tau_leg: ArrayLike, h_leg: ArrayLike | None = None
    ) -> np.ndarray:
        """Ground reaction force on the foot [N], world frame, from the leg's joint torques [N m].

        Solves ``J_leg^T grf = h_leg - tau_leg`` (joint rows of the dynamics at zero acceleration) in the
        least-squares sense, so a singular (stretched) leg gives the minimum-norm force instead of an
        error. ``h_leg`` is the leg's 3 entries of ``nonlinear_effects()`` [N m]; None means zero, the
        exact inverse of ``leg_torques_for_foot_force``.
        """
        tau = _checked_vector(tau_leg, JOINTS_PER_LEG, "tau_leg")
        rhs = -tau if h_leg is None else _checked_vector(h_leg, JOINTS_PER_LEG, "h_leg") - tau
        grf, *_ = np.linalg.lstsq(self.leg_jacobian(leg).T, rhs, rcond=None)
        return grf

    def foot_forces_from_joint_torques(self, foot_jacobians: np.ndarray, tau: ArrayLike, h: ArrayLike) -> np.ndarray:
        """(4, 3) ground reaction forces on the feet [N], world frame, rows LF, RF, LH, RH: each leg's
        ``foot_force_from_leg_torques`` from the stacked (12, nv) foot Jacobians (``foot_jacobians()`` or
        ``FootDynamics.foot_jacobians``), the 12 joint torques in canonical order and h (nv,) (with M vdot
        added for the full leg dynamics), the four 3 x 3 systems in one batched solve; a singular (stretched)
        leg falls back to that leg's minimum-norm least-squares force."""
        tau = _checked_vector(tau, NUM_LEGS * JOINTS_PER_LEG, "tau")
        h = _checked_vector(h, self.nv, "h")
        jacobians = np.asarray(foot_jacobians, dtype=float)
        if jacobians.shape != (NUM_LEGS * 3, self.nv):
            raise InputError(f"foot_jacobians: expected shape ({NUM_LEGS * 3}, {self.nv}), got {jacobians.shape}")
        blocks_t = jacobians[self._leg_block_rows, self._leg_block_cols].transpose(0, 2, 1)   # (4, 3, 3) J_leg^T
        rhs = (h[self._joint_v_indices] - tau).reshape(NUM_LEGS, JOINTS_PER_LEG, 1)
        try:
            return np.linalg.solve(blocks_t, rhs)[..., 0]
        except np.linalg.LinAlgError:
            return np.array([np.linalg.lstsq(blocks_t[leg], rhs[leg, :, 0], rcond=None)[0] for leg in range(NUM_LEGS)])

    # ------------------------------------------------------------------------------------------------
    # Validation
    # ------------------------------------------------------------------------------------------------
    def _checked_q(self, q: ArrayLike) -> np.ndarray:
        """A finite copy of q with the base quaternion normalised (Pinocchio assumes unit norm)."""
        q = _checked_vector(q, self.nq, "q").copy()
        norm = math.hypot(q[3], q[4], q[5], q[6])  # cheaper than numpy for 4 entries, called every tick
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise InputError(
                f"q[3:7] (base quaternion xyzw): quaternion norm {norm:.6g} is not 1 "
                f"(tolerance {QUATERNION_NORM_TOLERANCE})"
            )
        q[3:7] /= norm
        return q

    def _require_update(self) -> None:
        if not self._updated:
            raise RuntimeError("RobotModel: call update(q, v) before reading kinematic or dynamic quantities")


def _to_leg(leg: Leg | int | str) -> Leg:
    """Accept Leg, its integer value or its name ('LF'); InputError otherwise."""
    try:
        if isinstance(leg, str):
            return leg_from_name(leg)
        if isinstance(leg, (int, np.integer)) and not isinstance(leg, bool):
            return Leg(int(leg))
    except ValueError:
        pass
    raise InputError(f"unknown leg {leg!r}; expected one of {', '.join(LEG_NAMES)} (or 0..{NUM_LEGS - 1})")


def _leg_rows(leg: Leg) -> slice:
    return slice(3 * int(leg), 3 * int(leg) + 3)


def _checked_vector(value: ArrayLike, size: int, name: str) -> np.ndarray:
    """``value`` as a float (size,) array; InputError on a wrong shape or non-finite entries."""
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as error:
        raise InputError(f"{name}: cannot convert to a float array ({error})") from None
    if array.shape != (size,):
        raise InputError(f"{name}: expected shape ({size},), got {array.shape}")
    if not np.isfinite(array).all():
        bad = np.flatnonzero(~np.isfinite(array)).tolist()
        raise InputError(f"{name}: non-finite value(s) at index {bad}")
    return array


def _checked_unit_quaternion(value: ArrayLike, name: str) -> np.ndarray:
    """A quaternion (x, y, z, w) normalised if its norm is within QUATERNION_NORM_TOLERANCE of 1."""
    quat = _checked_vector(value, 4, name)
    norm = float(np.sqrt(quat @ quat))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise InputError(
            f"{name}: quaternion norm {norm:.6g} is not 1 (tolerance {QUATERNION_NORM_TOLERANCE})"
        )
    return quat / norm
