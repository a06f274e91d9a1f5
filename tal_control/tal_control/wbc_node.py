"""Node ``wbc``: motion generation + passive whole-body controller (sWBC) at 250 Hz.

Subscribes: joint_states, the base state (``ground_truth/odom`` or ``state_estimate``, parameter
state_source), cmd_vel_stamped (TwistStamped, applied from the first tick at or after its stamp: a
lockstep run with a scripted command does not depend on when the script's process runs), cmd_vel (Twist,
applied from the tick after it arrives, unless stamped commands are in use; see velocity_command),
footholds, body_pose_reference, terrain/heightmap, and with contact_source ground_truth
ground_truth/contacts (the simulator's foot contacts), with sensor foot_contacts (the feet's contact sensors'
flags, the bridge's foot_sensors: noisy, delayed, thresholded) or with
contact_source estimate the state estimator's contact_estimate (on its tick grid) for touchdowns: a planned
stance foot that does not touch searches for the ground, a swing foot that lands late in its swing is a
support; ``TouchdownSearch``).
Publishes: joint_command (feed-forward torques), gait_state, wbc/diagnostics.

When to tick and with which inputs is ``tick_policy.WbcTickPolicy`` (no rclpy): ticks lie on the sim-time
grid k * control_period_s; a tick is computed once the joint state of that tick and the base state expected
for it have arrived (the order of arrival does not matter, so lockstep runs are deterministic). A base state
older than ``stale_state_periods`` control periods (40 ms) puts the node in safe mode (joint damping hold,
MODE_SAFE in diagnostics) until fresh state returns; a younger one more than a period old (late on a busy
machine) is predicted to the tick at its linear and angular velocity (counted: predicted_base_ticks); the
wall-clock watchdog also enters safe mode. This node is the adapter: parameters, topics, message
conversion, the controller call and publishing. Input with NaN, wrong sizes or unknown joints is rejected
and counted; a QP that fails falls back to the decayed previous
solution and is counted (MODE_FALLBACK); nothing raises out of the loop.

Lockstep determinism: inputs without a fixed arrival order relative to the tick's joint state are tied to
sim time: a stamped command applies from its stamp's tick; a heightmap, footholds, body pose references and
terrain impedance (each stamped with the tick it was computed for) from the first tick one control period
after their stamp, in stamp order. A tick also waits for the answer to the previous tick of the TCE
(wait_for_impedance, c3WBC on the tce), of the vfa (wait_for_footholds, with the vfa's
answer_every_gait_state) and of the vpa (body_pose_period_s: its update period), and with heightmap_period_s
for the heightmap due at it (DDS gives no order between topics: a large map can come after the next tick's
joint state), so the whole graph repeats itself bit for bit in lockstep; the first tick waits for the TCE's
first answer and for the vfa's and vpa's gait_state subscriptions to be discovered (up to
command_source_wait_s).

Live parameters (``ros2 param set``, validated, effective from the next tick unless said otherwise): the
task gains K_* and D_*, friction_coefficient, min/max_normal_force_n, touchdown_depth_m,
foothold_feedback_s, step_height_m (from the next lift-off), stale_state_periods,
safe_damping_nms_per_rad, max_linear_velocity_m_s and max_yaw_rate_rad_s (the command in force is clamped
at once), impedance_min_confidence (from the next TCE update), map_alignment_time_constant_s (0 turns the
alignment off, a new value > 0 on) and summary_path. The others shape the graph, the QP or the gait
structure and are read-only.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from geometry_msgs.msg import Twist, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from tal_core.errors import InputError, TalCoreError
from tal_core.heightmap import GridNormals
from tal_core.robot_model import RobotModel
from tal_core.ros.cdr import CdrView, subscribe_view
from tal_core.ros.conversions import JointStateReader, base_state_from_odometry_view, heightmap_grid
from tal_core.ros.node_utils import declare, ns_from_stamp, run_node, stamp_from_ns, write_summary
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

from .locomotion import ImpedanceGate, LocomotionController
from .locomotion import TerrainImpedance as LegImpedance
from .map_alignment import HeightmapAligner
from .motion.footholds import DEFAULT_K_FEEDBACK
from .motion.gait import PRESETS as GAITS
from .motion.generator import MotionParameters
from .msg_conversions import GaitStateWriter, JointCommandWriter, WbcDiagnosticsWriter, wbc_diagnostics_message
from .tick_policy import Arrival, Mode, Tick, TickPolicyConfig, WbcTickPolicy
from .tracking_stats import TrackingStats
from .velocity_command import VelocityCommandInput
from .wbc import WbcGains, WbcSettings
from .wbc.swbc import QP_SOLVERS

MODES = {Mode.NORMAL: WbcDiagnostics.MODE_NORMAL, Mode.FALLBACK: WbcDiagnostics.MODE_FALLBACK,
         Mode.SAFE: WbcDiagnostics.MODE_SAFE}
# Stamped commands come ahead of their time, several per message burst: a deep queue. Volatile, so that
# any publisher matches (a transient-local subscription refuses volatile publishers).
STAMPED_COMMAND_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.VOLATILE)


def _pose_filter_parameters(p: dict) -> dict[str, float]:
    """The body-pose filter parameters given (non-zero) as ``MotionParameters`` keywords."""
    names = {"pose_bandwidth_rad_s": "pose_bandwidth_rad_s", "pose_max_height_rate_m_s": "max_height_rate_m_s",
             "pose_max_attitude_rate_rad_s": "max_attitude_rate_rad_s"}
    return {key: float(p[name]) for name, key in names.items() if p[name] > 0.0}


def _policy_counter(name: str, doc: str) -> property:
    """A read-only node attribute that is the tick policy's counter ``name``."""
    return property(lambda node: getattr(node.policy.counters, name), doc=doc)


