"""PyBullet world: HyQ (or any robot description) under torque control on a course of compliant boxes.

No ROS here. One ``Simulation`` owns one PyBullet physics client. Conventions:
  * world frame z up; base pose = pose of the description's base frame (the URDF root link);
  * joint arrays in the robot's canonical order (LF, RF, LH, RH) x (HAA, HFE, KFE);
  * ground compliance: every course box gets its patch's contact stiffness [N/m] and damping [N s/m].
    Bullet combines two bodies' contact stiffness in series (1/k = 1/k_a + 1/k_b) and adds damping, so
    the feet's own URDF <contact> (30000 N/m, 1000 N s/m on HyQ) is overridden with a stiffness far above
    any ground (FOOT_CONTACT_STIFFNESS) and zero damping: the ground is then the only compliance.
  * power-law ground (``ModelEffects.ground_contact_exponent`` != 1): the boxes become rigid and each
    foot carries, every step, the secant stiffness and damping of its patch's power law at its current
    sinkage (geometric: course height + foot radius - foot centre height). Bullet re-combines the two bodies'
    contact parameters whenever it refreshes a contact point, so the change acts on the next step.
  * shins: HyQ's lower-leg collision cylinder ends at the foot centre, so on soft ground (T1: ~6 cm static
    sinkage) it would touch the ground and carry load that belongs to the foot. Lower-leg/ground
    collisions are therefore filtered out; the foot sphere is the only leg contact. Trunk, hip and
    upper-leg collisions with the ground stay on and are reported as ``body_ground_contact`` (a fall).
"""

from __future__ import annotations

import math
import re
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tal_core.legs import LEGS
from tal_core.robot_description import RobotDescription, find_example_robot_data_dir
from tal_core.terrain import Course

from ._pybullet import BulletClient, pybullet, quiet_c_output
from .effects import ActuatorModel, ModelEffects, power_law_ground_scale
from .errors import BridgeConfigError

GRAVITY_M_S2 = 9.81
FOOT_CONTACT_STIFFNESS = 1e12  # [N/m] in series with the ground: leaves the ground's stiffness intact
SOFT_BOX_STIFFNESS_N_PER_M = 1e5
"""[N/m] ground boxes softer than this are soft terrain (T1..T3): their collision boxes overlap neighbours."""
SOFT_BOX_OVERLAP_M = 0.1
"""[m] how far a soft box's collision shape reaches under the neighbouring boxes, per side."""
SHIN_LINK_SUFFIX = "lowerleg"
FORGET_CONTACTS_LIFT_M = 1e3
"""[m] base height at which no robot link's bounding box overlaps a course box (Simulation._forget_contacts)."""


@dataclass(frozen=True)
class FootContact:
    """Ground truth contact of one foot (all vectors world frame)."""

    in_contact: bool
    force_n: np.ndarray        # (3,) [N] ground reaction force acting on the foot
    penetration_m: float       # [m] depth into the ground, >= 0 (0 when not in contact)
    normal: np.ndarray         # (3,) unit contact normal pointing out of the ground
    position_m: np.ndarray     # (3,) [m] foot sphere centre
    velocity_m_s: np.ndarray   # (3,) [m/s] foot sphere centre velocity


@dataclass(frozen=True)
class RobotState:
    """Ground truth rigid-body state after a physics step."""

    base_position_m: np.ndarray      # (3,) world frame
    base_quat_xyzw: np.ndarray       # (4,) world_R_base as quaternion (x, y, z, w)
    base_lin_vel_m_s: np.ndarray     # (3,) world frame
    base_ang_vel_rad_s: np.ndarray   # (3,) world frame
    base_lin_acc_m_s2: np.ndarray    # (3,) world frame, finite difference over the last step
    joint_position_rad: np.ndarray   # (12,)
    joint_velocity_rad_s: np.ndarray  # (12,)
    joint_torque_nm: np.ndarray      # (12,) torque delivered by the actuators this step


