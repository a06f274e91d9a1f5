"""HyQ in MuJoCo: a second physics engine, the *measured* side of tal_sim2real's gap workflow (issue 34 item 5).

The robot is the URDF the bridge loads (``tal_core.robot_description``, from example-robot-data), compiled by
MuJoCo's own URDF importer with these changes, each where MuJoCo cannot take the file as it is:

  * mesh geometry (``.dae``: trunk, hip and upper-leg collisions, every visual) is dropped: MuJoCo reads no
    COLLADA. The contacts that matter stay as the URDF gives them: the foot spheres (r = 0.02175 m). The
    lower-leg cylinders are kept but collide with nothing, as in the bridge (it filters shin/ground
    collisions); the robot does not collide with itself (PyBullet's default too). A fall is a trunk height
    below ``FALL_HEIGHT_FRACTION`` of the nominal (the bridge also counts body/ground contacts).
  * links whose inertia tensor is not positive definite (base_link, the feet, trunk_imu: 1e-6 kg with every
    entry 1e-6 kg m^2, off-diagonals included) get their off-diagonal entries set to zero; the masses stay,
    so the total mass is the URDF's (86.774 kg).
  * a free joint on the root link (``base_link``), whose qpos is the base frame's pose (MuJoCo's
    quaternion is w, x, y, z; converted to ROS x, y, z, w here), a flat plane at the course's height with its
    friction, and one torque motor per canonical joint (gear 1, control range = the robot's torque limits).

Kept from the URDF as MuJoCo imports it (the physical model, not the PyBullet model): joint damping
0.1 N m s/rad (the bridge zeroes it), no armature, no joint friction loss, the joint position limits.
MuJoCo's normal contact is its own: a soft constraint with the default ``solref`` (0.02 s, damping ratio 1)
and ``solimp`` (0.9, 0.95, 0.001), whose force for a given sinkage depends on the effective mass the contact
sees (a loaded HyQ foot sinks ~14 mm); PyBullet's "rigid" ground is a 2e6 N/m, 400 N s/m penalty per contact
point (~0.2 mm). That difference is what the workflow should find. The friction is not left at MuJoCo's
default (pyramidal cone, impratio 1): with it a loaded stance foot, far inside the friction cone (mu = 1), crept
forward with the trunk at ~0.28 m/s (93 mm per stance against 2.7 mm in PyBullet, measured), which is not
Coulomb friction but the default's soft friction constraint; an elliptic cone with impratio 100 holds it
(3.4 mm per stance, rolling of the sphere included). Time step 1 ms, Euler.

The torque path is the bridge's (``ActuatorModel`` of the nominal effects: the held command clipped at the
joint-angle-dependent limits); the measured joint torque is the delivered torque, as the bridge reports it.
The controller is tal's sWBC (rigid contact model) on the ground-truth state at 250 Hz, built as
``tal_lab.closed_loop`` builds it, and the bag is written by the datasets' recorder (``tal_lab.datasets``):
the same topics, rates, message layout and sensor-noise model as the hidden-effect datasets.
"""

from __future__ import annotations

import logging
import math
import types
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
from tqdm import tqdm

from tal_control.locomotion import LocomotionController
from tal_control.motion.gait import PRESETS
from tal_control.wbc import WbcSettings
from tal_core.legs import LEGS
from tal_core.robot_description import RobotDescription, load_robot_description
from tal_core.robot_model import RobotModel
from tal_core.ros.bag_io import BagWriter
from tal_core.rotations import rotation_from_quat_xyzw
from tal_core.state import BaseState
from tal_core.terrain import Course, load_course
from tal_sim_bridge.effects import ActuatorModel, ModelEffects
from tal_sim_bridge.physics import GRAVITY_M_S2, FootContact, RobotState

from .closed_loop import FALL_HEIGHT_FRACTION, ClosedLoopConfig
from .datasets import TOPIC_TYPES, DatasetError, DatasetRecorder, DatasetScenario

LOG = logging.getLogger("tal.lab.mujoco")