STARTUP_INPUTS = ("impedance", "footholds", "body_pose")
"""Inputs the first tick can wait for (``startup_inputs``): the TCE's first answer, the vfa's and vpa's discovery."""
MAX_FALLBACK_TIMES = 200
"""QP fallbacks whose sim time the summary lists (where a run struggled)."""

RESEND_AFTER_S = 0.25
"""[s] of wall time a tick waits for the answers to the last gait state before the wbc sends it again."""


class WbcNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("wbc", **kwargs)
        p = self._declare_parameters()
        self.p = p
        self.model = RobotModel.from_name(p["robot"])
        overrides = {name: p[name] for name in ("step_frequency_hz", "duty_factor", "step_height_m") if p[name]}
        self.gait = dataclasses.replace(GAITS[p["gait"]], **overrides)
        gains = WbcGains(K_x=p["K_x"], D_x=p["D_x"], K_theta=p["K_theta"], D_theta=p["D_theta"],
                         K_sw=p["K_sw"], D_sw=p["D_sw"], K_st=p["K_st"], D_st=p["D_st"])
        settings = WbcSettings(contact_model=p["contact_model"], qp_solver=p["qp_solver"],
                               default_stiffness_n_per_m=p["terrain_stiffness_n_per_m"],
                               default_damping_ns_per_m=p["terrain_damping_ns_per_m"],
                               friction_coefficient=p["friction_coefficient"],
                               min_normal_force_n=p["min_normal_force_n"],
                               max_normal_force_n=p["max_normal_force_n"], control_period_s=p["control_period_s"])
        self.controller = LocomotionController(self.model, self.gait, gains, settings,
                                               motion=MotionParameters(touchdown_depth_m=p["touchdown_depth_m"],
                                                                       k_feedback=p["foothold_feedback_s"],
                                                                       foothold_centre=p["foothold_centre"],
                                                                       contact_grace_s=p["contact_grace_s"],
                                                                       latch_contact=p["contact_latch"],
                                                                       **_pose_filter_parameters(p)))
        self.joint_names = list(self.model.description.joint_names)
        self.joint_index = {name: i for i, name in enumerate(self.joint_names)}
        self._last_command: bytes | None = None  # serialised: answered again when the driver repeats a state
        self._gait_writer = GaitStateWriter()
        self._command_writer = JointCommandWriter(self.joint_names)
        self._diag_writer = WbcDiagnosticsWriter(self.joint_names)
        self.command_input = VelocityCommandInput(p["max_linear_velocity_m_s"], p["max_yaw_rate_rad_s"])
        # The simulator's heightmap is in the true world frame; the estimate drifts in z (map_alignment).
        self.map_aligner = (HeightmapAligner(p["map_alignment_time_constant_s"], p["map_alignment_max_rate_m_s"])
                            if p["state_source"] == "estimate" and p["map_alignment_time_constant_s"] > 0.0
                            else None)
        self.rejected_inputs = 0
        self.predicted_base_ticks = 0   # ticks whose late base state was predicted to the tick
        self.fallback_times_s: list[float] = []   # [s] sim time of the first MAX_FALLBACK_TIMES QP fallbacks
        # Lockstep runs start when the wbc sends its first command; a command source discovered later (seen
        # across two network namespaces: 0.9 s of sim time) missed its first stamped commands: the policy
        # holds the first tick back up to command_source_wait_s.
        self.policy = WbcTickPolicy(
            TickPolicyConfig(period_ns=round(p["control_period_s"] * 1e9), stale_periods=p["stale_state_periods"],
                             base_period_ns=(None if p["state_source"] == "ground_truth"
                                             else round(p["estimate_period_s"] * 1e9)),
                             contacts=p["contact_source"] != "none",
                             contact_period_ns=(round(p["estimate_period_s"] * 1e9)
                                                if p["contact_source"] == "estimate" else None),
                             command_source_wait_s=p["command_source_wait_s"],
                             watchdog_timeout_s=p["watchdog_timeout_s"],
                             max_defer_ns=round(p["max_defer_s"] * 1e9),
                             waited_inputs=self._waited_inputs(p),
                             waited_periods_ns=((("body_pose", round(p["body_pose_period_s"] * 1e9)),)
                                                if p["body_pose_period_s"] > 0.0 else ()),
                             gait_driven=("footholds", "body_pose"),
                             startup_inputs=self._startup_inputs(p),
                             heightmap_period_ns=round(p["heightmap_period_s"] * 1e9)),
            self.command_input, command_source_found=lambda: self.count_publishers("cmd_vel_stamped") > 0,
            producers_ready=self._gait_consumers_ready)
        self.stats = TrackingStats()
        self._start_s = time.monotonic()
        self._body_pose: tuple[float, float, float] | None = None  # the last body pose reference (map frame)
        self.create_timer(5.0, self._report_first_tick_wait, clock=Clock(clock_type=ClockType.STEADY_TIME))
        # A producer's answer published before DDS matched its writer with our reader (or a gait state before
        # our writer matched the producer's reader) is lost, and a lockstep tick would wait for it until the
        # bridge times out: a tick that waits this long for answers sends the last gait state again, and the
        # producers answer a repeated gait state with their last answer (the policy drops repeats).
        self._last_gait_state: bytes | None = None
        self._overdue_since: tuple[int, float] | None = None
        self.gait_state_resends = 0
        self.create_timer(RESEND_AFTER_S, self._resend_overdue_gait_state,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))

        self.pub_command = self.create_publisher(JointCommand, "joint_command", 10)
        self.pub_gait = self.create_publisher(GaitState, "gait_state", 10)
        self.pub_diag = self.create_publisher(WbcDiagnostics, "wbc/diagnostics", 10)
        state_topic = "ground_truth/odom" if p["state_source"] == "ground_truth" else "state_estimate"
        # The control-rate inputs are read in place from their serialised bytes (tal_core.ros.cdr.CdrReader, no
        # Python message built); joint states: 1 kHz in, 250 Hz used, only the samples the tick policy acts on.
        self.read_joints = JointStateReader(self.joint_index)
        subscribe_view(self, JointState, "joint_states", self._on_joints, 10,
                       wants=lambda stamp: self.policy.wants_joint_state(stamp),
                       on_error=lambda exc: self._reject("joint_states", exc))
        subscribe_view(self, Odometry, state_topic, self._on_base, 10,
                       on_error=lambda exc: self._reject("base state", exc))
        self.create_subscription(Twist, "cmd_vel", self._on_cmd_vel, 10)
        self.create_subscription(TwistStamped, "cmd_vel_stamped", self._on_cmd_vel_stamped, STAMPED_COMMAND_QOS)
        self.create_subscription(FootholdArray, "footholds", self._on_footholds, 10)
        self.create_subscription(BodyPoseReference, "body_pose_reference", self._on_body_pose, 10)
        self.create_subscription(HeightMap, "terrain/heightmap", self._on_heightmap, 10)
        if p["contact_source"] != "none":
            contact_topic = {"ground_truth": "ground_truth/contacts", "estimate": "contact_estimate",
                             "sensor": "foot_contacts"}[p["contact_source"]]
            subscribe_view(self, ContactState, contact_topic, self._on_contacts, 10,
                           on_error=lambda exc: self._reject("contacts", exc))
        self._impedance: LegImpedance | None = None
        self.impedance_gate = ImpedanceGate(p["terrain_stiffness_n_per_m"], p["terrain_damping_ns_per_m"],
                                            p["impedance_min_confidence"], p["impedance_hold_limit_s"])
        if p["contact_model"] == "compliant" and p["impedance_source"] == "tce":
            subscribe_view(self, TerrainImpedance, "terrain_impedance", self._on_impedance, 10,
                           on_error=lambda exc: self._reject("terrain_impedance", exc))
        # The watchdog is a deadline, not a poll: each joint state handled restarts the timer, so it fires
        # watchdog_timeout_s after the last one (a poll every timeout/3 fired up to 4/3 timeout late), then
        # every watchdog_timeout_s while the silence lasts. Idle (cancelled) until the first joint state.
        self._watchdog_timer = None
        if p["watchdog_timeout_s"] > 0.0:
            self._watchdog_timer = self.create_timer(p["watchdog_timeout_s"], self._watchdog,
                                                     clock=Clock(clock_type=ClockType.STEADY_TIME))
            self._watchdog_timer.cancel()
        self.get_logger().info(f"wbc ready: gait {self.gait.name}, state from '{state_topic}', "
                               f"{1.0 / p['control_period_s']:.0f} Hz")

    def _declare_parameters(self) -> dict:
        g, s = WbcGains(), WbcSettings()
        p = {
            "robot": declare(self, "robot", "hyq", "robot YAML: shipped name or path"),
            "gait": declare(self, "gait", "trot", "gait: stand, crawl or trot", choices=tuple(GAITS)),
            "step_frequency_hz": declare(self, "step_frequency_hz", 0.0, "[Hz] 0 = gait preset", low=0.0,
                                         high=5.0),
            "duty_factor": declare(self, "duty_factor", 0.0, "[-] 0 = gait preset", low=0.0, high=1.0),
            "step_height_m": declare(self, "step_height_m", 0.0, "[m] swing apex, 0 = gait preset; live: from the "
                                     "next lift-off", low=0.0, high=0.4,
                                     on_change=self._live("step_height_m", self._set_step_height)),
            "state_source": declare(self, "state_source", "estimate",
                                    "base state topic: estimate (state_estimate, the state_estimator node) or "
                                    "ground_truth (ground_truth/odom)",
                                    choices=("ground_truth", "estimate")),
            "estimate_period_s": declare(self, "estimate_period_s", 0.003,
                                         "[s] tick of the state_estimator: a control tick waits for the estimate "
                                         "of the latest estimator tick at or before it", low=0.0005, high=0.1),
            "map_alignment_time_constant_s": declare(
                self, "map_alignment_time_constant_s", 1.0,
                "[s] with state_source estimate: filter constant of the z offset that moves terrain/heightmap "
                "into the estimate's frame (measured at the loaded stance feet); 0 = use the map as it is",
                low=0.0, high=100.0,
                on_change=self._live("map_alignment_time_constant_s", self._set_map_alignment)),
            "map_alignment_max_rate_m_s": declare(
                self, "map_alignment_max_rate_m_s", 0.05,
                "[m/s] bound on the alignment offset's rate (a touchdown on an unmapped step must not yank the "
                "body; the estimate's z drifts up to ~0.2 m/s while the feet sink into soft ground)",
                low=0.001, high=10.0, on_change=self._live("map_alignment_max_rate_m_s", self._set_map_rate)),
            "control_period_s": declare(self, "control_period_s", 0.004, "[s] control tick", low=0.0005,
                                        high=0.1),
            "stale_state_periods": declare(self, "stale_state_periods", 10,
                                           "[-] base state older than this many periods: safe mode (a younger "
                                           "one more than a period old is predicted to the tick)", low=1,
                                           high=1000, on_change=self._live("stale_state_periods",
                                                                           self._set_stale_periods)),
            "max_defer_s": declare(self, "max_defer_s", 0.0,
                                   "[s] sim time a tick waits for its base state before running on a later joint "
                                   "sample (0: the next sample; real-time runs: a few ms)", low=0.0, high=0.1),
            "heightmap_period_s": declare(self, "heightmap_period_s", 0.0,
                                          "[s] the heightmap's publishing period on the sim-time grid: a tick "
                                          "waits for the map due at it (lockstep); 0: maps are used as they arrive",
                                          low=0.0, high=10.0),
            "command_source_wait_s": declare(self, "command_source_wait_s", 0.0,
                                             "[s] wall time the first tick waits for a cmd_vel_stamped "
                                             "publisher to be discovered (lockstep: sim time starts with the "
                                             "command source connected); 0 = no wait", low=0.0, high=120.0),
            "watchdog_timeout_s": declare(self, "watchdog_timeout_s", 0.0,
                                          "[s] wall time without joint_states (from the end of handling "
                                          "the last one) before safe mode (0 = off; keep off in lockstep)",
                                          low=0.0, high=10.0),
            "safe_damping_nms_per_rad": declare(self, "safe_damping_nms_per_rad", 20.0,
                                                "[N m s/rad] joint damping in safe mode", low=0.0, high=1000.0,
                                                on_change=self._live("safe_damping_nms_per_rad")),
            "summary_path": declare(self, "summary_path", "", "JSON file for the tracking summary written "
                                    "at shutdown ('' = none)", on_change=self._live("summary_path")),
            "max_linear_velocity_m_s": declare(self, "max_linear_velocity_m_s", 1.0, "[m/s] cmd_vel clamp",
                                               low=0.0, high=5.0, on_change=self._live(
                                                   "max_linear_velocity_m_s", self._set_linear_limit)),
            "max_yaw_rate_rad_s": declare(self, "max_yaw_rate_rad_s", 1.0, "[rad/s] cmd_vel clamp", low=0.0,
                                          high=5.0, on_change=self._live("max_yaw_rate_rad_s",
                                                                         self._set_yaw_rate_limit)),
            "contact_source": declare(self, "contact_source", "none",
                                      "foot contacts for late and early touchdowns: none (trust the gait plan) "
                                      "or ground_truth (ground_truth/contacts, the simulator's contacts as foot "
                                      "contact sensors) or estimate (contact_estimate, the state estimator's "
                                      "contacts on its tick grid, estimate_period_s) or sensor (foot_contacts' "
                                      "flags: the feet's contact sensors, on the control grid)",
                                      choices=("none", "ground_truth", "estimate", "sensor")),
            "contact_grace_s": declare(self, "contact_grace_s", 0.0,
                                       "[s] with contact_source: a planned stance leg is a support this long "
                                       "without a reported contact before it searches for the ground (a foot "
                                       "sensor's latency)", low=0.0, high=0.5),
            "contact_latch": declare(self, "contact_latch", False,
                                     "with contact_source: a contact reported in a planned stance holds until "
                                     "lift-off (a load sensor's flag drops under a lightly loaded stance foot)"),
            "touchdown_depth_m": declare(self, "touchdown_depth_m", 0.0,
                                         "[m] swings end this far below the foothold (a target a little too "
                                         "high still meets the ground)", low=0.0, high=0.1,
                                         on_change=self._live("touchdown_depth_m", self._motion_setter(
                                             "touchdown_depth_m"))),
            "foothold_feedback_s": declare(self, "foothold_feedback_s", DEFAULT_K_FEEDBACK,
                                           "[s] Raibert velocity feedback of the nominal footholds, k in "
                                           "k (v - v_cmd) (0.12 s in ViTAL's stairs runs)", low=0.0, high=0.5,
                                           on_change=self._live("foothold_feedback_s",
                                                                self._motion_setter("k_feedback"))),
            "foothold_centre": declare(self, "foothold_centre", "hips",
                                       "nominal footholds about the hips (Raibert) or about the CoM (the diagonal "
                                       "support lines of a trot under the CoM; ViTAL's stairs runs)",
                                       choices=("hips", "com")),
            "pose_bandwidth_rad_s": declare(self, "pose_bandwidth_rad_s", 0.0,
                                            "[rad/s] bandwidth of the body height and attitude reference filters "
                                            "(0 = 4 rad/s; 6 in ViTAL's stairs runs)", low=0.0, high=100.0),
            "pose_max_height_rate_m_s": declare(self, "pose_max_height_rate_m_s", 0.0,
                                                "[m/s] rate limit of the body height reference (0 = 0.1 m/s; "
                                                "climbing stairs at v needs about v x rise / go)", low=0.0,
                                                high=5.0),
            "pose_max_attitude_rate_rad_s": declare(self, "pose_max_attitude_rate_rad_s", 0.0,
                                                    "[rad/s] rate limit of the roll and pitch references "
                                                    "(0 = 0.3 rad/s)", low=0.0, high=10.0),
            "qp_solver": declare(self, "qp_solver", "osqp",
                                 "the QP solver: osqp (ADMM, to its tolerance 1e-4) or daqp (dense active set, "
                                 "the exact optimum, 4x faster)", choices=QP_SOLVERS),
            "contact_model": declare(self, "contact_model", "rigid",
                                     "rigid (sWBC) or compliant (c3WBC; with impedance_source tce: STANCE)",
                                     choices=("rigid", "compliant")),
            "impedance_source": declare(self, "impedance_source", "tce",
                                        "c3WBC terrain impedance: tce (terrain_impedance topic, fixed values "
                                        "until estimates are valid) or fixed", choices=("tce", "fixed")),
            "terrain_stiffness_n_per_m": declare(self, "terrain_stiffness_n_per_m", 2e6,
                                                 "[N/m] c3WBC stiffness when fixed or not yet estimated",
                                                 low=1.0, high=1e9),
            "terrain_damping_ns_per_m": declare(self, "terrain_damping_ns_per_m", 400.0,
                                                "[N s/m] c3WBC damping when fixed or not estimated", low=0.0,
                                                high=1e6),
            "wait_for_footholds": declare(self, "wait_for_footholds", False,
                                          "a tick waits for the vfa's answer to the previous tick's gait state "
                                          "(needs vfa answer_every_gait_state; lockstep: deterministic)"),
            "startup_inputs": declare(self, "startup_inputs", "",
                                      "comma-separated inputs (impedance, footholds, body_pose) whose producers "
                                      "the first tick waits for (up to command_source_wait_s) even where later "
                                      "ticks do not wait: on the wall clock the robot starts once they run"),
            "body_pose_period_s": declare(self, "body_pose_period_s", 0.0,
                                          "[s] > 0: a tick waits for the vpa's answers, one every this much gait "
                                          "time (its update_period_s; lockstep: deterministic); 0: no wait",
                                          low=0.0, high=10.0),
            "wait_for_impedance": declare(self, "wait_for_impedance", True,
                                          "c3WBC on the tce: a tick waits for the TCE's answer to the previous "
                                          "tick (up to max_defer_s on the wall clock; lockstep: deterministic)"),
            "impedance_min_confidence": declare(self, "impedance_min_confidence", 0.1,
                                                "[-] a TCE estimate is adopted per leg from this confidence on; "
                                                "below it the leg keeps its last adopted value",
                                                low=0.0, high=1.0, on_change=self._live(
                                                    "impedance_min_confidence", self._set_min_confidence)),
            "impedance_hold_limit_s": declare(self, "impedance_hold_limit_s", 1.5,
                                              "[s] a leg's adopted TCE estimate expires this long after the last "
                                              "adoption without a new one (the rigid model again)", low=0.01,
                                              high=1e6),
            "friction_coefficient": declare(self, "friction_coefficient", s.friction_coefficient,
                                            "[-] mu of the friction pyramids", low=0.01, high=5.0,
                                            on_change=self._live("friction_coefficient",
                                                                 self._settings_setter("friction_coefficient"))),
            "min_normal_force_n": declare(self, "min_normal_force_n", s.min_normal_force_n,
                                          "[N] stance normal force lower bound", low=0.0, high=1e4,
                                          on_change=self._live("min_normal_force_n",
                                                               self._settings_setter("min_normal_force_n"))),
            "max_normal_force_n": declare(self, "max_normal_force_n", s.max_normal_force_n,
                                          "[N] stance normal force upper bound", low=1.0, high=1e5,
                                          on_change=self._live("max_normal_force_n",
                                                               self._settings_setter("max_normal_force_n"))),
        }
        for name, unit in (("K_x", "N/m"), ("D_x", "N s/m"), ("K_theta", "N m/rad"), ("D_theta", "N m s/rad"),
                           ("K_sw", "1/s^2"), ("D_sw", "1/s"), ("K_st", "1/s^2"), ("D_st", "1/s")):
            p[name] = declare(self, name, float(getattr(g, name)), f"[{unit}] task gain (thesis default)",
                              low=0.0, high=1e6, on_change=self._live(name, self._gain_setter(name)))
        return p

    # -- live parameters (see the module docstring) ---------------------------------------------------------
    def _live(self, name: str, apply: Callable[[Any], None] | None = None) -> Callable[[Any], None]:
        """``on_change`` of the live parameter ``name``: ``apply(value)`` takes effect (a domain error refuses
        the set with its message), then ``self.p`` holds the new value."""
        def on_change(value: Any) -> None:
            if apply is not None:
                try:
                    apply(value)
                except (TalCoreError, ValueError) as exc:
                    raise ValueError(f"parameter '{name}': {exc}") from exc
            self.p[name] = value
        return on_change

    def _gain_setter(self, name: str) -> Callable[[float], None]:
        def apply(value: float) -> None:
            self.controller.wbc.gains = dataclasses.replace(self.controller.wbc.gains, **{name: float(value)})
        return apply

    def _settings_setter(self, name: str) -> Callable[[float], None]:
        return lambda value: self.controller.wbc.update_settings(**{name: value})

    def _motion_setter(self, name: str) -> Callable[[float], None]:
        return lambda value: self.controller.motion.update_params(**{name: float(value)})

    def _set_step_height(self, value: float) -> None:
        height = float(value) or GAITS[self.p["gait"]].step_height_m
        self.controller.motion.set_step_height(height)
        self.gait = dataclasses.replace(self.gait, step_height_m=height)  # what a restart starts with

    def _set_map_alignment(self, time_constant_s: float) -> None:
        if self.p["state_source"] != "estimate":
            return  # the map and ground truth share their frame: nothing to align
        if time_constant_s <= 0.0:
            self.map_aligner = None
        elif self.map_aligner is None:
            self.map_aligner = HeightmapAligner(time_constant_s, self.p["map_alignment_max_rate_m_s"])
        else:
            self.map_aligner.time_constant_s = float(time_constant_s)

    def _set_map_rate(self, rate_m_s: float) -> None:
        if self.map_aligner is not None:
            self.map_aligner.max_rate_m_s = float(rate_m_s)

    def _set_stale_periods(self, periods: int) -> None:
        self.policy.set_stale_periods(periods)

    def _set_linear_limit(self, value: float) -> None:
        self.command_input.set_limits(value, self.command_input.max_yaw_rate_rad_s)

    def _set_yaw_rate_limit(self, value: float) -> None:
        self.command_input.set_limits(self.command_input.max_linear_m_s, value)

    def _set_min_confidence(self, value: float) -> None:
        self.impedance_gate.min_confidence = float(value)

    # -- inputs -----------------------------------------------------------------------------------------
    def _reject(self, what: str, exc: Exception) -> None:
        self.rejected_inputs += 1
        self.get_logger().warn(f"rejected {what} ({self.rejected_inputs} so far): {exc}", throttle_duration_sec=1.0)

    def _on_joints(self, view: CdrView) -> None:
        try:
            q, qd, _ = self.read_joints(view)
        except InputError as exc:
            self._reject("joint_states", exc)
            return
        stamp = view.stamp_ns
        arrival = self.policy.joint_state(stamp, (q, qd))
        if arrival.restarted:
            self.get_logger().warn(f"joint_states time jumped back to {stamp * 1e-9:.3f} s: restarting the "
                                   "controller")
            self.controller = LocomotionController(self.model, self.gait, self.controller.wbc.gains,
                                                   self.controller.wbc.settings, motion=self.controller.motion.params)
            self._last_command = None
        self._act(arrival)

    def _on_base(self, view: CdrView) -> None:
        try:
            base = base_state_from_odometry_view(view)
        except InputError as exc:
            self._reject("base state", exc)
            return
        self._act(self.policy.base_state(view.stamp_ns, base))

    def _on_contacts(self, view: CdrView) -> None:
        flags = view.array("in_contact").astype(bool)  # bool[4] in the message definition
        self._act(self.policy.contacts(view.stamp_ns, flags))

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

    @staticmethod
    def _waited_inputs(p: dict) -> tuple[str, ...]:
        waited = []
        if p["wait_for_impedance"] and p["contact_model"] == "compliant" and p["impedance_source"] == "tce":
            waited.append("impedance")
        if p["wait_for_footholds"]:
            waited.append("footholds")
        if p["body_pose_period_s"] > 0.0:
            waited.append("body_pose")
        return tuple(waited)

    @staticmethod
    def _startup_inputs(p: dict) -> tuple[str, ...]:
        names = tuple(name.strip() for name in p["startup_inputs"].split(",") if name.strip())
        unknown = sorted(set(names) - set(STARTUP_INPUTS))
        if unknown:
            raise InputError(f"startup_inputs: unknown input(s) {unknown}; known: {', '.join(STARTUP_INPUTS)}")
        uses_tce = p["contact_model"] == "compliant" and p["impedance_source"] == "tce"
        return tuple(name for name in names if name != "impedance" or uses_tce)  # the sWBC reads no impedance

    def _gait_consumers_ready(self) -> bool:
        """Every node publishing a waited footholds / body_pose_reference topic has its gait_state subscription
        discovered (it will get the first tick's gait state), and there is one for each."""
        listeners = {info.node_name for info in self.get_subscriptions_info_by_topic("gait_state")}
        config = self.policy.config
        for name, topic in (("footholds", "footholds"), ("body_pose", "body_pose_reference")):
            if name in config.waited_inputs or name in config.startup_inputs:
                producers = {info.node_name for info in self.get_publishers_info_by_topic(topic)}
                if not producers or not producers <= listeners:
                    return False
        return True

    def _on_footholds(self, msg: FootholdArray) -> None:
        self._act(self.policy.lagged("footholds", ns_from_stamp(msg.header.stamp), msg))

    def _apply_footholds(self, msg: FootholdArray) -> None:
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
        self._act(self.policy.lagged("body_pose", ns_from_stamp(msg.header.stamp), values))

    def _on_impedance(self, view: CdrView) -> None:
        arrays = (view.array("stiffness_normal").astype(float), view.array("damping_normal").astype(float),
                  view.array("valid").astype(bool), view.array("confidence").astype(float),
                  view.array("rigid").astype(bool), view.stamp_ns * 1e-9)
        self._act(self.policy.lagged("impedance", view.stamp_ns, arrays))

    def _apply_inputs(self, inputs: tuple[tuple[str, Any], ...]) -> None:
        """The lagged inputs released to a tick, in stamp order. Impedance: per leg, the estimate when valid and
        confident enough (the rigid model where the TCE flags rigid ground), else the last adopted
        (``ImpedanceGate``)."""
        for name, value in inputs:
            if name == "impedance":
                self._impedance = self.impedance_gate.update(*value)
            elif name == "footholds":
                self._apply_footholds(value)
            elif name == "body_pose":
                self._body_pose = value
                self.controller.motion.set_body_pose_reference(*value)

    def _on_heightmap(self, msg: HeightMap) -> None:
        try:
            grid = heightmap_grid(msg)
        except InputError as exc:
            self._reject("heightmap", exc)
            return
        self._act(self.policy.heightmap(ns_from_stamp(msg.header.stamp), grid))

    # -- the tick -----------------------------------------------------------------------------------------
    def _resend_overdue_gait_state(self) -> None:
        """The deferred tick has waited RESEND_AFTER_S (wall time) for answers: send the last gait state again."""
        if not self.policy.waiting_for_answers or self._last_gait_state is None:
            self._overdue_since = None
            return
        now, tick = time.monotonic(), self.policy.next_tick_ns
        if self._overdue_since is None or self._overdue_since[0] != tick:
            self._overdue_since = (tick, now)
        elif now - self._overdue_since[1] >= RESEND_AFTER_S:
            self.pub_gait.publish(self._last_gait_state)
            self.gait_state_resends += 1
            self._overdue_since = (tick, now)

    def _report_first_tick_wait(self) -> None:
        """Every 5 s of wall time until the first tick is computed: what it waits for (a lockstep run that does
        not start says why)."""
        missing = self.policy.first_tick_waits_for()
        if missing:
            self.get_logger().warn(f"first tick still waiting after {time.monotonic() - self._start_s:.0f} s for: "
                                   + "; ".join(missing))

    def _act(self, arrival: Arrival) -> None:
        """Do what the tick policy decided for an arrival."""
        if arrival.repeat_answer:
            # The driver repeats a state while it waits for its first command (our answer may have been
            # published before DDS matched us): answer again, identically.
            self.pub_command.publish(self._last_command)
            return
        if arrival.command_source_missing:
            self.get_logger().warn(f"no cmd_vel_stamped publisher after {self.p['command_source_wait_s']} s: "
                                   "starting without one")
        if arrival.tick is not None:
            self._apply_inputs(arrival.tick.inputs)
            if arrival.tick.safe_reason is not None:
                self._safe_mode(arrival.tick.stamp_ns, arrival.tick.safe_reason)
            else:
                self._tick(arrival.tick)
        if arrival.feed_watchdog:
            self._feed_watchdog()

    def _tick(self, tick: Tick) -> None:
        stamp_ns, (q, qd), base, grid = tick.stamp_ns, tick.joints, tick.base, tick.heightmap
        if tick.base_age_ns > self.policy.config.period_ns:
            # A base state that came late (a busy machine, a lost sample), younger than stale_state_periods:
            # moved to the tick at its velocities rather than used as it was.
            base = base.predicted(tick.base_age_ns * 1e-9)
            self.predicted_base_ticks += 1
        height = (lambda x, y: float(grid.height_at(x, y))) if grid is not None else None
        world_height = height
        if height is not None and self.map_aligner is not None:
            height = self.map_aligner.aligned(height)
            if self._body_pose is not None and self._body_pose[0] is not None:
                # The vpa's base height is a world (map) height: it moves with the map into the estimate's frame.
                world_base_height, roll, pitch = self._body_pose
                self.controller.motion.set_body_pose_reference(world_base_height + self.map_aligner.offset_m,
                                                               roll, pitch)
        normal = GridNormals(grid) if grid is not None else None
        try:
            out = self.controller.tick(stamp_ns * 1e-9, base, q, qd, tick.command, height, normal,
                                       impedance=self._impedance, foot_contact=tick.contacts)
        except InputError as exc:
            self._reject("state", exc)
            self._safe_mode(stamp_ns, str(exc))
            return
        if out.solution.fallback and len(self.fallback_times_s) < MAX_FALLBACK_TIMES:
            self.fallback_times_s.append(round(stamp_ns * 1e-9, 3))
        if self.policy.tick_done(fallback=out.solution.fallback):
            self.get_logger().info("fresh state: leaving safe mode")
        if world_height is not None and self.map_aligner is not None:
            self.map_aligner.update(stamp_ns * 1e-9, out.measured.foot_positions, out.targets.load_factor,
                                    self.controller.motion.foot_radius_m, world_height)
        self._publish_command(stamp_ns, effort=out.tau)
        self.stats.add(stamp_ns * 1e-9, base, out)
        self._last_gait_state = self._gait_writer(out, stamp_ns)
        self.pub_gait.publish(self._last_gait_state)
        if self.pub_diag.get_subscription_count():  # 250 Hz of per-joint arrays: built only for a listener
            self.pub_diag.publish(self._diag_writer(stamp_ns, self.mode, self.p["contact_model"], self.rejected_inputs,
                                                    self.controller.wbc.failed_solves, out))

    def _safe_mode(self, stamp_ns: int, reason: str) -> None:
        if self.policy.enter_safe_mode():
            self.get_logger().warn(f"safe mode (joint damping hold): {reason}")
        self.stats.safe_mode_ticks += 1
        n = len(self.joint_names)
        self._publish_command(stamp_ns, effort=np.zeros(n), velocity=np.zeros(n),
                              kd=np.full(n, self.p["safe_damping_nms_per_rad"]))
        self.pub_diag.publish(wbc_diagnostics_message(
            self._joints_stamp_msg(stamp_ns), WbcDiagnostics.MODE_SAFE, self.p["contact_model"],
            self.rejected_inputs, self.controller.wbc.failed_solves, reason=reason))

    def _feed_watchdog(self) -> None:
        """A joint state was handled (and maybe its tick computed): the watchdog's deadline starts now. It
        counts from the end of the work, because the time a tick takes is not silence of the driver (a
        joint state that arrived meanwhile waits in the queue, and the executor runs timers first)."""
        self.policy.feed_watchdog()
        if self._watchdog_timer is not None:
            self._watchdog_timer.reset()

    def _watchdog(self) -> None:
        trip = self.policy.watchdog()
        if trip is not None:
            self._safe_mode(trip.stamp_ns, f"no joint_states for {trip.silence_s * 1e3:.1f} ms (watchdog_timeout_s "
                                           f"{self.p['watchdog_timeout_s'] * 1e3:.1f} ms)")

    # -- outputs ------------------------------------------------------------------------------------------
    @staticmethod
    def _joints_stamp_msg(stamp_ns: int):
        return stamp_from_ns(stamp_ns)

    def _publish_command(self, stamp_ns: int, effort: np.ndarray, velocity: np.ndarray | None = None,
                         kd: np.ndarray | None = None) -> None:
        cmd = self._command_writer(stamp_ns, effort, velocity, kd)
        self.pub_command.publish(cmd)
        self._last_command = cmd
        self.policy.answered(stamp_ns)

    # -- what the tick policy counts ----------------------------------------------------------------------
    @property
    def mode(self) -> int:
        """WbcDiagnostics.MODE_* of the last command."""
        return MODES[self.policy.mode]

    ticks = _policy_counter("ticks", "Normal ticks computed.")
    deferred_ticks = _policy_counter("deferred_ticks", "Ticks whose base state (or contacts) had not arrived with "
                                     "their joint state.")
    watchdog_trips = _policy_counter("watchdog_trips", "Safe-mode commands sent by the wall-clock watchdog.")
    ticks_without_contacts = _policy_counter("ticks_without_contacts", "contact_source set, but no fresh "
                                             "contacts for the tick (the gait plan used).")
    ticks_without_waited = _policy_counter("ticks_without_waited", "Ticks run (past max_defer_s) without the "
                                           "previous tick's terrain impedance (wait_for_impedance).")
    ticks_without_heightmap = _policy_counter("ticks_without_heightmap", "Ticks run (past max_defer_s) without "
                                              "the heightmap due at them (heightmap_period_s).")
    command_source_waits = _policy_counter("command_source_waits", "Ticks held back waiting for a cmd_vel_stamped "
                                           "publisher.")

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
                "ticks_without_waited": self.ticks_without_waited,
                "ticks_without_heightmap": self.ticks_without_heightmap,
                "late_heightmaps": self.policy.late_heightmaps,
                "missed_heightmaps": self.policy.missed_heightmaps,
                "gait_state_resends": self.gait_state_resends,
                "repeated_answers": self.policy.counters.repeated_answers,
                "unanswered_inputs": list(self.policy.unanswered_inputs),
                "touchdown_searches_per_leg": self.controller.touchdown_search.searches.tolist(),
                "early_touchdowns_per_leg": self.controller.touchdown_search.early_touchdowns.tolist(),
                "command_source_waits": self.command_source_waits,
                "late_cmd_vel": self.command_input.late, "cmd_vel_ignored": self.command_input.unstamped_ignored,
                "heightmap_z_offset_m": None if aligner is None else aligner.offset_m,
                "failed_qps": self.controller.wbc.failed_solves, "gait": self.controller.motion.gait.name,
                "predicted_base_ticks": self.predicted_base_ticks, "qp_fallback_times_s": self.fallback_times_s,
                "impedance_adopted_per_leg": self.impedance_gate.adopted.tolist(),
                "impedance_held_per_leg": self.impedance_gate.held.tolist(),
                "impedance_rigid_per_leg": self.impedance_gate.rigid.tolist(),
                "impedance_expired_per_leg": self.impedance_gate.expired.tolist()}

    def destroy_node(self) -> None:
        write_summary(self.p["summary_path"], self.summary())
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: WbcNode(), args, name="wbc")


if __name__ == "__main__":
    raise SystemExit(main())
