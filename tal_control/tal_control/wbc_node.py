"""Node ``wbc``: motion generation + passive whole-body controller (sWBC) at 250 Hz.

Subscribes: joint_states, the base state (``ground_truth/odom`` or ``state_estimate``, parameter
state_source), cmd_vel_stamped (TwistStamped, applied from the first tick at or after its stamp: a
lockstep run with a scripted command does not depend on when the script's process runs), cmd_vel (Twist,
applied from the tick after it arrives, unless stamped commands are in use; see velocity_command),
footholds, body_pose_reference, terrain/heightmap, and with contact_source ground_truth
ground_truth/contacts (the simulator's foot contacts standing in for foot contact sensors: a planned
stance foot that does not touch searches for the ground, a swing foot that lands late in its swing is a
support; ``TouchdownSearch``).
Publishes: joint_command (feed-forward torques), gait_state, wbc/diagnostics.

Ticks lie on the sim-time grid k * control_period_s. A tick is computed once the joint state of that
tick and a base state with the same stamp have arrived (the order of arrival does not matter, so
lockstep runs are deterministic). A base state older than ``stale_state_periods`` control periods puts
the node in safe mode (joint damping hold, MODE_SAFE in diagnostics) until fresh state returns. Input
with NaN, wrong sizes or unknown joints is rejected and counted; a QP that fails falls back to the
decayed previous solution and is counted (MODE_FALLBACK); nothing raises out of the loop.

Lockstep determinism: inputs without a fixed arrival order relative to the tick's joint state are tied to
sim time: a stamped command applies from its stamp's tick, a heightmap from the first tick one control
period after its stamp. (footholds, body_pose_reference and terrain_impedance are still used as they
arrive.)
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from geometry_msgs.msg import Twist, TwistStamped, Vector3
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from tal_core.errors import InputError
from tal_core.heightmap import HeightMapGrid
from tal_core.node_utils import (
    TICK_TOLERANCE_NS,
    declare,
    ns_from_stamp,
    reaches_tick,
    run_node,
    stamp_from_ns,
    tick_after,
    write_summary,
)
from tal_core.robot_model import RobotModel
from tal_core.ros_conversions import base_state_from_odometry, canonical_joint_state, heightmap_grid, heightmap_normal
from tal_msgs.msg import (
    BodyPoseReference,
    ContactState,
    FootholdArray,
    GaitState,
    HeightMap,
    JointCommand,
    TerrainImpedance,
    WbcDiagnostics,
)

from .locomotion import BaseState, ImpedanceGate, LocomotionController, TickOutput
from .locomotion import TerrainImpedance as LegImpedance
from .map_alignment import HeightmapAligner
from .motion.footholds import DEFAULT_K_FEEDBACK
from .motion.gait import PRESETS as GAITS
from .motion.generator import MotionParameters
from .msg_conversions import gait_state_message
from .tracking_stats import TrackingStats
from .velocity_command import VelocityCommandInput
from .wbc import WbcGains, WbcSettings
from .wbc.tasks import orientation_error

CLOCK_RESET_NS = 500_000_000  # [ns] a jump back larger than this is a restarted clock, not reordering
# Stamped commands come ahead of their time, several per message burst: a deep queue. Volatile, so that
# any publisher matches (a transient-local subscription refuses volatile publishers).
STAMPED_COMMAND_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.VOLATILE)


def _pose_filter_parameters(p: dict) -> dict[str, float]:
    """The body-pose filter parameters given (non-zero) as ``MotionParameters`` keywords."""
    names = {"pose_bandwidth_rad_s": "pose_bandwidth_rad_s", "pose_max_height_rate_m_s": "max_height_rate_m_s",
             "pose_max_attitude_rate_rad_s": "max_attitude_rate_rad_s"}
    return {key: float(p[name]) for name, key in names.items() if p[name] > 0.0}


class WbcNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("wbc", **kwargs)
        p = self._declare_parameters()
        self.p = p
        self.model = RobotModel.from_name(p["robot"])
        overrides = {name: p[name] for name in ("step_frequency_hz", "duty_factor", "step_height_m") if p[name]}
        gait = dataclasses.replace(GAITS[p["gait"]], **overrides)
        gains = WbcGains(K_x=p["K_x"], D_x=p["D_x"], K_theta=p["K_theta"], D_theta=p["D_theta"],
                         K_sw=p["K_sw"], D_sw=p["D_sw"], K_st=p["K_st"], D_st=p["D_st"])
        settings = WbcSettings(contact_model=p["contact_model"],
                               default_stiffness_n_per_m=p["terrain_stiffness_n_per_m"],
                               default_damping_ns_per_m=p["terrain_damping_ns_per_m"],
                               friction_coefficient=p["friction_coefficient"],
                               min_normal_force_n=p["min_normal_force_n"],
                               max_normal_force_n=p["max_normal_force_n"], control_period_s=p["control_period_s"])
        self.controller = LocomotionController(self.model, gait, gains, settings,
                                               motion=MotionParameters(touchdown_depth_m=p["touchdown_depth_m"],
                                                                       k_feedback=p["foothold_feedback_s"],
                                                                       foothold_centre=p["foothold_centre"],
                                                                       **_pose_filter_parameters(p)))
        self.joint_names = list(self.model.description.joint_names)
        self.joint_index = {name: i for i, name in enumerate(self.joint_names)}
        self.period_ns = round(p["control_period_s"] * 1e9)
        self.stale_ns = p["stale_state_periods"] * self.period_ns
        self.estimate_period_ns = round(p["estimate_period_s"] * 1e9)
        self._next_tick_ns = 0
        self._deferred_tick_ns: int | None = None
        self._last_command: JointCommand | None = None
        self._joints: tuple[int, np.ndarray, np.ndarray] | None = None
        self._base: tuple[int, BaseState] | None = None
        self.command_input = VelocityCommandInput(p["max_linear_velocity_m_s"], p["max_yaw_rate_rad_s"])
        self._grid = None   # the heightmap in use
        self._pending_grids: list[tuple[int, HeightMapGrid]] = []  # (stamp [ns], map) received, not yet in use
        # The simulator's heightmap is in the true world frame; the estimate drifts in z (map_alignment).
        self.map_aligner = (HeightmapAligner(p["map_alignment_time_constant_s"])
                            if p["state_source"] == "estimate" and p["map_alignment_time_constant_s"] > 0.0
                            else None)
        self.mode = WbcDiagnostics.MODE_NORMAL
        self.rejected_inputs = 0
        self.ticks = 0
        self.deferred_ticks = 0   # ticks whose base state had not arrived with their joint state
        self._contacts: tuple[int, np.ndarray] | None = None  # (stamp [ns], (4,) touching) latest contacts
        self.ticks_without_contacts = 0  # contact_source set, but no fresh contacts for the tick (plan used)
        self.watchdog_trips = 0   # safe-mode commands sent by the wall-clock watchdog
        self._last_joint_wall = time.monotonic()
        # Lockstep runs start when the wbc sends its first command; a command source discovered later (seen
        # across two network namespaces: 0.9 s of sim time) missed its first stamped commands.
        self._source_deadline = None if p["command_source_wait_s"] <= 0.0 else \
            time.monotonic() + p["command_source_wait_s"]
        self.command_source_waits = 0
        self.stats = TrackingStats()

        self.pub_command = self.create_publisher(JointCommand, "joint_command", 10)
        self.pub_gait = self.create_publisher(GaitState, "gait_state", 10)
        self.pub_diag = self.create_publisher(WbcDiagnostics, "wbc/diagnostics", 10)
        state_topic = "ground_truth/odom" if p["state_source"] == "ground_truth" else "state_estimate"
        self.create_subscription(JointState, "joint_states", self._on_joints, 10)
        self.create_subscription(Odometry, state_topic, self._on_base, 10)
        self.create_subscription(Twist, "cmd_vel", self._on_cmd_vel, 10)
        self.create_subscription(TwistStamped, "cmd_vel_stamped", self._on_cmd_vel_stamped, STAMPED_COMMAND_QOS)
        self.create_subscription(FootholdArray, "footholds", self._on_footholds, 10)
        self.create_subscription(BodyPoseReference, "body_pose_reference", self._on_body_pose, 10)
        self.create_subscription(HeightMap, "terrain/heightmap", self._on_heightmap, 10)
        if p["contact_source"] == "ground_truth":
            self.create_subscription(ContactState, "ground_truth/contacts", self._on_contacts, 10)
        self._impedance: LegImpedance | None = None
        self.impedance_gate = ImpedanceGate(p["terrain_stiffness_n_per_m"], p["terrain_damping_ns_per_m"],
                                            p["impedance_min_confidence"])
        if p["contact_model"] == "compliant" and p["impedance_source"] == "tce":
            self.create_subscription(TerrainImpedance, "terrain_impedance", self._on_impedance, 10)
        # The watchdog is a deadline, not a poll: each joint state handled restarts the timer, so it fires
        # watchdog_timeout_s after the last one (a poll every timeout/3 fired up to 4/3 timeout late), then
        # every watchdog_timeout_s while the silence lasts. Idle (cancelled) until the first joint state.
        self._watchdog_timer = None
        if p["watchdog_timeout_s"] > 0.0:
            self._watchdog_timer = self.create_timer(p["watchdog_timeout_s"], self._watchdog,
                                                     clock=Clock(clock_type=ClockType.STEADY_TIME))
            self._watchdog_timer.cancel()
        self.get_logger().info(f"wbc ready: gait {gait.name}, state from '{state_topic}', "
                               f"{1.0 / p['control_period_s']:.0f} Hz")

    def _declare_parameters(self) -> dict:
        g, s = WbcGains(), WbcSettings()
        p = {
            "robot": declare(self, "robot", "hyq", "robot YAML: shipped name or path", read_only=True),
            "gait": declare(self, "gait", "trot", "gait: stand, crawl or trot", choices=tuple(GAITS),
                            read_only=True),
            "step_frequency_hz": declare(self, "step_frequency_hz", 0.0, "[Hz] 0 = gait preset", low=0.0,
                                         high=5.0, read_only=True),
            "duty_factor": declare(self, "duty_factor", 0.0, "[-] 0 = gait preset", low=0.0, high=1.0,
                                   read_only=True),
            "step_height_m": declare(self, "step_height_m", 0.0, "[m] 0 = gait preset", low=0.0, high=0.4,
                                     read_only=True),
            "state_source": declare(self, "state_source", "estimate",
                                    "base state topic: estimate (state_estimate, the state_estimator node) or "
                                    "ground_truth (ground_truth/odom)",
                                    choices=("ground_truth", "estimate"), read_only=True),
            "estimate_period_s": declare(self, "estimate_period_s", 0.003,
                                         "[s] tick of the state_estimator: a control tick waits for the estimate "
                                         "of the latest estimator tick at or before it", low=0.0005, high=0.1,
                                         read_only=True),
            "map_alignment_time_constant_s": declare(
                self, "map_alignment_time_constant_s", 1.0,
                "[s] with state_source estimate: filter constant of the z offset that moves terrain/heightmap "
                "into the estimate's frame (measured at the loaded stance feet); 0 = use the map as it is",
                low=0.0, high=100.0, read_only=True),
            "control_period_s": declare(self, "control_period_s", 0.004, "[s] control tick", low=0.0005,
                                        high=0.1, read_only=True),
            "stale_state_periods": declare(self, "stale_state_periods", 3,
                                           "[-] base state older than this many periods: safe mode", low=1,
                                           high=1000),
            "command_source_wait_s": declare(self, "command_source_wait_s", 0.0,
                                             "[s] wall time the first tick waits for a cmd_vel_stamped "
                                             "publisher to be discovered (lockstep: sim time starts with the "
                                             "command source connected); 0 = no wait", low=0.0, high=120.0,
                                             read_only=True),
            "watchdog_timeout_s": declare(self, "watchdog_timeout_s", 0.0,
                                          "[s] wall time without joint_states (from the end of handling "
                                          "the last one) before safe mode (0 = off; keep off in lockstep)",
                                          low=0.0, high=10.0),
            "safe_damping_nms_per_rad": declare(self, "safe_damping_nms_per_rad", 20.0,
                                                "[N m s/rad] joint damping in safe mode", low=0.0, high=1000.0),
            "summary_path": declare(self, "summary_path", "", "JSON file for the tracking summary written "
                                    "at shutdown ('' = none)"),
            "max_linear_velocity_m_s": declare(self, "max_linear_velocity_m_s", 1.0, "[m/s] cmd_vel clamp",
                                               low=0.0, high=5.0),
            "max_yaw_rate_rad_s": declare(self, "max_yaw_rate_rad_s", 1.0, "[rad/s] cmd_vel clamp", low=0.0,
                                          high=5.0),
            "contact_source": declare(self, "contact_source", "none",
                                      "foot contacts for late and early touchdowns: none (trust the gait plan) "
                                      "or ground_truth (ground_truth/contacts, the simulator's contacts as foot "
                                      "contact sensors)", choices=("none", "ground_truth"), read_only=True),
            "touchdown_depth_m": declare(self, "touchdown_depth_m", 0.0,
                                         "[m] swings end this far below the foothold (a target a little too "
                                         "high still meets the ground)", low=0.0, high=0.1, read_only=True),
            "foothold_feedback_s": declare(self, "foothold_feedback_s", DEFAULT_K_FEEDBACK,
                                           "[s] Raibert velocity feedback of the nominal footholds, k in "
                                           "k (v - v_cmd) (0.12 s in ViTAL's stairs runs)", low=0.0, high=0.5,
                                           read_only=True),
            "foothold_centre": declare(self, "foothold_centre", "hips",
                                       "nominal footholds about the hips (Raibert) or about the CoM (the diagonal "
                                       "support lines of a trot under the CoM; ViTAL's stairs runs)",
                                       choices=("hips", "com"), read_only=True),
            "pose_bandwidth_rad_s": declare(self, "pose_bandwidth_rad_s", 0.0,
                                            "[rad/s] bandwidth of the body height and attitude reference filters "
                                            "(0 = 4 rad/s; 6 in ViTAL's stairs runs)", low=0.0, high=100.0,
                                            read_only=True),
            "pose_max_height_rate_m_s": declare(self, "pose_max_height_rate_m_s", 0.0,
                                                "[m/s] rate limit of the body height reference (0 = 0.1 m/s; "
                                                "climbing stairs at v needs about v x rise / go)", low=0.0,
                                                high=5.0, read_only=True),
            "pose_max_attitude_rate_rad_s": declare(self, "pose_max_attitude_rate_rad_s", 0.0,
                                                    "[rad/s] rate limit of the roll and pitch references "
                                                    "(0 = 0.3 rad/s)", low=0.0, high=10.0, read_only=True),
            "contact_model": declare(self, "contact_model", "rigid",
                                     "rigid (sWBC) or compliant (c3WBC; with impedance_source tce: STANCE)",
                                     choices=("rigid", "compliant"), read_only=True),
            "impedance_source": declare(self, "impedance_source", "tce",
                                        "c3WBC terrain impedance: tce (terrain_impedance topic, fixed values "
                                        "until estimates are valid) or fixed", choices=("tce", "fixed"),
                                        read_only=True),
            "terrain_stiffness_n_per_m": declare(self, "terrain_stiffness_n_per_m", 2e6,
                                                 "[N/m] c3WBC stiffness when fixed or not yet estimated",
                                                 low=1.0, high=1e9, read_only=True),
            "terrain_damping_ns_per_m": declare(self, "terrain_damping_ns_per_m", 400.0,
                                                "[N s/m] c3WBC damping when fixed or not estimated", low=0.0,
                                                high=1e6, read_only=True),
            "impedance_min_confidence": declare(self, "impedance_min_confidence", 0.1,
                                                "[-] a TCE estimate is adopted per leg from this confidence on; "
                                                "below it the leg keeps its last adopted value",
                                                low=0.0, high=1.0, read_only=True),
            "friction_coefficient": declare(self, "friction_coefficient", s.friction_coefficient,
                                            "[-] mu of the friction pyramids", low=0.01, high=5.0),
            "min_normal_force_n": declare(self, "min_normal_force_n", s.min_normal_force_n,
                                          "[N] stance normal force lower bound", low=0.0, high=1e4),
            "max_normal_force_n": declare(self, "max_normal_force_n", s.max_normal_force_n,
                                          "[N] stance normal force upper bound", low=1.0, high=1e5),
        }
        for name, unit in (("K_x", "N/m"), ("D_x", "N s/m"), ("K_theta", "N m/rad"), ("D_theta", "N m s/rad"),
                           ("K_sw", "1/s^2"), ("D_sw", "1/s"), ("K_st", "1/s^2"), ("D_st", "1/s")):
            p[name] = declare(self, name, float(getattr(g, name)), f"[{unit}] task gain (thesis default)",
                              low=0.0, high=1e6, read_only=True)
        return p

    # -- inputs -----------------------------------------------------------------------------------------
    def _reject(self, what: str, exc: Exception) -> None:
        self.rejected_inputs += 1
        self.get_logger().warn(f"rejected {what} ({self.rejected_inputs} so far): {exc}", throttle_duration_sec=1.0)

    def _on_joints(self, msg: JointState) -> None:
        try:
            q, qd = canonical_joint_state(msg, self.joint_index)
        except InputError as exc:
            self._reject("joint_states", exc)
            return
        stamp = ns_from_stamp(msg.header.stamp)
        if self._joints is not None and stamp + CLOCK_RESET_NS < self._joints[0]:
            self._restart(stamp)
        if self._last_command is not None and stamp == ns_from_stamp(self._last_command.header.stamp):
            # The driver repeats a state while it waits for its first command (our answer may have been
            # published before DDS matched us): answer again, identically.
            self.pub_command.publish(self._last_command)
            return
        if self._joints is not None and stamp <= self._joints[0]:
            if stamp == self._joints[0] and self._source_deadline is not None:
                self._maybe_tick()  # the driver repeats its first state while we wait for the command source
            return  # repeated or out-of-order sample: keep the newer one
        self._joints = (stamp, q, qd)
        self._maybe_tick()
        self._feed_watchdog()

    def _feed_watchdog(self) -> None:
        """A joint state was handled (and maybe its tick computed): the watchdog's deadline starts now. It
        counts from the end of the work, because the time a tick takes is not silence of the driver (a
        joint state that arrived meanwhile waits in the queue, and the executor runs timers first)."""
        self._last_joint_wall = time.monotonic()
        if self._watchdog_timer is not None:
            self._watchdog_timer.reset()

    def _restart(self, stamp_ns: int) -> None:
        """The robot's clock jumped back (simulation restarted): start the controller afresh."""
        self.get_logger().warn(f"joint_states time jumped back to {stamp_ns * 1e-9:.3f} s: restarting the controller")
        self.controller = LocomotionController(self.model, self.controller.motion.gait, self.controller.wbc.gains,
                                               self.controller.wbc.settings, motion=self.controller.motion.params)
        self._joints = self._base = None
        if self._contacts is not None and self._contacts[0] > stamp_ns:
            self._contacts = None  # from before the restart
        self._next_tick_ns = 0
        self._deferred_tick_ns = None
        self._last_command = None
        self.command_input.reset()
        self._pending_grids.clear()

    def _on_base(self, msg: Odometry) -> None:
        try:
            base = base_state_from_odometry(msg)
        except InputError as exc:
            self._reject("base state", exc)
            return
        stamp = ns_from_stamp(msg.header.stamp)
        if self._base is not None and stamp + CLOCK_RESET_NS < self._base[0]:
            self._base = None  # restarted clock: the joint_states handler restarts the controller
        if self._base is not None and stamp <= self._base[0]:
            return
        self._base = (stamp, base)
        if self._maybe_tick():
            self._feed_watchdog()

    def _on_contacts(self, msg: ContactState) -> None:
        flags = np.array(msg.in_contact, dtype=bool)  # bool[4] in the message definition
        stamp = ns_from_stamp(msg.header.stamp)
        if self._contacts is not None and stamp + CLOCK_RESET_NS < self._contacts[0]:
            self._contacts = None  # restarted clock
        if self._contacts is not None and stamp <= self._contacts[0]:
            return
        self._contacts = (stamp, flags)
        if self._maybe_tick():
            self._feed_watchdog()

    def _contacts_for(self, stamp_ns: int) -> np.ndarray | None:
        """The contact flags of the tick at ``stamp_ns`` (None: not used, or none fresh: the gait plan)."""
        if self.p["contact_source"] == "none":
            return None
        if self._contacts is None or stamp_ns - self._contacts[0] > self.stale_ns:
            self.ticks_without_contacts += 1
            return None
        return self._contacts[1]

    def _on_cmd_vel(self, msg: Twist) -> None:
        try:
            self.command_input.unstamped((msg.linear.x, msg.linear.y, msg.angular.z))
        except InputError as exc:
            self._reject("cmd_vel", exc)

    def _on_cmd_vel_stamped(self, msg: TwistStamped) -> None:
        stamp = ns_from_stamp(msg.header.stamp)
        try:
            late = self.command_input.stamped(stamp, (msg.twist.linear.x, msg.twist.linear.y, msg.twist.angular.z))
        except InputError as exc:
            self._reject("cmd_vel_stamped", exc)
            return
        if late:
            self.get_logger().warn(f"cmd_vel_stamped for {stamp * 1e-9:.3f} s arrived after its tick "
                                   f"({self.command_input.late} late)", throttle_duration_sec=1.0)

    def _on_footholds(self, msg: FootholdArray) -> None:
        for foothold in msg.footholds:
            point = (foothold.selected.x, foothold.selected.y, foothold.selected.z)
            try:
                self.controller.motion.set_foothold(foothold.leg, foothold.step_count, point)
            except InputError as exc:
                self._reject("foothold", exc)

    def _on_body_pose(self, msg: BodyPoseReference) -> None:
        values = (msg.base_height, msg.roll, msg.pitch)
        if not all(np.isfinite(values)):
            self._reject("body_pose_reference", InputError("body pose reference has NaN or inf"))
            return
        self.controller.motion.set_body_pose_reference(*values)

    def _on_impedance(self, msg: TerrainImpedance) -> None:
        """Per leg, the estimate when valid and confident enough, else the last adopted (``ImpedanceGate``)."""
        self._impedance = self.impedance_gate.update(
            np.array(msg.stiffness_normal, dtype=float), np.array(msg.damping_normal, dtype=float),
            np.array(msg.valid, dtype=bool), np.array(msg.confidence, dtype=float))

    def _on_heightmap(self, msg: HeightMap) -> None:
        try:
            grid = heightmap_grid(msg)
        except InputError as exc:
            self._reject("heightmap", exc)
            return
        self._pending_grids.append((ns_from_stamp(msg.header.stamp), grid))

    def _update_grid(self, stamp_ns: int) -> None:
        """The newest heightmap stamped at least one control period before the tick comes into use.

        A map stamped with the tick itself (or just before it) may reach this node before or after the
        tick's joint state (other topic, no order between them), so using it at once made lockstep runs
        depend on delivery order; the maps of earlier ticks have been delivered by the time the next
        tick's joint state comes (the bridge waited for this node's command in between).
        """
        cutoff = stamp_ns - self.period_ns + TICK_TOLERANCE_NS
        due = [(s, g) for s, g in self._pending_grids if s <= cutoff]
        if due:
            self._grid = max(due, key=lambda item: item[0])[1]
            self._pending_grids = [(s, g) for s, g in self._pending_grids if s > cutoff]

    # -- the tick -----------------------------------------------------------------------------------------
    def _maybe_tick(self) -> bool:
        """Compute the tick once its joint state and the base state expected for it have arrived (ground
        truth: the same stamp; estimate: the estimator's latest tick at or before it), and with a
        contact_source the contacts of its stamp.

        That base state is on its way (the bridge publishes both each step, the estimator answers the
        bridge's samples), so a tick whose base state has not arrived yet is deferred; it is decided, with whatever base
        state is there, when the next tick's joint state arrives (the robot driver moved on). Safe mode
        follows when that base state is older than ``stale_state_periods``. Returns whether a tick (normal
        or safe) was decided.
        """
        if self._joints is None or self._base is None or self._awaiting_command_source():
            return False
        stamp, q, qd = self._joints
        if not reaches_tick(stamp, self._next_tick_ns):
            return False  # not a control tick
        base_stamp, base = self._base
        age = stamp - base_stamp
        deferred_before = self._deferred_tick_ns is not None and stamp > self._deferred_tick_ns
        # The bridge publishes the tick's contacts right after its joint state, like ground-truth odometry.
        contacts_missing = self.p["contact_source"] != "none" and (
            self._contacts is None or self._contacts[0] < stamp - TICK_TOLERANCE_NS)
        if ((base_stamp < self._expected_base_stamp(stamp) - TICK_TOLERANCE_NS or contacts_missing)
                and not deferred_before):
            self._deferred_tick_ns = stamp
            self.deferred_ticks += 1
            return False
        self._deferred_tick_ns = None
        self._next_tick_ns = tick_after(stamp, self.period_ns)
        self.command_input.at_tick(stamp)
        self._update_grid(stamp)
        if age > self.stale_ns:
            self._safe_mode(stamp, f"base state is {age * 1e-6:.1f} ms old")
        else:
            self._tick(stamp, base, q, qd)
        return True

    def _awaiting_command_source(self) -> bool:
        """True while the first tick waits (``command_source_wait_s``) for a cmd_vel_stamped publisher."""
        if self._source_deadline is None:
            return False
        found = self.count_publishers("cmd_vel_stamped") > 0
        if found or time.monotonic() > self._source_deadline:
            if not found:
                self.get_logger().warn(f"no cmd_vel_stamped publisher after {self.p['command_source_wait_s']} s: "
                                       "starting without one")
            self._source_deadline = None
            return False
        self.command_source_waits += 1
        return True

    def _expected_base_stamp(self, stamp_ns: int) -> int:
        """The stamp of the newest base state the source publishes at or before ``stamp_ns``: ground truth
        comes with every physics step, the estimate on the estimator's tick grid."""
        if self.p["state_source"] == "ground_truth":
            return stamp_ns
        period = self.estimate_period_ns
        return ((stamp_ns + TICK_TOLERANCE_NS) // period) * period

    def _tick(self, stamp_ns: int, base: BaseState, q: np.ndarray, qd: np.ndarray) -> None:
        grid = self._grid
        height = (lambda x, y: float(grid.height_at(x, y))) if grid is not None else None
        world_height = height
        if height is not None and self.map_aligner is not None:
            height = self.map_aligner.aligned(height)
        normal = (lambda x, y: heightmap_normal(grid, x, y)) if grid is not None else None
        try:
            out = self.controller.tick(stamp_ns * 1e-9, base, q, qd, self.command_input.command, height, normal,
                                       impedance=self._impedance, foot_contact=self._contacts_for(stamp_ns))
        except InputError as exc:
            self._reject("state", exc)
            self._safe_mode(stamp_ns, str(exc))
            return
        if self.mode == WbcDiagnostics.MODE_SAFE:
            self.get_logger().info("fresh state: leaving safe mode")
        if world_height is not None and self.map_aligner is not None:
            self.map_aligner.update(stamp_ns * 1e-9, out.measured.foot_positions, out.targets.load_factor,
                                    self.controller.motion.foot_radius_m, world_height)
        self.mode = WbcDiagnostics.MODE_FALLBACK if out.solution.fallback else WbcDiagnostics.MODE_NORMAL
        self._publish_command(stamp_ns, effort=out.tau)
        self.stats.add(stamp_ns * 1e-9, base, out)
        stamp = self._joints_stamp_msg(stamp_ns)
        self.pub_gait.publish(gait_state_message(out, stamp))
        self.pub_diag.publish(self._diagnostics(stamp, out))
        self.ticks += 1

    def _safe_mode(self, stamp_ns: int, reason: str) -> None:
        if self.mode != WbcDiagnostics.MODE_SAFE:
            self.get_logger().warn(f"safe mode (joint damping hold): {reason}")
        self.mode = WbcDiagnostics.MODE_SAFE
        self.stats.safe_mode_ticks += 1
        n = len(self.joint_names)
        self._publish_command(stamp_ns, effort=np.zeros(n), velocity=np.zeros(n),
                              kd=np.full(n, self.p["safe_damping_nms_per_rad"]))
        diag = WbcDiagnostics()
        diag.header.stamp = self._joints_stamp_msg(stamp_ns)
        diag.header.frame_id = "world"
        diag.mode = WbcDiagnostics.MODE_SAFE
        diag.contact_model = self.p["contact_model"]
        diag.qp_status_text = reason
        diag.rejected_inputs = self.rejected_inputs
        diag.failed_qps = self.controller.wbc.failed_solves
        self.pub_diag.publish(diag)

    def _watchdog(self) -> None:
        silence_s = time.monotonic() - self._last_joint_wall
        if self._joints is None or silence_s < self.p["watchdog_timeout_s"]:
            return
        self.watchdog_trips += 1
        self._safe_mode(self._joints[0], f"no joint_states for {silence_s * 1e3:.1f} ms (watchdog_timeout_s "
                                         f"{self.p['watchdog_timeout_s'] * 1e3:.1f} ms)")

    # -- outputs ------------------------------------------------------------------------------------------
    @staticmethod
    def _joints_stamp_msg(stamp_ns: int):
        return stamp_from_ns(stamp_ns)

    def _publish_command(self, stamp_ns: int, effort: np.ndarray, velocity: np.ndarray | None = None,
                         kd: np.ndarray | None = None) -> None:
        cmd = JointCommand()
        cmd.header.stamp = self._joints_stamp_msg(stamp_ns)
        cmd.name = self.joint_names
        cmd.effort = effort.tolist()
        if kd is not None:
            cmd.velocity = (velocity if velocity is not None else np.zeros(len(effort))).tolist()
            cmd.kd = kd.tolist()
        self.pub_command.publish(cmd)
        self._last_command = cmd

    def _diagnostics(self, stamp, out: TickOutput) -> WbcDiagnostics:
        sol = out.solution
        diag = WbcDiagnostics()
        diag.header.stamp = stamp
        diag.header.frame_id = "world"
        diag.mode = self.mode
        diag.contact_model = self.p["contact_model"]
        diag.qp_status = sol.status_val
        diag.qp_status_text = sol.status
        diag.qp_iterations = sol.iterations
        diag.qp_solve_time = sol.solve_time_s
        diag.cycle_time = sol.cycle_time_s
        diag.slack_norm = sol.slack_norm
        for leg in range(4):
            diag.stance[leg] = bool(out.targets.stance[leg])
            f = sol.forces[leg]
            diag.desired_force[leg] = Vector3(x=float(f[0]), y=float(f[1]), z=float(f[2]))
            if "penetration" in sol.extras:
                diag.desired_penetration[leg] = float(out.targets.normals[leg] @ sol.extras["penetration"][leg])
        w = sol.desired_wrench
        diag.desired_com_wrench.force = Vector3(x=float(w[0]), y=float(w[1]), z=float(w[2]))
        diag.desired_com_wrench.torque = Vector3(x=float(w[3]), y=float(w[4]), z=float(w[5]))
        e = out.targets.trunk.com_position - out.measured.com
        diag.com_position_error = Vector3(x=float(e[0]), y=float(e[1]), z=float(e[2]))
        r = orientation_error(out.targets.trunk.world_R_base, out.measured.world_R_base())
        diag.orientation_error = Vector3(x=float(r[0]), y=float(r[1]), z=float(r[2]))
        diag.joint_names = self.joint_names
        diag.desired_torque = sol.tau.tolist()
        diag.rejected_inputs = self.rejected_inputs
        diag.failed_qps = self.controller.wbc.failed_solves
        return diag


    @property
    def cmd_vel(self) -> tuple[float, float, float]:
        """The velocity command in force: vx, vy [m/s] (horizontal frame), yaw rate [rad/s]."""
        command = self.command_input.command
        return (float(command[0]), float(command[1]), float(command[2]))

    def summary(self) -> dict:
        aligner = self.map_aligner
        return {**self.stats.summary(), "rejected_inputs": self.rejected_inputs,
                "deferred_ticks": self.deferred_ticks, "watchdog_trips": self.watchdog_trips,
                "ticks_without_contacts": self.ticks_without_contacts,
                "touchdown_searches_per_leg": self.controller.touchdown_search.searches.tolist(),
                "early_touchdowns_per_leg": self.controller.touchdown_search.early_touchdowns.tolist(),
                "command_source_waits": self.command_source_waits,
                "late_cmd_vel": self.command_input.late, "cmd_vel_ignored": self.command_input.unstamped_ignored,
                "heightmap_z_offset_m": None if aligner is None else aligner.offset_m,
                "failed_qps": self.controller.wbc.failed_solves, "gait": self.controller.motion.gait.name,
                "impedance_adopted_per_leg": self.impedance_gate.adopted.tolist(),
                "impedance_held_per_leg": self.impedance_gate.held.tolist()}

    def destroy_node(self) -> None:
        write_summary(self.p["summary_path"], self.summary())
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: WbcNode(), args, name="wbc")


if __name__ == "__main__":
    raise SystemExit(main())
