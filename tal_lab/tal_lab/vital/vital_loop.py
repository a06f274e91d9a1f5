"""ViTAL in the closed loop without ROS: VFA and VPA (or TBR) driving a ``LocomotionController``.

``VitalLoop`` is a tick hook for ``tal_lab.closed_loop.run_closed_loop``. Every control
tick it does what the ``vfa`` and ``vpa`` nodes do over topics, in the same order and with the same
planners: it samples the robot-centric heightmap of the course at ``heightmap_period_s`` (the bridge's
terrain/heightmap), builds the gait state of the tick (``gait_snapshot_from_tick``, the gait_state
message's content), hands the swinging legs' footholds to the motion generator (``set_foothold``, as the
wbc does on ``footholds``) and the pose reference to the trunk (``set_body_pose_reference``). In lockstep
the nodes' answers also arrive before the next control tick, so the loop is the graph's timing.

It also watches the legs for collisions with the terrain, which the simulator cannot report for the
shins (their collisions with the ground are filtered out; see ``tal_sim_bridge.physics``):

* leg (shin/knee): a point of the lower-leg cylinder (knee -> foot, radius ``SHIN_RADIUS_M``) below the
  highest terrain within that radius, by more than ``COLLISION_TOLERANCE_M``;
* foot: a true foot contact during a swing, after the foot has left the ground in that swing (the
  contact of lift-off itself is not a collision), before ``FOOT_TOUCHDOWN_PROGRESS`` of the swing
  (tripping on an edge) or at any time with a contact normal steeper than ``RISER_NORMAL_Z`` (hitting a
  riser).

Counts are events (a collision starting), per leg. World frame z up, [m], [s]; legs LF, RF, LH, RH.

For comparing pose sources on equal terms, ``monitor_period_s`` evaluates, with the exact pose
evaluation, the number of safe footholds each leg has at the robot's actual hip heights (thesis Fig. 9A
and 5C: VPA vs TBR), and for the VPA the envelope thickness |F(u* + m) - F(u* - m)| of each leg's
approximated curve at the optimum with the cost margin m (thesis: C_sum vs C_int).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from tal_core.heightmap import HeightMapGrid, extract_heightmap
from tal_core.legs import LEGS, NUM_LEGS
from tal_core.robot_model import RobotModel
from tal_core.terrain import Course
from tal_perception.errors import VpaConfigError
from tal_perception.fec_settings import GaitTiming
from tal_perception.vfa import extract_patch
from tal_perception.vfa_planner import GaitSnapshot, HipFrame, PlannerSettings, VfaPlanner
from tal_perception.vpa import PoseAdapter
from tal_perception.vpa_planner import PosePlanner
from tal_perception.vpa_settings import VpaSettings

FloatArray = NDArray[np.float64]

SHIN_RADIUS_M = 0.02  # [m] HyQ's lower-leg collision cylinder (URDF)
COLLISION_TOLERANCE_M = 0.005  # [m] depth below which a shin point counts as touching (contact noise)
SHIN_SAMPLES = 12  # points from the knee to the top of the foot sphere
FOOT_TOUCHDOWN_PROGRESS = 0.75  # [-] swing progress after which a foot contact is an (early) touchdown
RISER_NORMAL_Z = 0.7  # [-] a contact normal with a smaller z component is a riser or an edge, not a tread


@dataclass(frozen=True)
class VitalLoopSettings:
    """What runs in the loop. pose_source: "vpa", "tbr" or "none" (the controller's default pose);
    vfa: the foothold adaptation on (False: nominal footholds); the rest as the nodes' parameters."""

    vfa: bool = True
    vfa_selector: str = "exact"
    pose_source: str = "vpa"
    vpa_use_cnn: bool = True
    vpa_update_period_s: float = 0.05  # [s] 20 Hz (thesis: 5 Hz, 0.2 s)
    vpa: VpaSettings = field(default_factory=VpaSettings)
    # The vfa planner's settings; diagonal-pair compensation on (the planner's own default is off).
    vfa_planner: PlannerSettings = field(default_factory=lambda: PlannerSettings(pair_compensation_m=0.08))
    heightmap_period_s: float = 0.05  # [s] the bridge's terrain/heightmap rate (20 Hz)
    heightmap_cells: int = 121  # [-] rows = cols; 121 x 0.02 m = 2.42 m around the base
    heightmap_resolution_m: float = 0.02
    monitor_period_s: float | None = None  # [s] exact safe-foothold count at the actual hips; None: off

    def __post_init__(self) -> None:
        if self.pose_source not in ("vpa", "tbr", "none"):
            raise VpaConfigError(f"pose_source must be vpa, tbr or none, got {self.pose_source!r}")
        for name in ("vpa_update_period_s", "heightmap_period_s", "heightmap_resolution_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise VpaConfigError(f"VitalLoopSettings.{name} must be > 0, got {value!r}")
        if int(self.heightmap_cells) < 33:
            raise VpaConfigError(f"heightmap_cells must be >= 33, got {self.heightmap_cells!r}")


def gait_snapshot_from_tick(t_s: float, out) -> GaitSnapshot:
    """The gait state of one controller tick (``TickOutput``), as the wbc publishes it on gait_state."""
    targets, phase = out.targets, out.targets.gait
    velocity = targets.trunk.command_velocity_world
    yaw = float(targets.trunk.rpy[2])
    c, s = math.cos(yaw), math.sin(yaw)
    twist = np.array([c * velocity[0] + s * velocity[1], -s * velocity[0] + c * velocity[1], 0.0, 0.0, 0.0,
                      float(targets.trunk.command_yaw_rate)])
    return GaitSnapshot(
        stamp_s=float(t_s), step_frequency_hz=float(phase.gait.step_frequency_hz),
        duty_factor=float(phase.gait.duty_factor), step_height_m=float(phase.gait.step_height_m),
        base_twist=twist, swing=np.asarray(phase.swing, dtype=bool),
        time_to_touchdown_s=np.asarray(phase.time_to_touchdown_s, dtype=float),
        step_count=np.asarray(phase.step_count, dtype=np.int64),
        liftoff_position=np.asarray(targets.liftoff_positions, dtype=float),
        nominal_foothold=np.asarray(targets.nominal_footholds, dtype=float),
        hip_position=np.asarray(targets.hip_positions, dtype=float), hip_velocity=targets.hip_velocities())


@dataclass
class VitalTrace:
    """Per-tick record of the loop (250 Hz), aligned with the closed-loop log's samples."""

    t: list[float] = field(default_factory=list)
    pose_reference: list[FloatArray] = field(default_factory=list)  # (3,) base z [m], roll, pitch [rad]; nan: none
    safe_footholds: list[NDArray[np.int64]] = field(default_factory=list)  # (4,) VPA's count at the pose (-1: none)
    leg_collision: list[NDArray[np.bool_]] = field(default_factory=list)  # (4,) shin/knee in the terrain
    foot_collision: list[NDArray[np.bool_]] = field(default_factory=list)  # (4,) swing foot hitting terrain
    shin_depth: list[FloatArray] = field(default_factory=list)  # (4,) [m] deepest shin point (< 0: clear)
    actual_safe_footholds: list[FloatArray] = field(default_factory=list)  # (4,) exact count at the actual
    # hips, held between monitor samples (nan: monitor off or no sample yet)
    envelope_thickness: list[FloatArray] = field(default_factory=list)  # (4,) [-] VPA |F(u*+m) - F(u*-m)|

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: np.array(values) for name, values in vars(self).items()}


class VitalLoop:
    """The tick hook (see the module docstring). ``course`` is the simulated course (its heightmap is
    what the robot sees: a perfect map, as in the thesis' simulations)."""

    def __init__(self, course: Course, model: RobotModel, settings: VitalLoopSettings | None = None) -> None:
        self.course = course
        self.model = model
        self.settings = settings if settings is not None else VitalLoopSettings()
        s = self.settings
        self.vfa = VfaPlanner.for_robot(model, s.vfa_selector, s.vfa_planner) if s.vfa else None
        if self.vfa is not None:
            self.vfa.warm_up()
        self.pose = (PosePlanner(model, s.pose_source, use_cnn=s.vpa_use_cnn, update_period_s=s.vpa_update_period_s,
                                 settings=s.vpa) if s.pose_source != "none" else None)
        self.trace = VitalTrace()
        self.decision_log: list[tuple[float, int, int, FloatArray, FloatArray, bool]] = []
        # (t [s], leg, step count, nominal (3,) [m], selected (3,) [m], a safe candidate existed)
        self.decisions = 0
        self.adapted = 0
        self.no_safe = 0
        self.rejected_footholds = 0
        self.pose_updates = 0
        self.pose_compute_s: list[float] = []
        self._last_map_s: float | None = None
        self._last_pose = np.full(3, np.nan)
        self._last_safe = np.full(NUM_LEGS, -1, dtype=np.int64)
        self._links: tuple[list[int], list[int]] | None = None
        self._airborne = np.zeros(NUM_LEGS, dtype=bool)  # the foot has left the ground in this swing
        self._monitor = PoseAdapter(model, s.vpa) if s.monitor_period_s is not None else None
        self._last_monitor_s: float | None = None
        self._actual_safe = np.full(NUM_LEGS, np.nan)
        self._thickness = np.full(NUM_LEGS, np.nan)
        self._grid: HeightMapGrid | None = None
        self._hips = HipFrame.from_model(model)

    # -- the hook -----------------------------------------------------------------------------------
    def __call__(self, ctx) -> None:
        t = float(ctx.t_s)
        state = ctx.state
        if self._last_map_s is None or t - self._last_map_s >= self.settings.heightmap_period_s - 1e-9:
            self._set_map(self._heightmap(state), t)
        snapshot = gait_snapshot_from_tick(t, ctx.output)
        motion = ctx.controller.motion
        if self.vfa is not None:
            for decision in self.vfa.update(snapshot):
                self.decisions += 1
                self.adapted += int(decision.adapted)
                self.no_safe += int(not decision.safe_candidate_found)
                self.decision_log.append((t, int(decision.leg), int(decision.step_count), decision.nominal.copy(),
                                          decision.selected.copy(), bool(decision.safe_candidate_found)))
                if self.pose is not None:
                    self.pose.set_foothold(int(decision.leg), decision.selected)
                if not motion.set_foothold(int(decision.leg), decision.step_count, decision.selected):
                    self.rejected_footholds += 1
        if self.pose is not None:
            reference = self.pose.update(snapshot, ctx.output.targets.target_footholds)
            if reference is not None:
                self.pose_updates += 1
                self.pose_compute_s.append(reference.elapsed_s)
                motion.set_body_pose_reference(reference.base_height_m, reference.roll_rad, reference.pitch_rad)
                self._last_pose = np.array([reference.base_height_m, reference.roll_rad, reference.pitch_rad])
                self._last_safe = np.asarray(reference.safe_footholds, dtype=np.int64)
                self._thickness = self._envelope_thickness()
        if self._monitor is not None and (self._last_monitor_s is None or t - self._last_monitor_s
                                          >= float(self.settings.monitor_period_s) - 1e-9):
            self._last_monitor_s = t
            self._actual_safe = self._safe_at_actual_hips(snapshot, ctx.output.targets.hip_positions)
        leg_hit, depth = self.shin_collisions(ctx.core.sim)
        self.trace.t.append(t)
        self.trace.pose_reference.append(self._last_pose.copy())
        self.trace.safe_footholds.append(self._last_safe.copy())
        self.trace.leg_collision.append(leg_hit)
        self.trace.shin_depth.append(depth)
        self.trace.actual_safe_footholds.append(self._actual_safe.copy())
        self.trace.envelope_thickness.append(self._thickness.copy())
        self.trace.foot_collision.append(self._foot_collisions(ctx.contacts, ctx.output.targets.gait))
        return None

    # -- maps ---------------------------------------------------------------------------------------
    def _heightmap(self, state) -> HeightMapGrid:
        x, y, z, w = state.base_quat_xyzw
        yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
        n = int(self.settings.heightmap_cells)
        return extract_heightmap(self.course, (float(state.base_position_m[0]), float(state.base_position_m[1])),
                                 yaw, rows=n, cols=n, resolution_m=self.settings.heightmap_resolution_m)

    def _set_map(self, grid: HeightMapGrid, t_s: float) -> None:
        self._last_map_s = t_s
        self._grid = grid
        if self.vfa is not None:
            self.vfa.set_map(grid, t_s)
        if self.pose is not None:
            self.pose.set_map(grid, t_s)

    # -- safe footholds ------------------------------------------------------------------------------
    def _safe_at_actual_hips(self, gait: GaitSnapshot, hips_world: np.ndarray) -> FloatArray:
        """(4,) number of safe footholds of each leg's map at its actual hip height (exact evaluation,
        linear between the sampled hip heights)."""
        assert self._monitor is not None and self._grid is not None
        fec = self._monitor.evaluator.settings
        heading = self._hips.heading(hips_world)  # as the planners take it
        timing = GaitTiming(float(gait.step_frequency_hz), float(gait.duty_factor), 0.0, float(gait.step_height_m))
        out = np.zeros(NUM_LEGS)
        for leg in LEGS:
            patch = extract_patch(self._grid, hips_world[leg, :2], heading, fec.patch_cells, fec.resolution_m)
            evaluation = self._monitor.pose_evaluator.evaluate(leg, patch, gait.base_twist, timing)
            out[leg] = np.interp(hips_world[leg, 2] - evaluation.reference_m, evaluation.hip_heights,
                                 evaluation.nsf.astype(float))
        return out

    def _envelope_thickness(self) -> FloatArray:
        """(4,) |F(u* + m) - F(u* - m)| [footholds] of the VPA's approximated curves at its last optimum
        (m: the cost margin); NaN when the last update held a pose without curves."""
        if self.pose is None or self.pose.adapter is None or self.pose.last_result is None:
            return np.full(NUM_LEGS, np.nan)
        result = self.pose.last_result
        diagnostics = result.diagnostics
        if diagnostics is None or diagnostics.weights is None or diagnostics.map_references is None:
            return np.full(NUM_LEGS, np.nan)
        adapter = self.pose.adapter
        references = np.nan_to_num(diagnostics.map_references[0], nan=diagnostics.body_reference_m)
        z = np.asarray(result.hip_heights_m, dtype=float) - references
        margin = adapter.settings.cost_margin_m
        upper = adapter.basis.evaluate(diagnostics.weights[0], z + margin)
        lower = adapter.basis.evaluate(diagnostics.weights[0], z - margin)
        return np.abs(upper - lower) * adapter.cells

    # -- collisions ---------------------------------------------------------------------------------
    def _leg_links(self, sim) -> tuple[list[int], list[int]]:
        """(knee links, foot links): the lower-leg links (their frames sit at the KFE joints) and feet."""
        if self._links is None:
            knees = []
            for leg in LEGS:
                joint = sim.joint_ids[3 * int(leg) + 2]  # KFE
                knees.append(int(joint))  # a joint's child link has the joint's index in PyBullet
            self._links = (knees, list(sim.foot_links))
        return self._links

    def shin_collisions(self, sim) -> tuple[NDArray[np.bool_], FloatArray]:
        """Per leg: whether the lower-leg cylinder is in the terrain, and its deepest point [m] (< 0: clear)."""
        knees, feet = self._leg_links(sim)
        states = sim.client.getLinkStates(sim.robot, knees + feet, computeForwardKinematics=1)
        knee = np.array([s[4] for s in states[:NUM_LEGS]])
        foot = np.array([s[4] for s in states[NUM_LEGS:]])
        radius = float(sim.description.foot_radius_m)
        axis = foot - knee
        length = np.linalg.norm(axis, axis=1, keepdims=True)
        # From the knee down to where the foot sphere begins: the sphere's own contact is the foot's.
        stop = np.clip((length - radius) / np.maximum(length, 1e-9), 0.0, 1.0)
        fractions = np.linspace(0.0, 1.0, SHIN_SAMPLES)[None, :, None] * stop[:, None, :]
        points = knee[:, None, :] + fractions * axis[:, None, :]  # (4, S, 3)
        offsets = np.array([[0.0, 0.0], [SHIN_RADIUS_M, 0.0], [-SHIN_RADIUS_M, 0.0], [0.0, SHIN_RADIUS_M],
                            [0.0, -SHIN_RADIUS_M]])
        xy = points[:, :, None, :2] + offsets[None, None]
        ground = np.asarray(self.course.height(xy[..., 0].ravel(), xy[..., 1].ravel()), dtype=float)
        ground = ground.reshape(xy.shape[:-1]).max(axis=2)  # (4, S) highest terrain within the radius
        depth = (ground - (points[..., 2] - SHIN_RADIUS_M)).max(axis=1)
        return depth > COLLISION_TOLERANCE_M, depth

    def _foot_collisions(self, contacts: list, phase) -> NDArray[np.bool_]:
        """(4,) whether each swinging foot hits the terrain (see the module docstring); contacts: the
        tick's true foot contacts, leg order."""
        hits = np.zeros(NUM_LEGS, dtype=bool)
        for leg, contact in enumerate(contacts):
            if not phase.swing[leg]:
                self._airborne[leg] = False
                continue
            if not contact.in_contact:
                self._airborne[leg] = True
                continue
            hits[leg] = self._airborne[leg] and (float(phase.swing_progress[leg]) < FOOT_TOUCHDOWN_PROGRESS
                                                 or float(contact.normal[2]) < RISER_NORMAL_Z)
        return hits


def collision_events(flags: np.ndarray) -> NDArray[np.int64]:
    """(4,) number of collision onsets per leg in a (N, 4) boolean trace."""
    flags = np.asarray(flags, dtype=bool)
    if flags.size == 0:
        return np.zeros(NUM_LEGS, dtype=np.int64)
    onsets = flags[1:] & ~flags[:-1]
    return (onsets.sum(axis=0) + flags[0]).astype(np.int64)
