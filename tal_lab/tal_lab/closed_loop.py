"""Closed-loop runner without ROS: ``LocomotionController`` driving the PyBullet simulation in lockstep.

The simulation steps at 1 kHz (``physics_dt_s``); every ``control_decimation`` steps (250 Hz) the
controller ticks on the ground-truth base and joint state and its torques are submitted to the bridge's
command hold (``BridgeCore.commands``), which applies them until the next tick -- the same path the
``sim_bridge`` node uses. Everything is deterministic: same config, same log.

The log (``ClosedLoopLog``) holds one sample per control tick (250 Hz), taken at the tick, i.e. the
state the controller saw and the command it produced. Frames: world (z up) unless the name says
``_h`` (horizontal frame: the actual base yaw only). Per-leg arrays are in leg order LF, RF, LH, RH,
joint arrays in the robot's canonical order (LF, RF, LH, RH) x (HAA, HFE, KFE).

A run has *fallen* when the trunk height above the terrain under the base drops below
``FALL_HEIGHT_FRACTION`` of the nominal height or any link other than a foot touches the ground.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from tal_control.locomotion import (
    BaseState,
    ImpedanceGate,
    LocomotionController,
    TerrainImpedance,
    TickOutput,
)
from tal_control.map_alignment import HeightmapAligner
from tal_control.motion.gait import PRESETS, GaitParameters
from tal_control.motion.generator import MotionParameters
from tal_control.motion.trunk import TrunkOscillation
from tal_control.wbc import WbcGains, WbcSettings
from tal_core.errors import InputError
from tal_core.legs import NUM_LEGS
from tal_core.robot_description import load_robot_description
from tal_core.robot_model import RobotModel
from tal_core.rotations import rotation_from_quat_xyzw
from tal_core.terrain import Course, load_course
from tal_estimation.state_estimator import StateEstimatorSettings, legs_from_impedance_arrays
from tal_estimation.streaming import StreamingEstimator
from tal_estimation.tce import TceSettings, foot_penetration
from tal_estimation.tce_driver import TceDriver
from tal_sim_bridge.bridge_core import BridgeCore
from tal_sim_bridge.effects import ModelEffects
from tal_sim_bridge.physics import SOFT_BOX_OVERLAP_M, RobotState, Simulation

BOUNDARY_MARGIN_M = SOFT_BOX_OVERLAP_M + 0.01
"""[m] beyond the foot radius: a foot this close to a patch boundary has no single true stiffness (soft
collision boxes reach SOFT_BOX_OVERLAP_M under their neighbours, so the strip there is a mixed ground)."""

FALL_HEIGHT_FRACTION = 0.6
"""A trunk lower than this fraction of the nominal height above the terrain counts as a fall."""

Command = tuple[float, float, float, float]  # (t_start [s], vx [m/s], vy [m/s], yaw rate [rad/s])


@dataclass(frozen=True)
class ClosedLoopConfig:
    """One closed-loop run.

    course: shipped course name, YAML path or a ``Course``. gait: preset name or ``GaitParameters``.
    commands: piecewise-constant velocity command, (t_start [s], vx [m/s], vy [m/s] horizontal frame,
    yaw rate [rad/s]) sorted by t_start; zero before the first segment. settings/gains: WBC settings and
    gains (None: defaults). effects: model effects of the simulated robot (None: nominal).
    stop_on_fall: end the run at the first fallen sample (the log ends there).
    impedance_source (c3WBC): "none" (the WBC settings' defaults), "fixed" (terrain_stiffness_n_per_m and
    terrain_damping_ns_per_m for every leg) or "tce" (STANCE: the online TCE on the ground-truth base
    state, as the thesis' motion capture; per leg the fixed values until an estimate with confidence >=
    impedance_min_confidence is adopted, then the last adopted one: ``ImpedanceGate``).
    trunk_oscillation: sinusoidal height/roll excitation of the trunk reference (aggressive manoeuvres).
    state_estimator: None -> the controller runs on the ground-truth base state; settings -> on the
    proprioceptive estimate (IMU with ``imu_noise`` = (gyro [rad/s], accel [m/s^2]) white-noise std per
    physics step, joint states, measured torques), ticking on its own grid and initialised at the true
    start pose, exactly as the state_estimator node does it.
    contact_feedback: the controller gets the simulator's foot contacts (``LocomotionController.tick``'s
    foot_contact: a planned stance foot that does not touch searches for the ground and carries no force).
    motion: the motion generator's parameters (None: defaults).
    """

    name: str = "run"
    course: str | Path | Course = "flat_rigid"
    gait: str | GaitParameters = "stand"
    commands: Sequence[Command] = ((0.0, 0.0, 0.0, 0.0),)
    duration_s: float = 5.0
    settings: WbcSettings | None = None
    gains: WbcGains | None = None
    effects: ModelEffects | None = None
    robot: str = "hyq"
    initial_xy: tuple[float, float] = (0.0, 0.0)
    initial_yaw_rad: float = 0.0
    physics_dt_s: float = 1e-3
    control_decimation: int = 4
    stop_on_fall: bool = True
    progress: bool = True
    impedance_source: str = "none"
    terrain_stiffness_n_per_m: float = 2e6
    terrain_damping_ns_per_m: float = 400.0
    tce: TceSettings | None = None
    trunk_oscillation: TrunkOscillation | None = None
    state_estimator: StateEstimatorSettings | None = None
    imu_noise: tuple[float, float] = (0.0, 0.0)
    impedance_min_confidence: float = 0.1
    impedance_hold_limit_s: float = 1.5
    contact_feedback: bool = False
    motion: MotionParameters | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.duration_s) and self.duration_s > 0.0):
            raise InputError(f"closed loop '{self.name}': duration_s must be > 0, got {self.duration_s!r}")
        if int(self.control_decimation) < 1:
            raise InputError(f"closed loop '{self.name}': control_decimation must be >= 1")
        commands = tuple(tuple(float(v) for v in c) for c in self.commands)
        if any(len(c) != 4 or not all(math.isfinite(v) for v in c) for c in commands):
            raise InputError(
                f"closed loop '{self.name}': commands must be (t_start, vx, vy, yaw_rate) "
                f"finite tuples, got {self.commands!r}"
            )
        if any(b[0] < a[0] for a, b in zip(commands, commands[1:])):
            raise InputError(f"closed loop '{self.name}': commands must be sorted by t_start")
        object.__setattr__(self, "commands", commands)
        if self.impedance_source not in ("none", "fixed", "tce"):
            raise InputError(f"closed loop '{self.name}': impedance_source must be none, fixed or tce, "
                             f"got {self.impedance_source!r}")
        for key in ("terrain_stiffness_n_per_m", "terrain_damping_ns_per_m"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value >= 0.0):
                raise InputError(f"closed loop '{self.name}': {key} must be finite and >= 0, got {value!r}")
        if isinstance(self.gait, str) and self.gait not in PRESETS:
            raise InputError(f"closed loop '{self.name}': unknown gait {self.gait!r} ({sorted(PRESETS)})")

    def command_at(self, t_s: float) -> tuple[float, float, float]:
        """The commanded (vx, vy, yaw rate) at time ``t_s`` [s]."""
        current = (0.0, 0.0, 0.0)
        for t_start, vx, vy, wz in self.commands:
            if t_s + 1e-9 < t_start:
                break
            current = (vx, vy, wz)
        return current


@dataclass(frozen=True)
class TickContext:
    """What a per-tick hook sees. Returning an array from the hook replaces the torque command [N m].
    contacts: the true foot contacts at the tick (``Simulation.foot_contacts``, leg order)."""

    t_s: float
    tick: int
    core: BridgeCore
    controller: LocomotionController
    output: TickOutput
    state: RobotState
    contacts: list


TickHook = Callable[[TickContext], "np.ndarray | None"]
StepHook = Callable[[float, RobotState, BridgeCore], None]
"""Called after every physics step with (sim time [s], the new ground-truth state, the bridge core)."""


@dataclass
class ClosedLoopLog:
    """Samples at the control rate (250 Hz). Shapes: (N,), (N, 3), (N, 4), (N, 4, 3), (N, 12)."""

    t: np.ndarray  # [s] sim time
    base_position: np.ndarray  # (N, 3) [m]
    base_rpy: np.ndarray  # (N, 3) [rad] roll, pitch, yaw (ZYX, yaw unwrapped)
    base_position_des: np.ndarray  # (N, 3) [m] desired base origin
    rpy_des: np.ndarray  # (N, 3) [rad] desired roll, pitch, yaw (yaw unwrapped)
    com: np.ndarray  # (N, 3) [m]
    com_des: np.ndarray  # (N, 3) [m]
    com_velocity: np.ndarray  # (N, 3) [m/s]
    com_velocity_des: np.ndarray  # (N, 3) [m/s] desired CoM velocity (incl. the crawl's CoM shift)
    trunk_height: np.ndarray  # (N,) [m] base origin above the terrain under it
    velocity_h: np.ndarray  # (N, 3) actual (vx, vy [m/s], yaw rate [rad/s]), horizontal frame
    cmd_profile: np.ndarray  # (N, 3) raw command (vx, vy, yaw rate) of the profile
    cmd_velocity_h: np.ndarray  # (N, 3) rate-limited command the trunk reference integrates
    stance: np.ndarray  # (N, 4) bool, planned stance
    normals: np.ndarray  # (N, 4, 3) terrain normals given to the WBC
    wbc_forces: np.ndarray  # (N, 4, 3) [N] WBC ground reaction forces on the feet
    wrench_des: np.ndarray  # (N, 6) [N, N m] desired centroidal wrench (world, about the CoM) of the trunk task
    wrench_wbc: np.ndarray  # (N, 6) [N, N m] centroidal wrench of the WBC's forces (what the QP delivered)
    slacks: np.ndarray  # (N, 4, 3) [m/s^2] swing-task slacks
    tau_wbc: np.ndarray  # (N, 12) [N m] WBC torques
    tau_cmd: np.ndarray  # (N, 12) [N m] torques submitted (after the hook)
    tau_measured: np.ndarray  # (N, 12) [N m] torques the actuators delivered (last step)
    qp_status: np.ndarray  # (N,) int OSQP status value (-1: fallback)
    qp_iterations: np.ndarray  # (N,) int
    fallback: np.ndarray  # (N,) bool QP not solved, previous solution decayed
    qp_solve_time: np.ndarray  # (N,) [s]
    joint_position: np.ndarray  # (N, 12) [rad]
    joint_velocity: np.ndarray  # (N, 12) [rad/s]
    foot_position: np.ndarray  # (N, 4, 3) [m] true foot-sphere centres
    foot_position_des: np.ndarray  # (N, 4, 3) [m] desired foot centres (stance: touchdown sample)
    foot_contact: np.ndarray  # (N, 4) bool, true contact with the ground
    contact_force: np.ndarray  # (N, 4, 3) [N] true ground reaction forces on the feet
    foot_slip_velocity: np.ndarray  # (N, 4, 3) [m/s] velocity of the foot material point at the contact
    body_contact: np.ndarray  # (N,) bool, a non-foot link touches the ground
    power: np.ndarray  # (N,) [W] sum over joints of |tau_measured * qd| (mechanical power)
    terrain_stiffness: np.ndarray  # (N, 4) [N/m] true normal stiffness under each foot (nan: at a boundary)
    penetration: np.ndarray  # (N, 4) [m] true penetration of each foot sphere along the normal (<0: above)
    penetration_des: np.ndarray  # (N, 4) [m] c3WBC desired penetration along the normal (0: rigid / swing)
    impedance_stiffness: np.ndarray  # (N, 4) [N/m] stiffness the c3WBC used (nan: none given)
    tce_stiffness: np.ndarray  # (N, 4) [N/m] TCE estimate (nan: no TCE / no estimate yet)
    tce_damping: np.ndarray  # (N, 4) [N s/m]
    tce_confidence: np.ndarray  # (N, 4) [0, 1]
    tce_in_contact: np.ndarray  # (N, 4) bool, TCE contact status (estimated force above threshold)
    meta: dict[str, object] = field(default_factory=dict)

    @property
    def fell(self) -> bool:
        return bool(self.meta.get("fell", False))

    @property
    def dt(self) -> float:
        return float(self.meta["control_period_s"])

    def after(self, t_s: float) -> np.ndarray:
        """Boolean mask of the samples at or after ``t_s`` [s]."""
        return self.t >= t_s - 1e-9

    def save_npz(self, path: str | Path) -> None:
        arrays = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "meta"}
        np.savez_compressed(path, **arrays)


def _rpy(quat_xyzw: np.ndarray) -> np.ndarray:
    x, y, z, w = quat_xyzw
    R20 = 2 * (x * z - y * w)
    R21, R22 = 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)
    R10, R00 = 2 * (x * y + z * w), 1 - 2 * (y * y + z * z)
    return np.array([math.atan2(R21, R22), -math.asin(max(-1.0, min(1.0, R20))), math.atan2(R10, R00)])


def _to_horizontal(vector_xy: np.ndarray, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([c * vector_xy[0] + s * vector_xy[1], -s * vector_xy[0] + c * vector_xy[1]])


class _Recorder:
    """Collects one sample per control tick and stacks them into a ClosedLoopLog."""

    def __init__(self) -> None:
        self.rows: dict[str, list[np.ndarray]] = {f.name: [] for f in fields(ClosedLoopLog) if f.name != "meta"}

    def add(self, **values: object) -> None:
        for key, value in values.items():
            self.rows[key].append(np.asarray(value))

    def log(self, meta: dict[str, object]) -> ClosedLoopLog:
        stacked = {key: np.array(rows) for key, rows in self.rows.items()}
        for key in ("base_rpy", "rpy_des"):
            if len(stacked[key]):
                stacked[key][:, 2] = np.unwrap(stacked[key][:, 2])
        return ClosedLoopLog(**stacked, meta=meta)


def _foot_slip_velocity(sim: Simulation, contacts: list) -> np.ndarray:
    """Velocity [m/s] of the foot-sphere material point at the contact (zero when not in contact)."""
    radius = sim.description.foot_radius_m
    slip = np.zeros((NUM_LEGS, 3))
    for leg, (link, contact) in enumerate(zip(sim.foot_links, contacts)):
        if not contact.in_contact:
            continue
        omega = np.array(sim.client.getLinkState(sim.robot, link, computeLinkVelocity=1)[7])
        slip[leg] = contact.velocity_m_s + np.cross(omega, -radius * contact.normal)
    return slip


def _stiffness_under_feet(course: Course, contacts: list, reach_m: float) -> np.ndarray:
    """True normal stiffness [N/m] under each foot; NaN where ground of another stiffness lies within
    ``reach_m`` (the sphere may touch the neighbouring patch's side: a mixed contact)."""
    offsets = np.array([[0.0, 0.0], [reach_m, 0.0], [-reach_m, 0.0], [0.0, reach_m], [0.0, -reach_m]])
    xy = np.array([c.position_m[:2] for c in contacts])[:, None, :] + offsets[None]
    k = np.asarray(course.properties_array(xy[..., 0].ravel(), xy[..., 1].ravel()).stiffness_n_per_m)
    k = k.reshape(len(contacts), len(offsets))
    return np.where(np.all(k == k[:, :1], axis=1), k[:, 0], np.nan)


def _true_penetration(contacts: list, course: Course, radius: float) -> np.ndarray:
    """Penetration [m] of each foot sphere into the undeformed surface along its normal (< 0: above)."""
    out = np.zeros(NUM_LEGS)
    for leg, contact in enumerate(contacts):
        x, y = float(contact.position_m[0]), float(contact.position_m[1])
        n = np.asarray(course.normal(x, y), dtype=float).reshape(3)
        out[leg] = foot_penetration(contact.position_m, radius, float(course.height(x, y)), n)
    return out


def run_closed_loop(config: ClosedLoopConfig, hook: TickHook | None = None,
                    step_hook: StepHook | None = None) -> ClosedLoopLog:
    """Run ``config`` and return its log; ``hook`` is called every control tick (see TickContext),
    ``step_hook`` after every physics step (e.g. to record the 1 kHz sensors)."""
    description = load_robot_description(config.robot)
    model = RobotModel(description)
    gait = PRESETS[config.gait] if isinstance(config.gait, str) else config.gait
    settings = config.settings or WbcSettings()
    if abs(settings.control_period_s - config.physics_dt_s * config.control_decimation) > 1e-12:
        raise InputError(
            f"closed loop '{config.name}': WbcSettings.control_period_s "
            f"{settings.control_period_s} s differs from the control period "
            f"{config.physics_dt_s * config.control_decimation} s"
        )
    controller = LocomotionController(model, gait, gains=config.gains, settings=settings, motion=config.motion)
    course = config.course if isinstance(config.course, Course) else load_course(config.course)
    sim = Simulation(
        description,
        course,
        time_step_s=config.physics_dt_s,
        effects=config.effects,
        initial_xy=config.initial_xy,
        initial_yaw_rad=config.initial_yaw_rad,
    )
    core = BridgeCore(sim)
    nominal = controller.motion.nominal_height_m

    def height_fn(x: float, y: float) -> float:
        return float(course.height(x, y))

    def normal_fn(x: float, y: float) -> np.ndarray:
        return np.asarray(course.normal(x, y), dtype=float).reshape(3)

    height_fn.many = course.height  # type: ignore[attr-defined]  # several points in one look-up
    normal_fn.many = course.normal  # type: ignore[attr-defined]

    if config.trunk_oscillation is not None:
        controller.motion.set_trunk_oscillation(config.trunk_oscillation)
    tce = None
    if config.impedance_source == "tce":  # the TCE ticks with the controller, on the ground-truth base state
        tce = TceDriver(RobotModel(description), config.tce, period_s=config.physics_dt_s * config.control_decimation)
        tce.set_terrain(height_fn, normal_fn)
    impedance_gate = ImpedanceGate(config.terrain_stiffness_n_per_m, config.terrain_damping_ns_per_m,
                                   config.impedance_min_confidence, config.impedance_hold_limit_s)
    fixed = TerrainImpedance(np.full(NUM_LEGS, config.terrain_stiffness_n_per_m),
                             np.full(NUM_LEGS, config.terrain_damping_ns_per_m))
    radius = description.foot_radius_m
    nan4 = np.full(NUM_LEGS, np.nan)

    estimated = _EstimatorInTheLoop(config, description, sim) if config.state_estimator is not None else None
    # As in the wbc node: on the estimate, the world-frame map is shifted into the estimate's z frame.
    aligner = HeightmapAligner() if estimated is not None else None
    control_height_fn = aligner.aligned(height_fn) if aligner is not None else height_fn

    recorder = _Recorder()
    n_steps = int(round(config.duration_s / config.physics_dt_s))
    decimation = int(config.control_decimation)
    steps_per_second = int(round(1.0 / config.physics_dt_s))
    fell, fall_time, fall_reason = False, None, ""
    fallbacks = 0
    wall_start = time.perf_counter()
    try:
        for k in range(n_steps):
            if k % decimation == 0:
                t = k * config.physics_dt_s
                state = sim.robot_state()
                contacts = sim.foot_contacts()  # the same physics state for the controller, hook and log
                truth = BaseState(
                    state.base_position_m, state.base_quat_xyzw, state.base_lin_vel_m_s, state.base_ang_vel_rad_s)
                base = truth if estimated is None else estimated.base
                cmd = config.command_at(t)
                impedance = None if config.impedance_source == "none" else fixed
                tce_k, tce_d, tce_conf, tce_contact = nan4, nan4, np.zeros(NUM_LEGS), np.zeros(NUM_LEGS, bool)
                if tce is not None:
                    tce_tick = tce.step(t, truth, state.joint_position_rad, state.joint_velocity_rad_s,
                                        state.joint_torque_nm)
                    tce_k, tce_d = tce_tick.stiffness_n_per_m, tce_tick.damping_ns_per_m
                    tce_conf, tce_contact = tce_tick.confidence, tce_tick.in_contact
                    impedance = impedance_gate.update(tce_k, tce_d, tce_tick.valid, tce_conf,
                                                      np.array([e.rigid for e in tce_tick.estimates]), t)
                    if estimated is not None:
                        estimated.stream.impedance = legs_from_impedance_arrays(
                            tce_k, tce_d, tce_tick.valid, np.array([normal_fn(*c.position_m[:2]) for c in contacts]),
                            confidence=tce_conf, rigid=np.array([e.rigid for e in tce_tick.estimates]))
                touching = (np.array([c.in_contact for c in contacts], dtype=bool)
                            if config.contact_feedback else None)
                out = controller.tick(
                    t, base, state.joint_position_rad, state.joint_velocity_rad_s, cmd, control_height_fn,
                    normal_fn, impedance=impedance, foot_contact=touching,
                )
                if aligner is not None:
                    aligner.update(t, out.measured.foot_positions, out.targets.load_factor, radius, height_fn)
                tau = out.tau
                if hook is not None:
                    replaced = hook(TickContext(t, k // decimation, core, controller, out, state, contacts))
                    if replaced is not None:
                        tau = np.asarray(replaced, dtype=float)
                core.commands.submit(sim.time_ns, description.joint_names, tau)
                body = bool(sim.body_ground_contact())
                rpy = _rpy(state.base_quat_xyzw)
                trunk = out.targets.trunk
                height = float(state.base_position_m[2] - height_fn(*state.base_position_m[:2]))
                sol = out.solution
                fallbacks += int(sol.fallback)
                recorder.add(
                    t=t,
                    base_position=state.base_position_m,
                    base_rpy=rpy,
                    base_position_des=trunk.base_position,
                    rpy_des=trunk.rpy,
                    com=out.measured.com,
                    com_des=trunk.com_position,
                    com_velocity=out.measured.com_velocity,
                    com_velocity_des=trunk.com_velocity,
                    trunk_height=height,
                    velocity_h=np.r_[_to_horizontal(state.base_lin_vel_m_s[:2], rpy[2]), state.base_ang_vel_rad_s[2]],
                    cmd_profile=np.asarray(cmd),
                    cmd_velocity_h=np.r_[
                        _to_horizontal(trunk.command_velocity_world[:2], rpy[2]), trunk.command_yaw_rate
                    ],
                    stance=out.targets.stance,
                    normals=out.targets.normals,
                    wbc_forces=sol.forces,
                    wrench_des=sol.desired_wrench,
                    wrench_wbc=sol.delivered_wrench,
                    slacks=sol.slacks,
                    tau_wbc=sol.tau,
                    tau_cmd=tau,
                    tau_measured=state.joint_torque_nm,
                    qp_status=sol.status_val,
                    qp_iterations=sol.iterations,
                    fallback=sol.fallback,
                    qp_solve_time=sol.solve_time_s,
                    joint_position=state.joint_position_rad,
                    joint_velocity=state.joint_velocity_rad_s,
                    foot_position=np.array([c.position_m for c in contacts]),
                    foot_position_des=out.targets.foot_position,
                    foot_contact=np.array([c.in_contact for c in contacts]),
                    contact_force=np.array([c.force_n for c in contacts]),
                    foot_slip_velocity=_foot_slip_velocity(sim, contacts),
                    body_contact=body,
                    power=float(np.sum(np.abs(state.joint_torque_nm * state.joint_velocity_rad_s))),
                    terrain_stiffness=_stiffness_under_feet(course, contacts, radius + BOUNDARY_MARGIN_M),
                    penetration=_true_penetration(contacts, course, radius),
                    penetration_des=np.einsum("lk,lk->l", sol.extras.get("penetration", np.zeros((NUM_LEGS, 3))),
                                              out.targets.normals),
                    impedance_stiffness=nan4 if impedance is None else impedance.stiffness_normal,
                    tce_stiffness=tce_k,
                    tce_damping=tce_d,
                    tce_confidence=tce_conf,
                    tce_in_contact=tce_contact,
                )
                if not fell and (height < FALL_HEIGHT_FRACTION * nominal or body):
                    fell, fall_time = True, t
                    fall_reason = "body-ground contact" if body else f"trunk height {height:.3f} m"
                    if config.progress:
                        sys.stderr.write(f"[{config.name}] FELL at t={t:.2f} s ({fall_reason})\n")
                    if config.stop_on_fall:
                        break
            stepped = core.step()
            if estimated is not None:
                estimated.add((k + 1) * config.physics_dt_s, stepped)
            if step_hook is not None:
                step_hook((k + 1) * config.physics_dt_s, stepped, core)
            if config.progress and (k + 1) % steps_per_second == 0:
                st = sim.robot_state()
                elapsed = time.perf_counter() - wall_start
                sys.stderr.write(
                    f"[{config.name}] t={(k + 1) * config.physics_dt_s:5.1f}/{config.duration_s:.1f} s  "
                    f"x={st.base_position_m[0]:+.2f} y={st.base_position_m[1]:+.2f} "
                    f"z={st.base_position_m[2]:.3f} m  vx={st.base_lin_vel_m_s[0]:+.2f} m/s  "
                    f"fallbacks={fallbacks}  wall={elapsed:.0f} s\n"
                )
    finally:
        sim.close()
    wall = time.perf_counter() - wall_start
    meta: dict[str, object] = {
        "name": config.name,
        "course": course.name,
        "gait": gait.name,
        "duration_s": config.duration_s,
        "commands": [list(c) for c in config.commands],
        "nominal_height_m": nominal,
        "control_period_s": config.physics_dt_s * decimation,
        "fell": fell,
        "fall_time_s": fall_time,
        "fall_reason": fall_reason,
        "wall_time_s": wall,
        "joint_names": list(description.joint_names),
        "friction_coefficient_wbc": settings.friction_coefficient,
        "contact_model": settings.contact_model,
        "impedance_source": config.impedance_source,
        "real_time_factor": (n_steps * config.physics_dt_s / wall) if wall > 0 else None,
    }
    return recorder.log(meta)


class _EstimatorInTheLoop:
    """The state estimator fed by the simulated IMU and joints every physics step, through the node's
    streaming tick: it starts at the true pose of t = 0 and ticks on its own grid."""

    def __init__(self, config: ClosedLoopConfig, description, sim: Simulation) -> None:
        assert config.state_estimator is not None
        from tal_sim_bridge.bridge_core import ImuModel

        self.imu = ImuModel(sim.effects, gyro_noise_std_rad_s=config.imu_noise[0],
                            accel_noise_std_m_s2=config.imu_noise[1])
        state = sim.robot_state()
        self.stream = StreamingEstimator(RobotModel(description), config.state_estimator,
                                         initial_position=state.base_position_m,
                                         initial_world_R_base=rotation_from_quat_xyzw(state.base_quat_xyzw))
        # The state of t = 0 is the first tick's joint sample; the IMU's first sample comes with the first step.
        self.stream.add_joints(0, lambda: (state.joint_position_rad, state.joint_velocity_rad_s,
                                           state.joint_torque_nm), t_s=0.0)
        self.base = BaseState(state.base_position_m, state.base_quat_xyzw, np.zeros(3), np.zeros(3))

    def add(self, t_s: float, state: RobotState) -> None:
        f, w = self.imu.measure(state)
        for out in self.stream.add_sample(round(t_s * 1e9), f, w, state.joint_position_rad,
                                          state.joint_velocity_rad_s, state.joint_torque_nm, t_s=t_s):
            if out.estimate is not None:
                self.base = out.estimate.base_state


# -- metrics on a log ---------------------------------------------------------------------------------
def tracking_metrics(log: ClosedLoopLog, settle_s: float = 2.0) -> dict[str, float]:
    """Mean absolute tracking errors after ``settle_s`` [s], QP statistics and distance travelled.

    ``velocity_mae_m_s``: horizontal CoM velocity vs the trunk reference's (the commanded velocity plus
    the crawl's CoM shift); ``velocity_vs_command_mae_m_s``: base velocity vs the rate-limited command
    (includes the designed sway); ``mean_vx_h_m_s``: mean forward velocity, horizontal frame."""
    mask = log.after(settle_s)
    if not np.any(mask):
        mask = np.ones_like(log.t, dtype=bool)
    height_err = np.abs(log.base_position_des[mask, 2] - log.base_position[mask, 2])
    vel_err = np.linalg.norm(log.com_velocity_des[mask, :2] - log.com_velocity[mask, :2], axis=1)
    cmd_err = np.linalg.norm(log.cmd_velocity_h[mask, :2] - log.velocity_h[mask, :2], axis=1)
    yaw_rate_err = np.abs(log.cmd_velocity_h[mask, 2] - log.velocity_h[mask, 2])
    com_err = np.linalg.norm(log.com_des[mask] - log.com[mask], axis=1)
    rpy_err = np.abs(log.rpy_des[mask] - log.base_rpy[mask])
    xy = log.base_position[:, :2]
    t_window = log.t[mask]
    span = float(t_window[-1] - t_window[0]) if len(t_window) > 1 else 0.0
    xy_window = xy[mask]
    mean_vx_h = float(np.mean(log.velocity_h[mask, 0]))
    return {
        "fell": float(log.fell),
        "fall_time_s": float("nan") if log.meta.get("fall_time_s") is None else float(log.meta["fall_time_s"]),
        "sim_time_s": float(log.t[-1] + log.dt) if len(log.t) else 0.0,
        "height_mae_m": float(np.mean(height_err)),
        "velocity_mae_m_s": float(np.mean(vel_err)),
        "velocity_vs_command_mae_m_s": float(np.mean(cmd_err)),
        "yaw_rate_mae_rad_s": float(np.mean(yaw_rate_err)),
        "mean_vx_h_m_s": mean_vx_h,
        "mean_cmd_vx_h_m_s": float(np.mean(log.cmd_velocity_h[mask, 0])),
        "mean_yaw_rate_rad_s": float(np.mean(log.velocity_h[mask, 2])),
        "com_error_mean_m": float(np.mean(com_err)),
        "roll_mae_rad": float(np.mean(rpy_err[:, 0])),
        "pitch_mae_rad": float(np.mean(rpy_err[:, 1])),
        "roll_error_max_rad": float(np.max(rpy_err[:, 0])),
        "pitch_error_max_rad": float(np.max(rpy_err[:, 1])),
        "fallbacks": float(np.sum(log.fallback)),
        "qp_iterations_mean": float(np.mean(log.qp_iterations)),
        "qp_iterations_max": float(np.max(log.qp_iterations)),
        "net_displacement_m": float(np.linalg.norm(xy[-1] - xy[0])),
        "path_length_m": float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1))),
        "path_length_1s_m": float(
            np.sum(np.linalg.norm(np.diff(xy[:: max(1, int(round(1.0 / log.dt)))], axis=0), axis=1))
        ),
        "window_displacement_m": float(np.linalg.norm(xy_window[-1] - xy_window[0])) if span else 0.0,
        "window_s": span,
    }


def stance_slip(log: ClosedLoopLog) -> dict[str, np.ndarray]:
    """Horizontal slip of the feet while in true contact, per leg [m].

    ``centre``: summed horizontal displacement of the foot-sphere centre between consecutive samples in
    contact (includes the sphere rolling as the shin turns); ``contact_point``: integral of the horizontal
    speed of the foot's material point at the contact (pure slip, rolling excluded)."""
    both = log.foot_contact[1:] & log.foot_contact[:-1]
    step = np.linalg.norm(np.diff(log.foot_position[:, :, :2], axis=0), axis=2)
    centre = np.sum(np.where(both, step, 0.0), axis=0)
    speed = np.linalg.norm(log.foot_slip_velocity[:, :, :2], axis=2)
    contact_point = np.sum(np.where(log.foot_contact, speed, 0.0), axis=0) * log.dt
    return {"centre": centre, "contact_point": contact_point}