MUJOCO_VERSION = mujoco.__version__
TIME_STEP_S = 1e-3
CONTROL_DECIMATION = 4  # 250 Hz controller, as the bridge's closed loop
DURATION_S = 8.0
COMMANDS = ((0.0, 0.2, 0.0, 0.0),)  # (t_start [s], vx [m/s], vy [m/s], yaw rate [rad/s]): straight trot
JOINT_NOISE = (2e-4, 0.02, 0.3)  # [rad], [rad/s], [N m]: the hidden-effect datasets' sensor noise
FRICTION_CONE = mujoco.mjtCone.mjCONE_ELLIPTIC
IMPRATIO = 100.0
"""Coulomb friction as MuJoCo models it without creep (module docstring): elliptic cone, friction impedance 100x
the normal one (MuJoCo's impratio; the setting of MuJoCo Menagerie's quadrupeds)."""
_INERTIA_KEYS = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")


class MujocoModelError(DatasetError):
    """The robot cannot be converted to MuJoCo, or the MuJoCo run is not valid (the robot fell)."""


def mujoco_urdf(description: RobotDescription) -> tuple[str, list[str]]:
    """The URDF text MuJoCo compiles (see the module docstring) and the links whose inertia was fixed."""
    root = ET.parse(description.urdf_path).getroot()
    fixed = []
    for link in root.iter("link"):
        for tag in ("visual", "collision"):
            for element in list(link.findall(tag)):
                if tag == "visual" or element.find("geometry/mesh") is not None:
                    link.remove(element)
        tensor = link.find("inertial/inertia")
        if tensor is None:
            continue
        ixx, ixy, ixz, iyy, iyz, izz = (float(tensor.get(k, "0")) for k in _INERTIA_KEYS)
        inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        if np.linalg.eigvalsh(inertia).min() <= 0.0:
            for key in ("ixy", "ixz", "iyz"):
                tensor.set(key, "0")
            fixed.append(link.get("name", ""))
    extension = ET.SubElement(root, "mujoco")
    # fusestatic off: a root link without a joint would be fused into the world before the free joint exists
    ET.SubElement(extension, "compiler", {"discardvisual": "true", "fusestatic": "false", "balanceinertia": "false"})
    return ET.tostring(root, encoding="unicode"), fixed


@dataclass(frozen=True)
class MujocoRobot:
    """A compiled MuJoCo model of the robot with tal's indices (canonical joint order, leg order)."""

    model: mujoco.MjModel
    joint_names: tuple[str, ...]
    qpos_adr: np.ndarray  # (12,) qpos index of each canonical joint
    dof_adr: np.ndarray  # (12,) qvel index of each canonical joint
    actuator_ids: np.ndarray  # (12,) motor of each canonical joint
    base_body: int
    foot_geoms: tuple[int, ...]  # foot spheres, leg order
    foot_bodies: tuple[int, ...]
    floor_geom: int
    inertia_fixed: tuple[str, ...]

    @property
    def total_mass_kg(self) -> float:
        return float(self.model.body_subtreemass[0])


