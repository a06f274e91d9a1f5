"""One control tick of the locomotion stack without ROS: motion generation, then the sWBC, then torques.

``LocomotionController.tick`` is what the ``wbc`` node calls at 250 Hz and what the offline experiments
call in a closed loop with the simulator. Its inputs are the base state (world frame) and the joint
state in the robot's canonical order; its output the joint torques plus everything the diagnostics and
the gait_state message report.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from tal_core.errors import InputError
from tal_core.legs import NUM_LEGS
from tal_core.robot_model import RobotModel
from tal_core.state import BaseState

from .motion.gait import GaitParameters
from .motion.generator import MeasuredState, MotionGenerator, MotionParameters, MotionTargets
from .motion.touchdown import SupportTargets, TouchdownSearch
from .wbc import StandardWbc, WbcGains, WbcReferences, WbcSettings, WbcSolution

HeightFunction = Callable[[float, float], float]


@dataclass(frozen=True)
class TerrainImpedance:
    """Per-leg terrain impedance in the contact frame (4,) each: stiffness [N/m], damping [N s/m]."""

    stiffness_normal: np.ndarray
    damping_normal: np.ndarray
    stiffness_tangential: np.ndarray | None = None
    damping_tangential: np.ndarray | None = None


class ImpedanceGate:
    """STANCE's link from the TCE to the c3WBC: per leg, a new estimate is adopted only when it is valid,
    finite, positive and at least ``min_confidence`` (the TCE's fill ratio x R^2); otherwise the leg keeps
    the value it last adopted (the fallback until the first). Why: where a window mixes two terrains (a
    foot crossing onto a new patch) or the penetration is wrong (a foot against a stair riser), the fit
    has R^2 ~ 0: in a trot over graph_tour such an estimate (100 N/m, the clamp, on rigid ground) made the
    c3WBC drop HyQ within 0.3 s, while every estimate within 30 % of the truth had confidence >= 0.1 in
    95 % of the samples (measured). A leg whose window the TCE flags rigid (``rigid``: the ground is at least
    as stiff as the TCE can tell; the value is a lower bound, not an estimate) takes the rigid model, the
    fallback stiffness and damping: adopting the lower bound (1.3e5-2e6 N/m from tick to tick on the stairs
    of the real-time tour) with the damping held from the last soft patch made the c3WBC expect millimetres of
    sinking on rigid steps, and HyQ fell there in 3 of 3 real-time tours (measured). A held value expires
    after ``hold_limit_s`` without a new one (given the update's time): the leg takes the rigid model again.
    A tce that lags behind (a busy machine) was not confident for 2-3 s after a patch change and the c3WBC
    modelled a rigid-ground foot with T2's 8000 N/m over that time; in lockstep no gap exceeds 0.92 s."""

    def __init__(self, fallback_stiffness_n_per_m: float, fallback_damping_ns_per_m: float,
                 min_confidence: float = 0.1, hold_limit_s: float = math.inf) -> None:
        if not 0.0 <= min_confidence <= 1.0:
            raise InputError(f"min_confidence must be in [0, 1], got {min_confidence!r}")
        if not hold_limit_s > 0.0:
            raise InputError(f"hold_limit_s must be > 0, got {hold_limit_s!r}")
        self.hold_limit_s = float(hold_limit_s)
        for name, value in (("fallback stiffness", fallback_stiffness_n_per_m),
                            ("fallback damping", fallback_damping_ns_per_m)):
            if not (np.isfinite(value) and value >= 0.0):
                raise InputError(f"{name} must be finite and >= 0, got {value!r}")
        self.min_confidence = float(min_confidence)
        self.fallback_stiffness = float(fallback_stiffness_n_per_m)
        self.fallback_damping = float(fallback_damping_ns_per_m)
        self.stiffness = np.full(NUM_LEGS, float(fallback_stiffness_n_per_m))
        self.damping = np.full(NUM_LEGS, float(fallback_damping_ns_per_m))
        self.adopted = np.zeros(NUM_LEGS, dtype=np.int64)    # estimates taken, per leg
        self.held = np.zeros(NUM_LEGS, dtype=np.int64)       # estimates refused (value held), per leg
        self.rigid = np.zeros(NUM_LEGS, dtype=np.int64)      # rigid windows (the rigid model taken), per leg
        self.expired = np.zeros(NUM_LEGS, dtype=np.int64)    # held values expired (hold_limit_s), per leg
        self._adopted_s = np.full(NUM_LEGS, -math.inf)       # [s] time of each leg's last adoption

    def update(self, stiffness: np.ndarray, damping: np.ndarray, valid: np.ndarray,
               confidence: np.ndarray, rigid: np.ndarray | None = None, t_s: float | None = None) -> TerrainImpedance:
        """Fold one TCE update (NUM_LEGS,) each into the per-leg values and return the impedance to use;
        ``t_s`` [s]: the update's time (the hold limit counts from the last adoption)."""
        k, d = np.asarray(stiffness, dtype=float), np.asarray(damping, dtype=float)
        c = np.asarray(confidence, dtype=float)
        legs = (NUM_LEGS,)
        r = np.zeros(NUM_LEGS, dtype=bool) if rigid is None else np.asarray(rigid, dtype=bool)
        if k.shape != legs or d.shape != legs or np.shape(valid) != legs or c.shape != legs or r.shape != legs:
            raise InputError(f"impedance arrays must have {NUM_LEGS} entries, got {k.shape}, {d.shape}, "
                             f"{np.shape(valid)}, {c.shape}, {r.shape}")
        take = np.asarray(valid, dtype=bool) & np.isfinite(k) & (k > 0.0) & np.isfinite(c) & (c >= self.min_confidence)
        rigid_model = take & r
        self.stiffness = np.where(rigid_model, self.fallback_stiffness, np.where(take, k, self.stiffness))
        self.damping = np.where(rigid_model, self.fallback_damping,
                                np.where(take & np.isfinite(d) & (d >= 0.0), d, self.damping))
        self.adopted += take
        self.rigid += rigid_model
        if t_s is not None:
            self._adopted_s = np.where(take, float(t_s), self._adopted_s)
            soft = (self.stiffness != self.fallback_stiffness) | (self.damping != self.fallback_damping)
            expire = ~take & soft & (float(t_s) - self._adopted_s > self.hold_limit_s)
            if expire.any():
                self.stiffness = np.where(expire, self.fallback_stiffness, self.stiffness)
                self.damping = np.where(expire, self.fallback_damping, self.damping)
                self.expired += expire
        self.held += ~take & np.asarray(valid, dtype=bool)
        return TerrainImpedance(stiffness_normal=self.stiffness.copy(), damping_normal=self.damping.copy())


@dataclass(frozen=True)
class TickOutput:
    tau: np.ndarray                 # (12,) [N m] canonical joint order
    targets: MotionTargets
    solution: WbcSolution
    measured: MeasuredState
    support: SupportTargets | None = None  # contact feedback's supports and searches (None: not given)


class LocomotionController:
    """Motion generator + sWBC for one robot."""

    def __init__(self, model: RobotModel, gait: GaitParameters, gains: WbcGains | None = None,
                 settings: WbcSettings | None = None, nominal_height_m: float | None = None,
                 motion: MotionParameters | None = None) -> None:
        self.model = model
        self.motion = MotionGenerator(model.description, gait, nominal_height_m=nominal_height_m, params=motion)
        self.wbc = StandardWbc(model, gains, settings)
        self.touchdown_search = TouchdownSearch(
            contact_grace_s=motion.contact_grace_s if motion is not None else 0.0,
            latch_contact=motion.latch_contact if motion is not None else False)
        self.ticks = 0

    def tick(self, t_s: float, base: BaseState, joint_position: np.ndarray, joint_velocity: np.ndarray,
             cmd_vel: Sequence[float], terrain_height: HeightFunction | None = None,
             terrain_normal: Callable[[float, float], np.ndarray] | None = None,
             impedance: TerrainImpedance | None = None, foot_contact: np.ndarray | None = None) -> TickOutput:
        """Compute joint torques for the state at sim time ``t_s`` [s]. Raises InputError on bad input.

        ``foot_contact`` (4,) bool: which feet touch the ground now (None: trust the gait plan). With it, a
        planned stance foot that does not touch is no support: it searches downwards for the ground
        (``TouchdownSearch``) and carries no planned force; a swinging foot that touches late in its swing
        is a support from then on.

        ``impedance`` (c3WBC): per-leg terrain stiffness/damping in the contact frame; None uses the WBC
        settings' defaults. In compliant mode the legs load and unload over T = 4.6 / sqrt(k / m_e)
        (thesis), m_e = robot mass / number of stance feet, instead of the gait's fixed loading time.
        """
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
        load_factor = targets.load_factor
        if self.wbc.compliant:
            load_factor = self._terrain_aware_load_factor(targets, impedance)
        stiffness = impedance.stiffness_normal if impedance is not None else None
        stance, touchdown = targets.stance, targets.touchdown_positions
        foot = (targets.foot_position, targets.foot_velocity, targets.foot_acceleration)
        support = None
        if foot_contact is not None:
            support = self.touchdown_search.update(t_s, targets.stance, np.asarray(foot_contact, dtype=bool),
                                                   *foot, measured.foot_positions, targets.gait.swing_progress)
            for leg in np.flatnonzero(support.anchored):
                self.motion.anchor_stance_foot(int(leg), measured.foot_positions[leg])
            touchdown = np.where(support.anchored[:, None], measured.foot_positions, touchdown)
            touchdown = np.where(support.early[:, None], support.foot_position, touchdown)
            stance = support.supported
            # An early touchdown loads as a stance leg's ramp would have by then: fully.
            load_factor = np.where(support.early, 1.0, np.where(stance, load_factor, 0.0))
            foot = (support.foot_position, support.foot_velocity, support.foot_acceleration)
        refs = WbcReferences(
            com_position=trunk.com_position, com_velocity=trunk.com_velocity,
            com_acceleration=trunk.com_acceleration, world_R_base=trunk.world_R_base,
            angular_velocity=trunk.angular_velocity, angular_acceleration=trunk.angular_acceleration,
            foot_position=foot[0], foot_velocity=foot[1],
            foot_acceleration=foot[2], stance=stance,
            load_factor=load_factor, touchdown_position=touchdown,
            normals=targets.normals, stiffness_normal=stiffness,
            stiffness_tangential=None if impedance is None else impedance.stiffness_tangential,
            damping_normal=None if impedance is None else impedance.damping_normal,
            damping_tangential=None if impedance is None else impedance.damping_tangential)
        solution = self.wbc.solve(q, v, refs)
        self.ticks += 1
        return TickOutput(tau=solution.tau, targets=targets, solution=solution, measured=measured, support=support)

    def _terrain_aware_load_factor(self, targets: MotionTargets, impedance: TerrainImpedance | None) -> np.ndarray:
        """Load factor ramps over T_l/u = 4.6 / sqrt(k / m_e) per leg (1 % settling of the foot-mass system),
        at most ``max_load_ramp_stance_fraction`` of the gait's stance duration."""
        phase = targets.gait
        if phase.gait.is_standing:
            return targets.load_factor
        settings = self.wbc.settings
        k = (impedance.stiffness_normal if impedance is not None
             else np.full(len(targets.stance), settings.default_stiffness_n_per_m))
        n_stance = max(int(np.sum(targets.stance)), 1)
        m_e = self.model.total_mass_kg / n_stance
        ramp = np.minimum(4.6 / np.sqrt(np.maximum(k, 1.0) / m_e),
                          settings.max_load_ramp_stance_fraction * phase.gait.stance_duration_s)
        since_touchdown = phase.t_s - phase.touchdown_time_s
        to_liftoff = phase.time_to_liftoff_s
        factor = np.clip(np.minimum(since_touchdown, to_liftoff) / ramp, 0.0, 1.0)
        return np.where(targets.stance, factor, 0.0)
