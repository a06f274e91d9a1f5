"""Motion generator: gait schedule, footholds, swing trajectories and trunk references, one call per tick.

``MotionGenerator.update`` (250 Hz) takes the measured state and the velocity command and returns the
``MotionTargets`` the whole-body controller tracks. Lift-off and touchdown positions are sampled from the
measured feet when the gait scheduler says a leg lifts off or touches down. Each swing aims at the
nominal (Raibert) foothold, re-planned as the velocity changes until ``retarget_until_progress``, unless
an external foothold (from VFA, ``set_foothold``) replaced it for that step.

Footholds (nominal, target, ``set_foothold``) are terrain points (terrain height in z, as in the
Foothold and GaitState messages); foot positions (swing, lift-off, touchdown) are foot-sphere centres
(``RobotModel.foot_positions``), one foot radius higher. World frame, z up; [m], [m/s], [m/s^2].
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from tal_control.errors import MotionConfigError
from tal_control.motion.footholds import (
    DEFAULT_K_FEEDBACK,
    HeightFunction,
    NormalFunction,
    raibert_footholds_xy,
    terrain_height,
    terrain_normals,
)
from tal_control.motion.gait import STAND, GaitParameters, GaitPhase, GaitScheduler
from tal_control.motion.swing import SwingTrajectory
from tal_control.motion.trunk import FeetMotion, TrunkOscillation, TrunkParameters, TrunkReference, TrunkTarget
from tal_core.errors import InputError
from tal_core.legs import LEGS, NUM_LEGS, Leg
from tal_core.robot_description import RobotDescription
from tal_core.robot_model import RobotModel
from tal_core.rotations import cross_rows, rotation_from_quat_xyzw

# MotionParameters read at every update (the others shape what the constructor builds)
RUNTIME_MOTION_PARAMETERS = frozenset({"k_feedback", "touchdown_depth_m", "retarget_until_progress",
                                       "retarget_threshold_m", "min_external_time_left_s"})
_REACH_FRACTION = 0.4  # default foothold offset limit, as a fraction of the nominal hip-to-foot height


@dataclass(frozen=True)
class MotionParameters:
    """Generator settings. k_feedback [s]: Raibert velocity gain. max_foothold_offset_m [m]: limit of the
    foothold's distance from the hip at touchdown (None: 0.4 x nominal hip-to-foot height).
    retarget_until_progress [-]: nominal footholds stop following the velocity after this swing progress.
    retarget_threshold_m [m]: smaller foothold changes are ignored. min_external_time_left_s [s]: external
    footholds for a swing with less time left are ignored. touchdown_depth_m [m]: the swing ends this far
    below the foothold's surface, so that a foot whose target height is a little too high (heightmap
    cells at a stair edge, tracking error) still reaches the ground by the planned touchdown instead of
    hovering into its stance. foothold_centre: "hips" (Raibert: each nominal foothold about its hip) or
    "com" (all four shifted by the CoM's horizontal offset from the hips' centre, under the trunk's
    attitude, so that the diagonal support lines of a trot pass under the CoM: HyQ's CoM is 3.9 cm ahead
    of its hips' centre, and with hip-centred footholds each two-leg phase tips the trunk forward about its
    support line). trunk: None builds it from the robot model, with the body-pose filter settings
    pose_bandwidth_rad_s [rad/s] (height and attitude), max_height_rate_m_s [m/s] and
    max_attitude_rate_rad_s [rad/s] where given (None: ``TrunkParameters``' defaults; a height reference
    that climbs stairs at v needs a rate of about v x rise / go, 0.2 m/s at 0.5 m/s on ViTAL's stairs)."""

    k_feedback: float = DEFAULT_K_FEEDBACK
    max_foothold_offset_m: float | None = None
    retarget_until_progress: float = 0.7
    retarget_threshold_m: float = 0.002
    min_external_time_left_s: float = 0.05
    touchdown_depth_m: float = 0.0
    foothold_centre: str = "hips"
    trunk: TrunkParameters | None = None
    pose_bandwidth_rad_s: float | None = None
    max_height_rate_m_s: float | None = None
    max_attitude_rate_rad_s: float | None = None
    contact_grace_s: float = 0.0   # [s] a planned stance leg is a support that long without a reported contact
    latch_contact: bool = False    # a contact reported in a planned stance holds until lift-off

    def __post_init__(self) -> None:
        for name in ("pose_bandwidth_rad_s", "max_height_rate_m_s", "max_attitude_rate_rad_s"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0.0):
                raise MotionConfigError(f"motion parameter {name} must be > 0 or None, got {value!r}")
        if self.trunk is not None and self.pose_filter_overrides():
            raise MotionConfigError("motion parameters: give the pose filter settings in trunk, not both")
        if self.foothold_centre not in ("hips", "com"):
            raise MotionConfigError(f"motion parameter foothold_centre must be 'hips' or 'com', "
                                    f"got {self.foothold_centre!r}")
        checks = {"k_feedback": self.k_feedback >= 0.0,
                  "retarget_threshold_m": self.retarget_threshold_m >= 0.0,
                  "retarget_until_progress": 0.0 <= self.retarget_until_progress <= 1.0,
                  "min_external_time_left_s": self.min_external_time_left_s >= 0.0,
                  "touchdown_depth_m": 0.0 <= self.touchdown_depth_m <= 0.1,
                  "contact_grace_s": 0.0 <= self.contact_grace_s <= 0.5}
        if self.max_foothold_offset_m is not None:
            checks["max_foothold_offset_m"] = self.max_foothold_offset_m > 0.0
        for name, ok in checks.items():
            if not (ok and math.isfinite(getattr(self, name))):
                raise MotionConfigError(f"motion parameter {name} is out of range: {getattr(self, name)!r}")

    def pose_filter_overrides(self) -> dict[str, float]:
        """The given body-pose filter settings as ``TrunkParameters`` keywords."""
        keys = {"height_bandwidth_rad_s": self.pose_bandwidth_rad_s,
                "attitude_bandwidth_rad_s": self.pose_bandwidth_rad_s,
                "max_height_rate_m_s": self.max_height_rate_m_s,
                "max_attitude_rate_rad_s": self.max_attitude_rate_rad_s}
        return {key: float(value) for key, value in keys.items() if value is not None}


def _leg_and_point(caller: str, leg: Leg | int, xyz: Sequence[float]) -> tuple[Leg, np.ndarray]:
    """A leg and a finite world point (3,) [m] given to ``caller``, or InputError naming the bad one."""
    point = np.asarray(xyz, dtype=float).reshape(-1)
    if point.shape != (3,) or not np.all(np.isfinite(point)):
        raise InputError(f"{caller}: xyz must be 3 finite values [m], got {xyz!r}")
    try:
        return Leg(int(leg)), point
    except ValueError:
        raise InputError(f"{caller}: unknown leg {leg!r}") from None


def _array(value: object, shape: tuple[int, ...], name: str) -> np.ndarray:
    try:
        array = np.array(value, dtype=float)
    except (TypeError, ValueError) as error:
        raise InputError(f"measured state: {name} is not numeric ({error})") from None
    if array.shape != shape or not np.isfinite(array).all():
        raise InputError(f"measured state: {name} must be finite with shape {shape}, got {array.shape}")
    array.setflags(write=False)
    return array


@dataclass(frozen=True, eq=False)
class MeasuredState:
    """Estimated robot state, world frame: base position [m], base orientation world_R_base as a
    quaternion (x, y, z, w), base linear [m/s] and angular [rad/s] velocity, feet (4, 3) [m] and [m/s]
    (foot-sphere centres, legs LF, RF, LH, RH), CoM [m] and optionally its velocity [m/s]."""

    base_position: np.ndarray
    base_quat_xyzw: np.ndarray
    base_lin_vel: np.ndarray
    base_ang_vel: np.ndarray
    foot_positions: np.ndarray
    foot_velocities: np.ndarray
    com: np.ndarray
    com_velocity: np.ndarray | None = None

    def __post_init__(self) -> None:
        shapes = {"base_position": (3,), "base_quat_xyzw": (4,), "base_lin_vel": (3,), "base_ang_vel": (3,),
                  "foot_positions": (NUM_LEGS, 3), "foot_velocities": (NUM_LEGS, 3), "com": (3,)}
        if self.com_velocity is not None:
            shapes["com_velocity"] = (3,)
        for name, shape in shapes.items():
            object.__setattr__(self, name, _array(getattr(self, name), shape, name))
        norm = float(np.linalg.norm(self.base_quat_xyzw))
        if abs(norm - 1.0) > 1e-3:
            raise InputError(f"measured state: base_quat_xyzw norm {norm:.6g} is not 1")
        object.__setattr__(self, "base_quat_xyzw", self.base_quat_xyzw / norm)

    def world_R_base(self) -> np.ndarray:
        return rotation_from_quat_xyzw(self.base_quat_xyzw)


@dataclass(frozen=True, eq=False)
class MotionTargets:
    """What the WBC tracks for one tick; per-leg arrays in leg order LF, RF, LH, RH, world frame.

    foot_position/velocity/acceleration (4, 3): desired swing foot centres [m, m/s, m/s^2] (stance legs:
    their touchdown position and zeros). touchdown_positions: foot centres sampled at the last touchdown
    (the stance task's anchors). liftoff_positions: foot centres at the last lift-off.
    nominal_footholds: Raibert footholds (stance legs: predicted for their next step); target_footholds:
    the swing target in use (stance legs: where they stand) -- both terrain points. normals: unit terrain
    normals at the stance feet and swing targets. external_foothold: target set by ``set_foothold``.
    """

    t_s: float
    stance: np.ndarray
    load_factor: np.ndarray
    foot_position: np.ndarray
    foot_velocity: np.ndarray
    foot_acceleration: np.ndarray
    touchdown_positions: np.ndarray
    liftoff_positions: np.ndarray
    nominal_footholds: np.ndarray
    target_footholds: np.ndarray
    hip_positions: np.ndarray
    normals: np.ndarray
    external_foothold: np.ndarray
    trunk: TrunkTarget
    gait: GaitPhase

    def __post_init__(self) -> None:
        for value in vars(self).values():
            if isinstance(value, np.ndarray):
                value.setflags(write=False)

    def hip_velocities(self) -> np.ndarray:
        """(4, 3) [m/s] world frame: the hips' velocities in the trunk reference (the CoM's reference
        velocity plus the reference angular velocity about the CoM, applied at ``hip_positions``). With
        ``time_to_touchdown`` it predicts where a swinging leg's hip is at touchdown (the ``vfa`` node's
        hip height on the way down a flight of stairs)."""
        lever = self.hip_positions - self.trunk.com_position[None, :]
        return self.trunk.com_velocity[None, :] + cross_rows(self.trunk.angular_velocity[None, :], lever)


class MotionGenerator:
    """Gait, footholds, swing and trunk references for a quadruped described by a robot model/description.

    The robot is used once, at construction, for the hip positions and CoM in the base frame, the foot
    radius, the nominal base height (default ``nominal_height_m``) and the leg length (reach limit).
    """

    def __init__(self, robot: RobotModel | RobotDescription, gait: GaitParameters = STAND,
                 nominal_height_m: float | None = None, params: MotionParameters | None = None) -> None:
        description = robot.description if isinstance(robot, RobotModel) else robot
        if not isinstance(description, RobotDescription):
            raise MotionConfigError(f"MotionGenerator needs a RobotModel or RobotDescription, got {robot!r}")
        model = RobotModel(description)  # private copy: its cache must not disturb the caller's model
        height = model.nominal_base_height_m
        model.update(model.neutral_q(height), np.zeros(model.nv))
        base = np.array([0.0, 0.0, height])
        self.hip_offsets_base = model.hip_positions() - base  # (4, 3) [m] hips in the base frame
        self.foot_radius_m = float(description.foot_radius_m)
        leg_height = float(np.mean(self.hip_offsets_base[:, 2] - (model.foot_positions() - base)[:, 2]))
        self.params = params or MotionParameters()
        if nominal_height_m is not None and not (math.isfinite(nominal_height_m) and nominal_height_m > 0.0):
            raise MotionConfigError(f"nominal_height_m must be > 0, got {nominal_height_m!r}")
        self.nominal_height_m = height if nominal_height_m is None else float(nominal_height_m)
        self.trunk_params = self.params.trunk or TrunkParameters(
            nominal_height_m=self.nominal_height_m, com_offset_base_m=tuple(model.com() - base),
            **self.params.pose_filter_overrides())
        # [m] base frame: what the nominal footholds are moved by (rotated into the world each tick)
        self._foothold_offset_base = (np.array(self.trunk_params.com_offset_base_m, dtype=float)
                                      if self.params.foothold_centre == "com" else None)
        self.max_foothold_offset_m = (self.params.max_foothold_offset_m if self.params.max_foothold_offset_m
                                      is not None else _REACH_FRACTION * leg_height)
        self._scheduler = GaitScheduler(gait)
        self._trunk: TrunkReference | None = None
        self._pose_override: tuple[float | None, float | None, float | None] | None = None
        self._oscillation: TrunkOscillation | None = None
        self._swings: list[SwingTrajectory | None] = [None] * NUM_LEGS
        self._external = np.zeros(NUM_LEGS, dtype=bool)
        self._pending: dict[Leg, tuple[int, np.ndarray]] = {}
        self._touchdown = np.zeros((NUM_LEGS, 3))
        self._liftoff = np.zeros((NUM_LEGS, 3))
        self._targets = np.zeros((NUM_LEGS, 3))
        self._last: MotionTargets | None = None

    # --- commands from outside ---
    @property
    def gait(self) -> GaitParameters:
        return self._scheduler.gait

    def set_step_height(self, step_height_m: float) -> None:
        """Swing apex [m] from the next lift-off on (``GaitScheduler.set_step_height``)."""
        self._scheduler.set_step_height(step_height_m)

    def update_params(self, **changes: float) -> None:
        """Change the settings read every tick (``RUNTIME_MOTION_PARAMETERS``) from the next update on;
        MotionConfigError names one out of range or one fixed at construction."""
        fixed = sorted(set(changes) - RUNTIME_MOTION_PARAMETERS)
        if fixed:
            raise MotionConfigError(f"motion parameters {fixed} are fixed at construction; at run time only "
                                    f"{sorted(RUNTIME_MOTION_PARAMETERS)} change")
        self.params = replace(self.params, **changes)

    def set_gait(self, params: GaitParameters) -> None:
        """Switch gait at the next cycle boundary (see ``GaitScheduler.set_gait``)."""
        self._scheduler.set_gait(params)

    @property
    def body_pose_reference(self) -> tuple[float | None, float | None, float | None] | None:
        """The body pose reference in use (base height [m], roll, pitch [rad]); None: the default pose."""
        return self._pose_override

    def set_body_pose_reference(self, base_height_m: float | None = None, roll: float | None = None,
                                pitch: float | None = None) -> None:
        """VPA's body pose reference: base origin world z [m], roll, pitch [rad] (None: keep default)."""
        self._pose_override = (base_height_m, roll, pitch)
        if self._trunk is not None:
            self._trunk.override(base_height_m, roll, pitch)

    def set_trunk_oscillation(self, oscillation: TrunkOscillation | None) -> None:
        """Add (or, with None, remove) sinusoidal height/roll excitation to the trunk reference."""
        self._oscillation = oscillation
        if self._trunk is not None:
            self._trunk.oscillation = oscillation

    def clear_body_pose_reference(self) -> None:
        self._pose_override = None
        if self._trunk is not None:
            self._trunk.clear_override()

    def set_foothold(self, leg: Leg | int, step_count: int, xyz: Sequence[float]) -> bool:
        """Replace the target of ``leg``'s current swing by the terrain point ``xyz`` [m] (world); used
        from the next update on. Ignored (returns False) unless the leg is swinging its step
        ``step_count`` with at least ``min_external_time_left_s`` left."""
        leg, point = _leg_and_point("set_foothold", leg, xyz)
        phase = None if self._last is None else self._last.gait
        if (phase is None or not phase.swing[leg] or int(step_count) != int(phase.step_count[leg])
                or phase.time_to_touchdown_s[leg] < self.params.min_external_time_left_s):
            return False
        self._pending[leg] = (int(step_count), point)
        return True

    def anchor_stance_foot(self, leg: Leg | int, xyz: Sequence[float]) -> None:
        """Move ``leg``'s stance anchor (touchdown sample) to ``xyz`` [m] (world): where the foot touched
        after a late touchdown (``TouchdownSearch``), instead of where it hovered at the planned one."""
        leg, point = _leg_and_point("anchor_stance_foot", leg, xyz)
        self._touchdown[leg] = point

    # --- the tick ---
    def update(self, t_s: float, measured: MeasuredState, cmd_vel: Sequence[float],
               terrain_height_fn: HeightFunction | None = None, *,
               terrain_normal_fn: NormalFunction | None = None) -> MotionTargets:
        """One control tick at sim time ``t_s`` [s]. cmd_vel: (vx, vy [m/s] horizontal frame, yaw rate
        [rad/s]). terrain_height_fn(x, y) -> z [m] (None: the ground is where the feet touched down)."""
        if not isinstance(measured, MeasuredState):
            raise InputError(f"update needs a MeasuredState, got {type(measured).__name__}")
        cmd = np.asarray(cmd_vel, dtype=float).reshape(-1)  # checked before any state changes
        if cmd.shape != (3,) or not np.isfinite(cmd).all():
            raise InputError(f"cmd_vel must be 3 finite values (vx, vy, yaw rate), got {cmd_vel!r}")
        phase = self._scheduler.update(t_s)
        world_R_base = measured.world_R_base()
        if self._trunk is None:
            self._start(measured, world_R_base)
        assert self._trunk is not None
        hips = measured.base_position + self.hip_offsets_base @ world_R_base.T
        for leg in LEGS:
            if phase.touchdown_event[leg]:
                self._touchdown[leg] = measured.foot_positions[leg]
                self._swings[leg] = None
                self._external[leg] = False
                self._pending.pop(leg, None)
        nominal = self._nominal_footholds(phase, measured, world_R_base, hips, terrain_height_fn)
        positions, velocities, accelerations = self._swing_feet(phase, measured, nominal, terrain_height_fn)
        ground = self._touchdown - np.array([0.0, 0.0, self.foot_radius_m])
        for leg in LEGS:
            if phase.stance[leg]:
                x, y, z = ground[leg]
                ground[leg, 2] = terrain_height(terrain_height_fn, x, y, z)
        footholds = np.where(phase.swing[:, None], self._targets, ground)
        normals = terrain_normals(terrain_normal_fn, footholds[:, :2])
        trunk = self._trunk.update(t_s, cmd, phase, FeetMotion(positions, velocities, accelerations),
                                   footholds, measured.com)
        self._last = MotionTargets(
            t_s=float(t_s), stance=phase.stance.copy(), load_factor=phase.load_factor.copy(),
            foot_position=positions, foot_velocity=velocities, foot_acceleration=accelerations,
            touchdown_positions=self._touchdown.copy(), liftoff_positions=self._liftoff.copy(),
            nominal_footholds=nominal, target_footholds=footholds, hip_positions=hips, normals=normals,
            external_foothold=self._external & phase.swing, trunk=trunk, gait=phase)
        return self._last

    def _start(self, measured: MeasuredState, world_R_base: np.ndarray) -> None:
        """First tick: all feet are stance feet where they are; the trunk starts at the measured pose."""
        self._touchdown[:] = measured.foot_positions
        self._liftoff[:] = measured.foot_positions
        R = world_R_base
        rpy = (math.atan2(R[2, 1], R[2, 2]), -math.asin(max(-1.0, min(1.0, R[2, 0]))),
               math.atan2(R[1, 0], R[0, 0]))
        self._trunk = TrunkReference(self.trunk_params, measured.com, rpy)
        self._trunk.oscillation = self._oscillation
        if self._pose_override is not None:
            self._trunk.override(*self._pose_override)

    def _nominal_footholds(self, phase: GaitPhase, measured: MeasuredState, world_R_base: np.ndarray,
                           hips: np.ndarray, height_fn: HeightFunction | None) -> np.ndarray:
        """Raibert footholds (4, 3) for every leg: for the current swing, or the next one of stance legs.

        The crawl's CoM shift is taken out: the hips are moved back by the current shift and the velocity
        feedback sees the trunk tracking error only (measured minus desired CoM velocity), so the
        footholds follow the neutral trunk path and the sway does not drag the feet sideways."""
        last = None if self._last is None else self._last.trunk
        if last is not None:
            hips = hips - last.com_shift
        v_cmd = np.zeros(2) if last is None else last.command_velocity_world[:2]
        yaw_rate = 0.0 if last is None else last.command_yaw_rate
        v_meas = measured.base_lin_vel if measured.com_velocity is None else measured.com_velocity
        v_error = np.zeros(2) if last is None else v_meas[:2] - last.com_velocity[:2]
        stance_s = phase.gait.stance_duration_s if not phase.gait.is_standing else 0.0
        to_liftoff = phase.time_to_liftoff_s
        t_left = np.where(phase.swing, phase.time_to_touchdown_s,
                          np.where(np.isfinite(to_liftoff), to_liftoff + phase.swing_duration_s, 0.0))
        if self._foothold_offset_base is not None:
            # Every foothold moves with the CoM's offset from the hips' centre (base frame, nominal pose).
            offset = world_R_base @ self._foothold_offset_base
            hips = hips + np.array([offset[0], offset[1], 0.0])
        xy = raibert_footholds_xy(hips[:, :2], v_cmd + v_error, v_cmd, yaw_rate, stance_s, t_left,
                                  self.params.k_feedback, rotation_centre_xy_world=measured.base_position[:2],
                                  max_offset_m=self.max_foothold_offset_m)
        ground_z = self._touchdown[:, 2] - self.foot_radius_m
        z = [terrain_height(height_fn, x, y, z0) for (x, y), z0 in zip(xy, ground_z, strict=True)]
        return np.column_stack([xy, z])

    def _swing_feet(self, phase: GaitPhase, measured: MeasuredState, nominal: np.ndarray,
                    terrain_height_fn: HeightFunction | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Start, re-plan and sample the swing trajectories; stance feet rest at their touchdown."""
        lift = np.array([0.0, 0.0, self.foot_radius_m - self.params.touchdown_depth_m])
        positions, velocities, accelerations = self._touchdown.copy(), np.zeros((4, 3)), np.zeros((4, 3))
        for leg in LEGS:
            if not phase.swing[leg]:
                self._targets[leg] = nominal[leg]
                continue
            tau = phase.t_s - phase.liftoff_time_s[leg]
            swing = self._swings[leg]
            if phase.liftoff_event[leg] or swing is None:
                self._liftoff[leg] = measured.foot_positions[leg]
                self._targets[leg] = nominal[leg]
                self._external[leg] = False
                x0, y0, z0 = self._liftoff[leg]
                surface = terrain_height(terrain_height_fn, x0, y0, z0 - self.foot_radius_m)
                swing = SwingTrajectory(self._liftoff[leg], nominal[leg] + lift, phase.swing_duration_s[leg],
                                        phase.gait.step_height_m, clear_z=surface + self.foot_radius_m)
                self._swings[leg] = swing
            pending = self._pending.pop(leg, None)
            if pending is not None and pending[0] == phase.step_count[leg] and tau < swing.duration_s:
                self._targets[leg], self._external[leg] = pending[1], True
                swing.retarget(pending[1] + lift, tau)
            elif (not self._external[leg] and phase.swing_progress[leg] <= self.params.retarget_until_progress
                  and np.linalg.norm(nominal[leg] - self._targets[leg]) > self.params.retarget_threshold_m
                  and 0.0 <= tau < swing.duration_s):
                self._targets[leg] = nominal[leg]
                swing.retarget(nominal[leg] + lift, tau)
            sample = swing.sample(tau)
            positions[leg], velocities[leg], accelerations[leg] = (sample.position, sample.velocity,
                                                                   sample.acceleration)
        return positions, velocities, accelerations