def build_robot(description: RobotDescription, course: Course, time_step_s: float = TIME_STEP_S) -> MujocoRobot:
    """Compile ``description`` into MuJoCo on ``course`` (flat only: one plane at its default height)."""
    if course.patches:
        raise MujocoModelError(f"course '{course.name}' has patches; the MuJoCo model has a flat floor only")
    text, fixed = mujoco_urdf(description)
    try:
        spec = mujoco.MjSpec.from_string(text)
    except ValueError as exc:
        raise MujocoModelError(f"MuJoCo cannot read {description.urdf_path}: {exc}") from exc
    spec.option.timestep = float(time_step_s)
    spec.option.gravity = [0.0, 0.0, -GRAVITY_M_S2]
    spec.option.cone = FRICTION_CONE
    spec.option.impratio = IMPRATIO
    base = spec.body(description.base_frame)
    if base is None or base.parent.name != "world":
        raise MujocoModelError(f"base frame '{description.base_frame}' is not the URDF's root link")
    base.add_freejoint(name="floating_base_free")
    friction = float(course.default.friction)
    feet = [spec.body(description.foot_frames[leg]) for leg in LEGS]
    for leg, body in zip(LEGS, feet):
        spheres = [g for g in body.geoms if g.type == mujoco.mjtGeom.mjGEOM_SPHERE]
        if len(spheres) != 1:
            raise MujocoModelError(f"foot '{body.name}' has {len(spheres)} collision spheres, expected 1")
        spheres[0].name = f"{leg.name.lower()}_foot_sphere"
    for geom in spec.geoms:  # feet collide with the floor only; everything else with nothing (see docstring)
        is_foot = geom.name.endswith("_foot_sphere")
        geom.contype, geom.conaffinity = (1, 0) if is_foot else (0, 0)
        if is_foot:
            geom.friction = [friction, geom.friction[1], geom.friction[2]]
    floor = spec.worldbody.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[0.0, 0.0, 1.0],
        pos=[0.0, 0.0, float(course.default.height_m)],
    )
    floor.contype, floor.conaffinity = 0, 1
    floor.friction = [friction, floor.friction[1], floor.friction[2]]
    tau_min, tau_max = description.torque_limits(description.nominal_joint_positions_rad)
    for name, low, high in zip(description.joint_names, tau_min, tau_max):
        motor = spec.add_actuator(name=f"{name}_motor", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        motor.gear = [1.0, 0, 0, 0, 0, 0]
        motor.ctrllimited = True
        motor.ctrlrange = [float(low), float(high)]
    model = spec.compile()
    joint_ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in description.joint_names]
    if min(joint_ids) < 0:
        raise MujocoModelError(f"MuJoCo model lacks joints of {description.joint_names}")
    geom = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"{leg.name.lower()}_foot_sphere") for leg in LEGS]
    return MujocoRobot(
        model=model,
        joint_names=tuple(description.joint_names),
        qpos_adr=np.array([model.jnt_qposadr[j] for j in joint_ids]),
        dof_adr=np.array([model.jnt_dofadr[j] for j in joint_ids]),
        actuator_ids=np.array(
            [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, f"{n}_motor") for n in description.joint_names]
        ),
        base_body=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, description.base_frame),
        foot_geoms=tuple(geom),
        foot_bodies=tuple(int(model.geom_bodyid[g]) for g in geom),
        floor_geom=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor"),
        inertia_fixed=tuple(fixed),
    )