def _prepared_urdf(description: RobotDescription, effects: ModelEffects) -> Path:
    """Write a copy of the URDF that PyBullet can load: package:// resolved, payload merged in."""
    text = description.urdf_path.read_text()
    if "package://" in text:
        share = find_example_robot_data_dir().parent
        text = re.sub(r"package://", str(share) + "/", text)
    root = ET.fromstring(text)
    if effects.payload_mass_kg > 0.0:
        _merge_payload(root, description.base_frame, effects)
    handle = tempfile.NamedTemporaryFile("w", suffix=".urdf", prefix="tal_robot_", delete=False)
    with handle:
        handle.write(ET.tostring(root, encoding="unicode"))
    return Path(handle.name)


def _merge_payload(root: ET.Element, base_frame: str, effects: ModelEffects) -> None:
    """Add a point-mass payload to the heaviest link fixed to the base (parallel-axis theorem)."""
    links = {link.get("name"): link for link in root.iter("link")}
    fixed_children = [j.find("child").get("name") for j in root.iter("joint")  # type: ignore[union-attr]
                      if j.get("type") == "fixed" and j.find("parent").get("name") == base_frame]  # type: ignore[union-attr]
    candidates = [name for name in [base_frame, *fixed_children] if links[name].find("inertial") is not None]

    def mass_of(name: str) -> float:
        return float(links[name].find("inertial").find("mass").get("value"))  # type: ignore[union-attr]

    target = max(candidates, key=mass_of)
    inertial = links[target].find("inertial")
    assert inertial is not None
    origin = inertial.find("origin")
    com = np.array([float(v) for v in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()])
    if origin is not None and any(abs(float(v)) > 1e-12 for v in origin.get("rpy", "0 0 0").split()):
        raise BridgeConfigError(f"payload: link '{target}' has a rotated inertial frame, not supported")
    mass = mass_of(target)
    tensor_element = inertial.find("inertia")
    assert tensor_element is not None
    names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    ixx, ixy, ixz, iyy, iyz, izz = (float(tensor_element.get(n, "0")) for n in names)
    inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    payload_mass = effects.payload_mass_kg
    payload_pos = com + np.asarray(effects.payload_offset_m)
    new_mass = mass + payload_mass
    new_com = (mass * com + payload_mass * payload_pos) / new_mass

    def shift(m: float, d: np.ndarray) -> np.ndarray:
        return m * (float(d @ d) * np.eye(3) - np.outer(d, d))

    new_inertia = inertia + shift(mass, com - new_com) + shift(payload_mass, payload_pos - new_com)
    inertial.find("mass").set("value", repr(new_mass))  # type: ignore[union-attr]
    if origin is None:
        origin = ET.SubElement(inertial, "origin")
    origin.set("xyz", " ".join(repr(float(v)) for v in new_com))
    origin.set("rpy", "0 0 0")
    for name, (r, c) in zip(names, ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
        tensor_element.set(name, repr(float(new_inertia[r, c])))


class Simulation:
    """A PyBullet simulation of one legged robot on one course, stepped at a fixed time step."""

    def __init__(self, description: RobotDescription, course: Course, *, time_step_s: float = 1e-3,
                 effects: ModelEffects | None = None, gui: bool = False,
                 initial_xy: tuple[float, float] = (0.0, 0.0), initial_yaw_rad: float = 0.0,
                 solver_iterations: int = 50) -> None:
        if not (0.0 < time_step_s <= 0.01):
            raise BridgeConfigError(f"time_step_s must be in (0, 0.01] s, got {time_step_s}")
        self.description = description
        self.course = course
        self.time_step_s = float(time_step_s)
        self.effects = effects or ModelEffects()
        self.step_count = 0
        with quiet_c_output():
            self.client = BulletClient(connection_mode=pybullet.GUI if gui else pybullet.DIRECT)
        self._urdf: Path | None = None
        try:  # a rejected setting (e.g. initial_xy off the course) must not leak the client or the URDF
            self.client.setGravity(0.0, 0.0, -GRAVITY_M_S2)
            self.client.setPhysicsEngineParameter(fixedTimeStep=self.time_step_s,
                                                  numSolverIterations=int(solver_iterations),
                                                  deterministicOverlappingPairs=1)
            self.ground_bodies = self._build_course()
            self._urdf = _prepared_urdf(description, self.effects)
            with quiet_c_output():
                self.robot = self.client.loadURDF(str(self._urdf), [0.0, 0.0, 1.0],
                                                  flags=pybullet.URDF_USE_INERTIA_FROM_FILE)
            self._index_links()
            # PyBullet's base pose and velocity are those of the base link's inertial (CoM) frame; a payload
            # with an offset moves that frame, so every base quantity is converted to the link frame.
            self._base_com_offset = np.array(self.client.getDynamicsInfo(self.robot, -1)[3])
            self._configure_robot()
            tau_min, tau_max = description.torque_limits(description.nominal_joint_positions_rad)
            self.actuators = ActuatorModel(self.effects, self.time_step_s, tau_min, tau_max)
            self._last_torque = np.zeros(len(self.joint_ids))
            self.reset(initial_xy, initial_yaw_rad)
        except BaseException:
            self.close()
            raise

    # -- construction ---------------------------------------------------------------------------------
    def _build_course(self) -> list[int]:
        bodies = []
        for box in self.course.primitives():
            half = list(box.half_extents_xyz)
            if box.stiffness_n_per_m < SOFT_BOX_STIFFNESS_N_PER_M and not any(box.rpy):
                # A foot sunk into soft ground near the patch's side is closer to that side face than to the
                # top, and Bullet pushes a penetrating sphere out through the nearest face. Extending soft boxes
                # under their neighbours keeps the top face the nearest (the thesis overlapped its terrains for
                # the same reason); the overlap strip is stiffer, like theirs.
                half[0] += SOFT_BOX_OVERLAP_M
                half[1] += SOFT_BOX_OVERLAP_M
            shape = self.client.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half)
            visual = self.client.createVisualShape(pybullet.GEOM_BOX, halfExtents=list(box.half_extents_xyz),
                                                   rgbaColor=_terrain_colour(box.stiffness_n_per_m))
            body = self.client.createMultiBody(
                baseMass=0.0, baseCollisionShapeIndex=shape, baseVisualShapeIndex=visual,
                basePosition=list(box.center_xyz),
                baseOrientation=self.client.getQuaternionFromEuler(list(box.rpy)))
            self._apply_box_contact(body, box.stiffness_n_per_m, box.damping_ns_per_m, box.friction)
            bodies.append(body)
        return bodies

    def _apply_box_contact(self, body: int, stiffness: float, damping: float, friction: float) -> None:
        if self.effects.ground_contact_exponent != 1.0:  # the feet carry the compliance (module docstring)
            stiffness, damping = FOOT_CONTACT_STIFFNESS, 0.0
        self.client.changeDynamics(body, -1, contactStiffness=stiffness, contactDamping=damping,
                                   lateralFriction=1.0 * friction, rollingFriction=0.0, spinningFriction=0.0,
                                   restitution=0.0)

    def set_contact_model(self, course: Course, effects: ModelEffects) -> None:
        """Switch to the contact parameters of ``course`` (same geometry as the built one; e.g. another
        stiffness, damping or friction) and to ``effects`` (all but the payload, which is built into the
        URDF): tal_sim2real re-simulates many candidate models without rebuilding the world."""
        boxes = course.primitives()
        if len(boxes) != len(self.ground_bodies):
            raise BridgeConfigError(f"course '{course.name}' has {len(boxes)} boxes, the simulation "
                                    f"{len(self.ground_bodies)}: only contact parameters can be switched")
        if (effects.payload_mass_kg, effects.payload_offset_m) != (self.effects.payload_mass_kg,
                                                                   self.effects.payload_offset_m):
            raise BridgeConfigError("the payload is part of the loaded URDF; build a new Simulation to change it")
        self.course = course
        self.effects = effects
        self.actuators = ActuatorModel(effects, self.time_step_s, self.actuators.tau_min, self.actuators.tau_max)
        for body, box in zip(self.ground_bodies, boxes):
            self._apply_box_contact(body, box.stiffness_n_per_m, box.damping_ns_per_m, box.friction)
        for link in self.foot_links:  # undo a power-law ground's per-step foot parameters
            self.client.changeDynamics(self.robot, link, contactStiffness=FOOT_CONTACT_STIFFNESS, contactDamping=0.0)
        self._foot_contact_parameters = [(FOOT_CONTACT_STIFFNESS, 0.0)] * len(self.foot_links)

    def _index_links(self) -> None:
        names: dict[str, int] = {}
        joint_names: dict[str, int] = {}
        for j in range(self.client.getNumJoints(self.robot)):
            info = self.client.getJointInfo(self.robot, j)
            joint_names[info[1].decode()] = j
            names[info[12].decode()] = j  # child link name -> link index
        missing = [n for n in self.description.joint_names if n not in joint_names]
        if missing:
            raise BridgeConfigError(f"URDF {self.description.urdf_path} lacks joints {missing}")
        self.joint_ids = [joint_names[n] for n in self.description.joint_names]
        self.foot_links = [names[self.description.foot_frames[leg]] for leg in LEGS]
        self.shin_links = [i for n, i in names.items() if n.endswith(SHIN_LINK_SUFFIX)]
        self.link_names = {i: n for n, i in names.items()}
        self.total_mass_kg = float(sum(self.client.getDynamicsInfo(self.robot, link)[0]
                                       for link in range(-1, self.client.getNumJoints(self.robot))))

    def _configure_robot(self) -> None:
        c = self.client
        for link in range(-1, c.getNumJoints(self.robot)):
            # PyBullet adds 0.04 linear/angular damping by default; the nominal model has none.
            c.changeDynamics(self.robot, link, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0)
        for link in self.foot_links:
            c.changeDynamics(self.robot, link, contactStiffness=FOOT_CONTACT_STIFFNESS, contactDamping=0.0,
                             lateralFriction=1.0, rollingFriction=0.0, spinningFriction=0.0, restitution=0.0)
        # (stiffness [N/m], damping [N s/m]) last given to each foot (the power-law ground updates them)
        self._foot_contact_parameters: list[tuple[float, float]] = [(FOOT_CONTACT_STIFFNESS, 0.0)] * len(
            self.foot_links)
        for body in self.ground_bodies:
            for link in self.shin_links:
                c.setCollisionFilterPair(self.robot, body, link, -1, enableCollision=0)
        # Torque control needs the default velocity motors switched off.
        c.setJointMotorControlArray(self.robot, self.joint_ids, pybullet.VELOCITY_CONTROL,
                                    forces=[0.0] * len(self.joint_ids))

    # -- state ------------------------------------------------------------------------------------------
    def reset(self, initial_xy: tuple[float, float] = (0.0, 0.0), initial_yaw_rad: float = 0.0,
              joint_positions_rad: np.ndarray | None = None, drop_height_m: float = 0.0) -> None:
        """Place the robot in its nominal pose with its feet on the terrain below (plus drop height)."""
        q = (self.description.nominal_joint_positions_rad if joint_positions_rad is None
             else np.asarray(joint_positions_rad, dtype=float))
        self._forget_contacts()  # a teleport too (see set_state)
        for joint, angle in zip(self.joint_ids, q):
            self.client.resetJointState(self.robot, joint, float(angle), 0.0)
        quat = self.client.getQuaternionFromEuler([0.0, 0.0, initial_yaw_rad])
        self._reset_base_pose([initial_xy[0], initial_xy[1], 0.0], quat)
        feet = np.array([self.client.getLinkState(self.robot, f, computeForwardKinematics=1)[4]
                         for f in self.foot_links])
        if joint_positions_rad is None:
            # [m] base origin above flat ground in the nominal pose, level base (the base is at z = 0 here)
            self.nominal_base_height_m = self.description.foot_radius_m - float(np.min(feet[:, 2]))
        ground = np.array([float(self.course.height(x, y)) for x, y in feet[:, :2]])
        if not np.all(np.isfinite(ground)):
            raise BridgeConfigError(f"initial position {initial_xy} puts a foot outside the course extent")
        lift = float(np.max(ground - feet[:, 2])) + self.description.foot_radius_m + drop_height_m
        self._reset_base_pose([initial_xy[0], initial_xy[1], lift], quat)
        self.client.resetBaseVelocity(self.robot, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
        self.actuators.reset()
        self._last_torque = np.zeros(len(self.joint_ids))
        self._prev_base_vel = np.zeros(3)
        self._base_acc = np.zeros(3)
        self.step_count = 0

    def set_state(self, base_position_m: np.ndarray, base_quat_xyzw: np.ndarray,
                  base_lin_vel_world_m_s: np.ndarray, base_ang_vel_world_rad_s: np.ndarray,
                  joint_position_rad: np.ndarray, joint_velocity_rad_s: np.ndarray) -> None:
        """Teleport the robot to a full rigid-body state (world frame, canonical joint order) and clear the
        actuator history (open-loop prediction from a measured state, tal_sim2real)."""
        q = np.asarray(joint_position_rad, dtype=float)
        qd = np.asarray(joint_velocity_rad_s, dtype=float)
        if q.shape != (len(self.joint_ids),) or qd.shape != q.shape:
            raise BridgeConfigError(f"set_state needs {len(self.joint_ids)} joint positions and velocities, "
                                    f"got {q.shape} and {qd.shape}")
        self._forget_contacts()
        for joint, angle, rate in zip(self.joint_ids, q, qd):
            self.client.resetJointState(self.robot, joint, float(angle), float(rate))
        quat = [float(v) for v in base_quat_xyzw]
        self._reset_base_pose([float(v) for v in base_position_m], quat)
        lin = np.asarray(base_lin_vel_world_m_s, dtype=float)
        ang = np.asarray(base_ang_vel_world_rad_s, dtype=float)
        com_lever = self._world_R(quat) @ self._base_com_offset
        self.client.resetBaseVelocity(self.robot, (lin + np.cross(ang, com_lever)).tolist(), ang.tolist())
        self.actuators.reset()
        self._last_torque = np.zeros(len(self.joint_ids))
        self._prev_base_vel = lin.copy()
        self._base_acc = np.zeros(3)

    def _forget_contacts(self) -> None:
        """Drop Bullet's cached robot/ground contact points before a teleport.

        Bullet keeps a persistent manifold per overlapping body pair and, on the next step, refreshes its
        points from their body-local anchors: a point cached at the old pose whose anchors end up within the
        contact breaking threshold (2 cm) of each other at the new pose survives as an extra contact with a
        stale depth and warm-start impulse. A teleported foot then pushes on the ground through two points, and
        an open-loop segment from a state differs from that state's own continuation (on a 1.3e4 N/m
        ground the ground stiffness fitted to the simulator's own data came out ~20% low). Lifting the robot
        out of every ground box's bounding box and running the broadphase removes the pairs and their
        manifolds; the next step starts with fresh contacts, as a continuous run has after a touchdown."""
        _, quat = self.client.getBasePositionAndOrientation(self.robot)
        self.client.resetBasePositionAndOrientation(self.robot, [0.0, 0.0, FORGET_CONTACTS_LIFT_M], quat)
        self.client.performCollisionDetection()

    def _world_R(self, quat_xyzw) -> np.ndarray:
        return np.array(self.client.getMatrixFromQuaternion(list(quat_xyzw))).reshape(3, 3)

    def _reset_base_pose(self, position_m, quat_xyzw) -> None:
        """Place the base link frame (not PyBullet's CoM frame) at ``position_m`` [m] world."""
        com = np.asarray(position_m, dtype=float) + self._world_R(quat_xyzw) @ self._base_com_offset
        self.client.resetBasePositionAndOrientation(self.robot, com.tolist(), list(quat_xyzw))

    def base_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Base link frame position [m] (world) and orientation quaternion (x, y, z, w)."""
        com, quat = self.client.getBasePositionAndOrientation(self.robot)
        return np.asarray(com) - self._world_R(quat) @ self._base_com_offset, np.asarray(quat)

    def base_velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """Base link frame linear [m/s] and angular [rad/s] velocity, world frame."""
        lin, ang = self.client.getBaseVelocity(self.robot)
        ang = np.asarray(ang)
        if not self._base_com_offset.any():
            return np.asarray(lin), ang
        _, quat = self.client.getBasePositionAndOrientation(self.robot)
        return np.asarray(lin) - np.cross(ang, self._world_R(quat) @ self._base_com_offset), ang

    @property
    def time_s(self) -> float:
        return self.step_count * self.time_step_s

    @property
    def time_ns(self) -> int:
        return self.step_count * round(self.time_step_s * 1e9)

    def joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        """Joint positions [rad] and velocities [rad/s], canonical order."""
        states = self.client.getJointStates(self.robot, self.joint_ids)
        return np.array([s[0] for s in states]), np.array([s[1] for s in states])

    def step(self, commanded_torque_nm: np.ndarray,
             joint_state: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Advance one physics step applying the commanded joint torques [N m] through the actuator model.

        ``joint_state`` (q [rad], qd [rad/s]) of this step when the caller already read it.
        """
        q, qd = self.joint_state() if joint_state is None else joint_state
        if self.effects.ground_contact_exponent != 1.0:
            self._apply_power_law_ground()
        tau_min, tau_max = self.description.torque_limits(q)
        delivered = self.actuators.delivered_torque(np.asarray(commanded_torque_nm, dtype=float), tau_min, tau_max)
        self._advance(delivered, delivered + self.actuators.friction_torque(qd))
        vel = self.base_velocity()[0]
        self._base_acc = (vel - self._prev_base_vel) / self.time_step_s
        self._prev_base_vel = vel

    def step_delivered(self, delivered_torque_nm: np.ndarray) -> None:
        """Advance one physics step with joint torques [N m] that already went through the actuator model
        (what ``step`` computes from a command with ``actuators.delivered_torque``), plus the joint friction.

        For open-loop re-simulation (tal_sim2real): the actuator model's output depends only on the command
        sequence when the torque limits do not depend on the joint angles, so a caller can compute a whole
        segment's torques ahead. The physics is ``step``'s: the same applied torques, except that without
        joint friction the joint state is not read and no friction is added (``step`` adds a signed zero,
        which can turn a torque of -0.0 into 0.0: the same force). The base acceleration of ``robot_state``
        is not updated.
        """
        if self.effects.ground_contact_exponent != 1.0:
            self._apply_power_law_ground()
        delivered = np.asarray(delivered_torque_nm, dtype=float)
        friction = self.actuators.effects
        if friction.joint_viscous_friction_nms_per_rad != 0.0 or friction.joint_coulomb_friction_nm != 0.0:
            self._advance(delivered, delivered + self.actuators.friction_torque(self.joint_state()[1]))
        else:
            self._advance(delivered, delivered)

    def _advance(self, delivered: np.ndarray, applied: np.ndarray) -> None:
        """Apply ``applied`` [N m] (delivered + friction) to the joints and step the physics once."""
        self.client.setJointMotorControlArray(self.robot, self.joint_ids, pybullet.TORQUE_CONTROL,
                                              forces=applied.tolist())
        self.client.stepSimulation()
        self.step_count += 1
        self._last_torque = delivered

    def _apply_power_law_ground(self) -> None:
        """Give each foot the secant stiffness [N/m] and damping [N s/m] of its patch's power law at its
        current sinkage (the boxes are rigid, so the foot's parameters are the contact's)."""
        states = self.client.getLinkStates(self.robot, self.foot_links, computeForwardKinematics=1)
        feet = np.array([s[4] for s in states])
        ground, props = self.course.height_and_properties(feet[:, 0], feet[:, 1])
        depth = ground + self.description.foot_radius_m - feet[:, 2]
        depth[np.isnan(depth)] = 0.0  # off the course: no sinkage
        scale = power_law_ground_scale(depth, self.effects.ground_contact_exponent)
        stiffness = np.where(np.isnan(props.stiffness_n_per_m), FOOT_CONTACT_STIFFNESS,
                             props.stiffness_n_per_m) * scale
        damping = np.where(np.isnan(props.damping_ns_per_m), 0.0, props.damping_ns_per_m) * scale
        applied = self._foot_contact_parameters
        for i, (link, k, d) in enumerate(zip(self.foot_links, stiffness, damping)):
            # a foot above the ground keeps the floor-depth value step after step: setting the same
            # parameters again changes nothing in Bullet, so it is skipped (the call is most of this method)
            if applied[i] != (k, d):
                self.client.changeDynamics(self.robot, link, contactStiffness=float(k), contactDamping=float(d))
                applied[i] = (k, d)

    def robot_state(self) -> RobotState:
        position, quat = self.base_pose()
        lin, ang = self.base_velocity()
        q, qd = self.joint_state()
        return RobotState(np.array(position), np.array(quat), np.array(lin), np.array(ang),
                          self._base_acc.copy(), q, qd, self._last_torque.copy())

    def foot_contacts(self) -> list[FootContact]:
        """Ground truth contact per foot, in leg order."""
        feet = []
        ground = set(self.ground_bodies)
        for link in self.foot_links:
            force = np.zeros(3)
            depth = 0.0
            normal_sum = np.zeros(3)
            for point in self.client.getContactPoints(bodyA=self.robot, linkIndexA=link):
                if point[2] not in ground:
                    continue
                normal = np.array(point[7])  # on B (ground), pointing towards A (foot)
                force += point[9] * normal + point[10] * np.array(point[11]) + point[12] * np.array(point[13])
                depth = max(depth, -point[8])
                normal_sum += point[9] * normal
            state = self.client.getLinkState(self.robot, link, computeLinkVelocity=1, computeForwardKinematics=1)
            feet.append((force, depth, normal_sum, np.array(state[4]), np.array(state[6])))
        # A foot in the air gets the terrain's normal under it: one course look-up for all of them.
        airborne = [i for i, foot in enumerate(feet) if not np.linalg.norm(foot[2]) > 0.0]
        under = {}
        if airborne:
            xy = np.array([feet[i][3][:2] for i in airborne])
            under = dict(zip(airborne, np.asarray(self.course.normal(xy[:, 0], xy[:, 1]), dtype=float).reshape(-1, 3)))
        contacts = []
        for i, (force, depth, normal_sum, position, velocity) in enumerate(feet):
            normal = under[i] if i in under else normal_sum / np.linalg.norm(normal_sum)
            contacts.append(FootContact(i not in under, force, depth, normal, position, velocity))
        return contacts

    def body_ground_contact(self) -> list[str]:
        """Names of robot links other than feet touching the ground (non-empty means the robot fell)."""
        touching = set()
        feet = set(self.foot_links)
        for body in self.ground_bodies:
            for point in self.client.getContactPoints(bodyA=self.robot, bodyB=body):
                if point[3] not in feet:
                    touching.add(self.link_names.get(point[3], "base"))
        return sorted(touching)

    def close(self) -> None:
        if self.client is not None:
            try:
                self.client.disconnect()
            except pybullet.error:
                pass
            self.client = None  # type: ignore[assignment]
        if self._urdf is not None:
            self._urdf.unlink(missing_ok=True)


def _terrain_colour(stiffness_n_per_m: float) -> list[float]:
    """Grey for rigid ground, shading to brown for soft ground (for the GUI only)."""
    softness = float(np.clip(1.0 - math.log10(max(stiffness_n_per_m, 1.0)) / 6.3, 0.0, 1.0))
    return [0.55 + 0.25 * softness, 0.55, 0.55 - 0.3 * softness, 1.0]