class MujocoSimulation:
    """The MuJoCo counterpart of ``tal_sim_bridge.physics.Simulation`` for a flat course: same state and
    contact records (world frame, canonical joint order), same torque path."""

    def __init__(self, description: RobotDescription, course: Course, time_step_s: float = TIME_STEP_S) -> None:
        self.description = description
        self.course = course
        self.robot = build_robot(description, course, time_step_s)
        self.model = self.robot.model
        self.data = mujoco.MjData(self.model)
        self.time_step_s = float(self.model.opt.timestep)
        tau_min, tau_max = description.torque_limits(description.nominal_joint_positions_rad)
        self.actuators = ActuatorModel(ModelEffects(), self.time_step_s, tau_min, tau_max)
        self.step_count = 0
        self.reset()

    @property
    def time_ns(self) -> int:
        return self.step_count * round(self.time_step_s * 1e9)

    def reset(self, initial_xy: tuple[float, float] = (0.0, 0.0)) -> None:
        """Nominal pose, level base, the lowest foot touching the floor (as the bridge's reset)."""
        d, r = self.data, self.robot
        mujoco.mj_resetData(self.model, d)
        d.qpos[0:3] = [initial_xy[0], initial_xy[1], 0.0]
        d.qpos[3:7] = [1.0, 0.0, 0.0, 0.0]
        d.qpos[r.qpos_adr] = self.description.nominal_joint_positions_rad
        mujoco.mj_kinematics(self.model, d)
        feet_z = d.geom_xpos[list(r.foot_geoms), 2]
        d.qpos[2] = float(self.course.default.height_m) - float(np.min(feet_z)) + self.description.foot_radius_m
        mujoco.mj_forward(self.model, d)
        self.nominal_base_height_m = float(d.qpos[2] - self.course.default.height_m)
        self.actuators.reset()
        self._last_torque = np.zeros(len(r.joint_names))
        self._prev_base_vel = np.zeros(3)
        self._base_acc = np.zeros(3)
        self.step_count = 0

    def joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        return self.data.qpos[self.robot.qpos_adr].copy(), self.data.qvel[self.robot.dof_adr].copy()

    def base_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Base frame position [m], quaternion (x, y, z, w), linear and angular velocity [m/s, rad/s], world
        frame. MuJoCo's free joint: qvel[0:3] world linear velocity of the body origin, qvel[3:6] angular
        velocity in the body frame."""
        qpos, qvel = self.data.qpos, self.data.qvel
        w, x, y, z = qpos[3:7]
        quat = np.array([x, y, z, w]) / math.sqrt(w * w + x * x + y * y + z * z)
        world_R_base = rotation_from_quat_xyzw(quat)
        return qpos[0:3].copy(), quat, qvel[0:3].copy(), world_R_base @ qvel[3:6]

    def step(self, commanded_torque_nm: np.ndarray) -> RobotState:
        """One physics step with the commanded torques [N m] through the bridge's actuator model."""
        q, _ = self.joint_state()
        tau_min, tau_max = self.description.torque_limits(q)
        delivered = self.actuators.delivered_torque(np.asarray(commanded_torque_nm, dtype=float), tau_min, tau_max)
        self.data.ctrl[self.robot.actuator_ids] = delivered
        mujoco.mj_step(self.model, self.data)
        self.step_count += 1
        self._last_torque = delivered
        velocity = self.base_state()[2]
        self._base_acc = (velocity - self._prev_base_vel) / self.time_step_s
        self._prev_base_vel = velocity
        return self.robot_state()

    def robot_state(self) -> RobotState:
        position, quat, lin, ang = self.base_state()
        q, qd = self.joint_state()
        return RobotState(position, quat, lin, ang, self._base_acc.copy(), q, qd, self._last_torque.copy())

    def foot_contacts(self) -> list[FootContact]:
        """Ground-truth contact per foot (leg order): the summed floor force on the foot [N], the deepest
        penetration [m], normal, sphere centre and its velocity (world frame)."""
        d, r = self.data, self.robot
        force = np.zeros((len(r.foot_geoms), 3))
        depth = np.zeros(len(r.foot_geoms))
        touching = np.zeros(len(r.foot_geoms), dtype=bool)
        index = {g: i for i, g in enumerate(r.foot_geoms)}
        wrench = np.zeros(6)
        for c in range(d.ncon):
            contact = d.contact[c]
            pair = (int(contact.geom1), int(contact.geom2))
            if r.floor_geom not in pair or not (set(pair) & set(index)):
                continue
            leg = index[pair[1] if pair[0] == r.floor_geom else pair[0]]
            mujoco.mj_contactForce(self.model, d, c, wrench)
            frame = contact.frame.reshape(3, 3)  # rows: normal (geom1 -> geom2), two tangents
            on_geom2 = frame.T @ wrench[:3]
            force[leg] += on_geom2 if pair[1] == r.foot_geoms[leg] else -on_geom2
            depth[leg] = max(depth[leg], -float(contact.dist))
            touching[leg] = True
        out = []
        velocity = np.zeros(6)
        for leg, (geom, body) in enumerate(zip(r.foot_geoms, r.foot_bodies)):
            mujoco.mj_objectVelocity(self.model, d, mujoco.mjtObj.mjOBJ_BODY, body, velocity, 0)
            out.append(
                FootContact(
                    bool(touching[leg]),
                    force[leg].copy(),
                    float(depth[leg]),
                    np.array([0.0, 0.0, 1.0]),
                    d.geom_xpos[geom].copy(),
                    velocity[3:].copy(),
                )
            )
        return out

    def close(self) -> None:
        """Nothing to release (MuJoCo's model and data are freed with the objects); for symmetry with PyBullet."""


@dataclass
class MujocoRun:
    """What a recorded MuJoCo trot did: figures for the report and the checks."""

    bag: Path
    duration_s: float
    fell: bool
    fall_time_s: float | None
    net_displacement_m: float
    base_height_mean_m: float
    base_height_min_m: float
    nominal_base_height_m: float
    total_mass_kg: float
    message_counts: dict[str, int]
    inertia_fixed: tuple[str, ...]


def record_trot(
    bag: Path,
    duration_s: float = DURATION_S,
    commands: tuple = COMMANDS,
    seed: int = 0,
    course_name: str = "flat_rigid",
    progress: bool = True,
) -> MujocoRun:
    """Drive MuJoCo's HyQ with tal's sWBC (rigid contact model, ground truth, 250 Hz) through a trot and write
    the measured bag ``bag`` (replaced if it exists). Raises MujocoModelError when the robot falls."""
    import shutil

    bag = Path(bag)
    if bag.exists():
        shutil.rmtree(bag)
    bag.parent.mkdir(parents=True, exist_ok=True)
    description = load_robot_description("hyq")
    course = load_course(course_name)
    settings = WbcSettings()
    period = TIME_STEP_S * CONTROL_DECIMATION
    if abs(settings.control_period_s - period) > 1e-12:
        raise MujocoModelError(f"the WBC's control period {settings.control_period_s} s is not {period} s")
    controller = LocomotionController(RobotModel(description), PRESETS["trot"], settings=settings)
    config = ClosedLoopConfig(
        name="mujoco_trot", course=course, gait="trot", commands=commands, duration_s=duration_s, progress=False
    )
    scenario = DatasetScenario(
        "mujoco_trot",
        "HyQ trot recorded in MuJoCo",
        course,
        "trot",
        commands=config.commands,
        joint_position_noise_std_rad=JOINT_NOISE[0],
        joint_velocity_noise_std_rad_s=JOINT_NOISE[1],
        joint_effort_noise_std_nm=JOINT_NOISE[2],
    )
    sim = MujocoSimulation(description, course)
    core = types.SimpleNamespace(sim=sim)  # what the datasets' recorder reads: core.sim.foot_contacts()
    nominal = controller.motion.nominal_height_m
    ground = float(course.default.height_m)

    def height_fn(x: float, y: float) -> float:
        return float(course.height(x, y))

    def normal_fn(x: float, y: float) -> np.ndarray:
        return np.asarray(course.normal(x, y), dtype=float).reshape(3)

    n_steps = int(round(duration_s / TIME_STEP_S))
    heights, fell, fall_time = [], False, None
    tau = np.zeros(len(description.joint_names))
    with BagWriter(bag) as writer:
        for topic, type_name in TOPIC_TYPES.items():
            writer.add_topic(topic, type_name)
        recorder = DatasetRecorder(writer, scenario, config, description.joint_names, seed, course)
        start = sim.robot_state()
        recorder.on_step(0.0, start, core)
        for k in tqdm(range(n_steps), desc="MuJoCo trot", unit="step", disable=not progress, mininterval=2.0):
            if k % CONTROL_DECIMATION == 0:
                t = k * TIME_STEP_S
                state = sim.robot_state()
                base = BaseState(
                    state.base_position_m, state.base_quat_xyzw, state.base_lin_vel_m_s, state.base_ang_vel_rad_s
                )
                out = controller.tick(
                    t,
                    base,
                    state.joint_position_rad,
                    state.joint_velocity_rad_s,
                    config.command_at(t),
                    height_fn,
                    normal_fn,
                )
                tau = out.tau
                recorder.on_tick(types.SimpleNamespace(t_s=t, output=out))
                height = float(state.base_position_m[2]) - ground
                heights.append(height)
                if height < FALL_HEIGHT_FRACTION * nominal or not np.all(np.isfinite(tau)):
                    fell, fall_time = True, t
                    break
            state = sim.step(tau)
            recorder.on_step((k + 1) * TIME_STEP_S, state, core)
        counts = dict(writer.message_counts)
    final = sim.robot_state().base_position_m
    run = MujocoRun(
        bag,
        duration_s,
        fell,
        fall_time,
        float(np.linalg.norm(final[:2] - start.base_position_m[:2])),
        float(np.mean(heights)),
        float(np.min(heights)),
        nominal,
        sim.robot.total_mass_kg,
        counts,
        sim.robot.inertia_fixed,
    )
    if fell:
        raise MujocoModelError(
            f"HyQ fell in MuJoCo at t = {fall_time:.2f} s (trunk height {heights[-1]:.3f} m); "
            f"the recording {bag} is not valid"
        )
    return run
