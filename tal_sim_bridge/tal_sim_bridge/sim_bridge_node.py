"""Node ``sim_bridge``: PyBullet HyQ on a compliant course, standing in for the robot hardware.

Publishes (relative names): joint_states, imu, ground_truth/odom (1 kHz by default), clock and
ground_truth/contacts (250 Hz), terrain/heightmap (20 Hz). Subscribes: joint_command.

foot_sensors: the four feet's contact sensors (``foot_sensor.py``: load with noise, a sample's delay, a flag
with hysteresis) on foot_contacts at the contact rate, for controllers and estimators that use foot sensors
rather than the simulator's ground_truth/contacts.

heightmap_frame: world (default) publishes terrain/heightmap in the true world frame; estimate publishes it in
the state estimate's frame, as a robot's own elevation map would be (``odom_maps.py``: a map captured at tick t
is placed with the estimate of the estimator's newest tick at or before t, subscribed from state_estimate, and
waits for it; in lockstep the next control period waits with it, so no consumer sees a later joint state
before that map), and the world-frame map as ground_truth/heightmap (motion-capture experiments: a TCE on the
ground-truth base).

Modes:
  * lockstep: physics advances one control period (control_period_s) only after a joint_command stamped
    at (or after) the current control tick arrives, so results do not depend on machine speed. If no
    command arrives within lockstep_timeout_s of wall time the bridge advances anyway with the held
    command and counts a lockstep timeout (a controller that never starts cannot freeze the graph).
    While a tick waits longer than MAP_RESEND_AFTER_S the last RESENT_MAPS heightmaps are sent again, oldest
    first (counted): DDS drops what a writer publishes before it has matched a late reader, and a map consumer
    (vfa, vpa, tce, wbc) holds its tick for the map due at it, which one period after a map (the consumers'
    one-tick lag) is still the one before the last. Consumers drop a map stamp they already have.
  * realtime: physics follows the wall clock (steady time) from the first command (the initial state is
    re-sent until a controller answers, at most startup_timeout_s), catching up at most max_catch_up_steps
    per timer call; falling behind is counted as overruns.

A fall (``fall.py``: trunk, hip or thigh on the ground, or the base low over the terrain, held for
fall_confirm_s) ends the run as duration_s does (summary written, ``finished``), logged as an error with its
time, place and links, unless stop_on_fall is false. The summary also gives the command latency: wall time
from a joint state's publication to the arrival of the joint_command stamped with it (``latency.py``).

The bridge is the clock source: its own timers run on the steady clock, never on sim time.
"""

from __future__ import annotations

import json
import math
import time
from collections import deque
from pathlib import Path

from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import Imu, JointState

from tal_core.errors import InputError
from tal_core.heightmap import extract_heightmap
from tal_core.robot_description import load_robot_description
from tal_core.ros.cdr import CdrView, stamp_ns_of, subscribe_view
from tal_core.ros.conversions import base_state_from_odometry_view
from tal_core.ros.node_utils import declare, ns_from_stamp, run_node
from tal_core.rotations import yaw_from_quat_xyzw
from tal_core.terrain import load_course
from tal_msgs.msg import ContactState, HeightMap, JointCommand

from .bridge_core import BridgeCore, ImuModel
from .effects import ModelEffects
from .errors import CommandRejectedError
from .fall import DEFAULT_CONFIRM_S, DEFAULT_MIN_HEIGHT_RATIO, FallDetector
from .foot_sensor import FootForceSensor, FootSensorSettings
from .latency import CommandLatency
from .odom_maps import EstimateFrameMaps, PlacedMap, PlanarPose
from .physics import Simulation
from .sensor_messages import SensorWriters
from .stepping import LockstepGate, OutputSchedule, RealtimePacer

MAP_RESEND_AFTER_S = 0.5
"""[s] of wall time a lockstep tick waits before the last heightmaps are sent again (then once per this period)."""
RESENT_MAPS = 2
"""Heightmaps re-sent while a tick waits: a waiting consumer's due map is the last or the one before it."""
SENSOR_HISTORY = 100
"""Samples each sensor writer keeps for a reader that fell behind (0.1 s of the 1 kHz topics)."""

EFFECT_PARAMETERS: dict[str, tuple[object, str]] = {
    "actuator_delay_s": (0.0, "[s] transport delay of the joint torques"),
    "actuator_lag_s": (0.0, "[s] first-order lag time constant of the joint torques"),
    "torque_gain": (1.0, "[-] delivered / commanded torque"),
    "torque_limit_scale": (1.0, "[-] scale on the robot's torque limits"),
    "joint_viscous_friction_nms_per_rad": (0.0, "[N m s/rad] viscous joint friction"),
    "joint_coulomb_friction_nm": (0.0, "[N m] Coulomb joint friction"),
    "payload_mass_kg": (0.0, "[kg] point mass added to the trunk"),
    "payload_offset_m": ([0.0, 0.0, 0.0], "[m] payload position relative to the trunk CoM, base frame"),
    "imu_gyro_bias_rad_s": ([0.0, 0.0, 0.0], "[rad/s] gyroscope bias, base frame"),
    "imu_accel_bias_m_s2": ([0.0, 0.0, 0.0], "[m/s^2] accelerometer bias, base frame"),
    "ground_contact_exponent": (1.0, "[-] power-law (Hunt-Crossley-type) ground exponent; 1 = Kelvin-Voigt"),
}


class SimBridgeNode(Node):
    """Thin ROS adapter around ``BridgeCore``."""

    def __init__(self, **kwargs) -> None:
        super().__init__("sim_bridge", **kwargs)
        p = self._declare_parameters()
        self.mode: str = p["mode"]
        robot = load_robot_description(p["robot"])
        course = load_course(p["course"])
        effects = ModelEffects.from_mapping(
            {name: self.get_parameter(f"effects.{name}").value for name in EFFECT_PARAMETERS})
        sim = Simulation(robot, course, time_step_s=1.0 / p["physics_rate_hz"], effects=effects,
                         gui=p["gui"], initial_xy=(p["initial_x_m"], p["initial_y_m"]),
                         initial_yaw_rad=p["initial_yaw_rad"])
        imu = ImuModel(effects, p["imu_gyro_noise_std_rad_s"], p["imu_accel_noise_std_m_s2"], p["seed"])
        fall = FallDetector.for_robot(sim.nominal_base_height_m, p["fall_min_base_height_ratio"],
                                      p["fall_confirm_s"])
        self.core = BridgeCore(sim, imu=imu, safe_damping_nms_per_rad=p["safe_damping_nms_per_rad"],
                               summary_window_steps=max(1, int(p["contact_rate_hz"])), fall_detector=fall)
        self.params = p
        self.steps_per_control = max(1, round(p["control_period_s"] * p["physics_rate_hz"]))
        self.schedule = OutputSchedule.from_rates(p["physics_rate_hz"], p["sensor_rate_hz"], p["contact_rate_hz"],
                                                  p["heightmap_rate_hz"], p["clock_rate_hz"],
                                                  p["ground_truth_rate_hz"])
        self.schedule.check_control_steps(self.steps_per_control)
        self.writers = SensorWriters(sim.description.joint_names, p["imu_gyro_noise_std_rad_s"],
                                     p["imu_accel_noise_std_m_s2"])
        self._set_duration(p["duration_s"])
        self.finished = False
        self.fall_logged = False
        self.stopped_on_fall = False
        self.latency = CommandLatency()
        self.initial_state_repeats = 0  # re-sends of the initial state while waiting for a controller
        self.gate = LockstepGate(p["lockstep_timeout_s"], p["startup_timeout_s"])
        self.pacer = RealtimePacer(p["physics_rate_hz"], p["max_catch_up_steps"], time.monotonic())
        # The run's wall-clock start for the summary's real-time factor: the pacer's start moves forward when it
        # drops a backlog (sim time then falls behind), this one does not.
        self._run_start_s = self.pacer.start_s
        self._started_without_command = False
        self._last_resend_s = self._run_start_s
        # the last maps published, raw CDR, oldest first (re-sent while a tick waits)
        self._recent_heightmaps: deque[bytes] = deque(maxlen=RESENT_MAPS)
        self._recent_truth_maps: deque[bytes] = deque(maxlen=RESENT_MAPS)
        self.estimate_maps = (EstimateFrameMaps(round(p["estimate_period_s"] * 1e9))
                              if p["heightmap_frame"] == "estimate" else None)
        self.rejected_estimates = 0
        self._command_held = False   # lockstep: the command came, the step waits for a waiting map's estimate
        self._last_map_resend_s = 0.0
        self.heightmap_resends = 0
        self.commands_before_map_subscribers = 0  # first commands dropped while map consumers were matching
        self._map_subscribers_ready = self.mode != "lockstep" or p["map_subscribers"] == 0
        self.final_summary: dict[str, object] | None = None  # set when duration_s is reached

        # Reliable, and 100 samples (0.1 s of the 1 kHz topics) kept for readers that fall behind: a reliable
        # writer re-sends only what its history still holds (with 10, an estimator descheduled for 10 ms on a
        # busy machine lost IMU samples and re-initialised).
        qos_sensor = QoSProfile(depth=SENSOR_HISTORY, reliability=ReliabilityPolicy.RELIABLE,
                                history=HistoryPolicy.KEEP_LAST)
        self.pub_clock = self.create_publisher(ClockMsg, "clock", qos_sensor)
        self.pub_joints = self.create_publisher(JointState, "joint_states", qos_sensor)
        self.pub_imu = self.create_publisher(Imu, "imu", qos_sensor)
        self.pub_odom = self.create_publisher(Odometry, "ground_truth/odom", qos_sensor)
        self.pub_contacts = self.create_publisher(ContactState, "ground_truth/contacts", qos_sensor)
        self.foot_sensor = None
        self._last_foot_sensors: bytes | None = None
        if p["foot_sensors"]:
            self.foot_sensor = FootForceSensor(FootSensorSettings(
                delay_samples=round(p["foot_sensor_delay_s"] * p["contact_rate_hz"]),
                noise_std_n=p["foot_sensor_noise_n"], threshold_n=p["foot_sensor_threshold_n"],
                hysteresis_fraction=p["foot_sensor_hysteresis"], seed=p["seed"] + 1))
            self.pub_foot_sensors = self.create_publisher(ContactState, "foot_contacts", qos_sensor)
        self.pub_heightmap = self.create_publisher(HeightMap, "terrain/heightmap", qos_sensor)
        self.pub_truth_map = None
        if self.estimate_maps is not None:
            self.pub_truth_map = self.create_publisher(HeightMap, "ground_truth/heightmap", qos_sensor)
            subscribe_view(self, Odometry, "state_estimate", self._on_estimate, 50,
                           on_error=self._reject_estimate)
        self.create_subscription(JointCommand, "joint_command", self._on_command, 10)

        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._publish_step_outputs(force_all=True)
        if self.mode == "lockstep":
            self.gate.wait_for(self.core.sim.time_ns, time.monotonic())
            self.create_timer(0.05, self._check_lockstep_timeout, clock=steady)
        else:
            self.create_timer(1.0 / p["physics_rate_hz"], self._realtime_tick, clock=steady)
        self.get_logger().info(
            f"sim_bridge ready: robot '{robot.name}' ({sim.total_mass_kg:.2f} kg), course '{course.name}', "
            f"mode {self.mode}, physics {p['physics_rate_hz']:.0f} Hz, control period {p['control_period_s']} s"
            + (f", effects {effects.active()}" if effects.active() else ""))

    # -- parameters -------------------------------------------------------------------------------------
    def _declare_parameters(self) -> dict[str, object]:
        p: dict[str, object] = {
            "mode": declare(self, "mode", "lockstep", "lockstep (deterministic) or realtime (wall clock)",
                            choices=("lockstep", "realtime")),
            "robot": declare(self, "robot", "hyq", "robot YAML: shipped name or path"),
            "course": declare(self, "course", "flat_rigid", "course YAML: shipped name or path"),
            "gui": declare(self, "gui", False, "open the PyBullet GUI instead of DIRECT"),
            "physics_rate_hz": declare(self, "physics_rate_hz", 1000.0, "[Hz] physics step rate",
                                       low=100.0, high=10000.0),
            "control_period_s": declare(self, "control_period_s", 0.004,
                                        "[s] control tick of the lockstep protocol", low=0.0005, high=0.1),
            "lockstep_timeout_s": declare(self, "lockstep_timeout_s", 2.0,
                                          "[s] wall time to wait for a command before advancing anyway",
                                          low=0.01, high=3600.0, on_change=self._set_gate("timeout_s")),
            "map_subscribers": declare(self, "map_subscribers", 0,
                                       "[-] lockstep: the first step waits (up to startup_timeout_s) until this many "
                                       "terrain/heightmap subscriptions have matched, and sends the first map again "
                                       "for them (a map consumer holds its ticks for the map due at them; DDS drops "
                                       "what was published before a subscription matched); 0: no wait",
                                       low=0, high=100),
            "startup_timeout_s": declare(self, "startup_timeout_s", 30.0,
                                         "[s] wall time to wait for the very first command (DDS discovery)",
                                         low=0.01, high=3600.0, on_change=self._set_gate("startup_timeout_s")),
            "max_catch_up_steps": declare(self, "max_catch_up_steps", 20,
                                          "[-] realtime: most physics steps per timer call", low=1, high=1000,
                                          on_change=self._set_catch_up),
            "sensor_rate_hz": declare(self, "sensor_rate_hz", 1000.0,
                                      "[Hz] joint_states, imu", low=1.0, high=10000.0),
            "ground_truth_rate_hz": declare(self, "ground_truth_rate_hz", 250.0,
                                            "[Hz] ground_truth/odom (evaluation, or the base state of a controller "
                                            "run on ground truth: a whole multiple of the control rate)",
                                            low=1.0, high=10000.0),
            "clock_rate_hz": declare(self, "clock_rate_hz", 250.0,
                                     "[Hz] clock (sim time for use_sim_time nodes; every node ticks on message "
                                     "stamps, so the control rate is enough)", low=1.0, high=10000.0),
            "contact_rate_hz": declare(self, "contact_rate_hz", 250.0, "[Hz] ground_truth/contacts",
                                       low=1.0, high=10000.0),
            "heightmap_rate_hz": declare(self, "heightmap_rate_hz", 20.0, "[Hz] terrain/heightmap",
                                         low=0.1, high=1000.0),
            "heightmap_rows": declare(self, "heightmap_rows", 33, "[-] cells along x", low=1, high=1001),
            "heightmap_cols": declare(self, "heightmap_cols", 33, "[-] cells along y", low=1, high=1001),
            "heightmap_resolution_m": declare(self, "heightmap_resolution_m", 0.02, "[m] cell size",
                                              low=0.001, high=1.0),
            "foot_sensors": declare(self, "foot_sensors", False,
                                    "publish the feet's contact sensors on foot_contacts (at contact_rate_hz)"),
            "foot_sensor_delay_s": declare(self, "foot_sensor_delay_s", 0.004,
                                           "[s] foot_sensors: delay of a reading (whole sensor samples)",
                                           low=0.0, high=1.0),
            "foot_sensor_noise_n": declare(self, "foot_sensor_noise_n", 2.0, "[N] foot_sensors: reading noise std",
                                           low=0.0, high=1e4),
            "foot_sensor_threshold_n": declare(self, "foot_sensor_threshold_n", 15.0,
                                               "[N] foot_sensors: the contact flag turns on at this reading",
                                               low=0.0, high=1e5),
            "foot_sensor_hysteresis": declare(self, "foot_sensor_hysteresis", 0.3,
                                              "[-] foot_sensors: the flag turns off below (1 - this) x threshold",
                                              low=0.0, high=0.99),
            "heightmap_frame": declare(self, "heightmap_frame", "world",
                                       "frame of terrain/heightmap: world (the truth) or estimate (the state "
                                       "estimate's, as a robot's own map; the world map then goes to "
                                       "ground_truth/heightmap)", choices=("world", "estimate")),
            "estimate_period_s": declare(self, "estimate_period_s", 0.003,
                                         "[s] heightmap_frame estimate: the estimator's tick (a map captured at t "
                                         "waits for the estimate of the newest tick at or before t)",
                                         low=0.0005, high=0.1),
            "initial_x_m": declare(self, "initial_x_m", 0.0, "[m] world x of the robot at start",
                                   low=-1e4, high=1e4),
            "initial_y_m": declare(self, "initial_y_m", 0.0, "[m] world y of the robot at start",
                                   low=-1e4, high=1e4),
            "initial_yaw_rad": declare(self, "initial_yaw_rad", 0.0, "[rad] heading at start",
                                       low=-math.pi, high=math.pi),
            "imu_gyro_noise_std_rad_s": declare(self, "imu_gyro_noise_std_rad_s", 0.0,
                                                "[rad/s] gyroscope white noise", low=0.0, high=10.0),
            "imu_accel_noise_std_m_s2": declare(self, "imu_accel_noise_std_m_s2", 0.0,
                                                "[m/s^2] accelerometer white noise", low=0.0, high=100.0),
            "seed": declare(self, "seed", 0, "[-] seed of the sensor noise", low=0, high=2**31 - 1),
            "safe_damping_nms_per_rad": declare(self, "safe_damping_nms_per_rad", 5.0,
                                                "[N m s/rad] joint damping before any valid command",
                                                low=0.0, high=1000.0),
            "duration_s": declare(self, "duration_s", 0.0, "[s] sim time after which the bridge stops; 0 = never",
                                  low=0.0, high=1e6, on_change=self._set_duration),
            "summary_path": declare(self, "summary_path", "", "JSON file for the end-of-run summary ('' = none)",
                                    on_change=lambda value: self.params.__setitem__("summary_path", value)),
            "stop_on_fall": declare(self, "stop_on_fall", True,
                                    "end the run at a fall (summary written, the node finishes) as at duration_s",
                                    on_change=lambda value: self.params.__setitem__("stop_on_fall", value)),
            "fall_min_base_height_ratio": declare(
                self, "fall_min_base_height_ratio", DEFAULT_MIN_HEIGHT_RATIO,
                "[-] a fall: base origin above the terrain under it below this fraction of the robot's nominal "
                "base height (0 = off; trunk, hip or thigh contact with the ground always counts)",
                low=0.0, high=1.0),
            "fall_confirm_s": declare(self, "fall_confirm_s", DEFAULT_CONFIRM_S,
                                      "[s] sim time a fall condition must hold (a graze does not count)",
                                      low=0.0, high=10.0),
        }
        for name, (default, description) in EFFECT_PARAMETERS.items():
            declare(self, f"effects.{name}", default, description)
        return p

    def _set_gate(self, attribute: str):
        def apply(value: float) -> None:
            setattr(self.gate, attribute, float(value))
        return apply

    def _set_catch_up(self, value: int) -> None:
        self.pacer.max_catch_up_steps = int(value)

    def _set_duration(self, duration_s: float) -> None:
        """Live: a run may be lengthened or shortened while it goes (not below the current step)."""
        steps = round(duration_s * self.params["physics_rate_hz"]) if duration_s > 0 else None
        if steps is not None and steps < self.core.sim.step_count:
            raise ValueError(f"duration_s {duration_s} s is before the current sim time "
                             f"{self.core.sim.time_ns * 1e-9:.3f} s")
        self.duration_steps = steps

    # -- commands ---------------------------------------------------------------------------------------
    def _on_command(self, msg: JointCommand) -> None:
        arrived_s = time.monotonic()
        stamp_ns = ns_from_stamp(msg.header.stamp)
        if not self._map_subscribers_ready and self._awaiting_map_subscribers(arrived_s):
            self.commands_before_map_subscribers += 1
            return  # the controller answers the initial state's next repeat again
        try:
            self.core.commands.submit(stamp_ns, list(msg.name), msg.effort, msg.position, msg.velocity,
                                      msg.kp, msg.kd)
        except CommandRejectedError as exc:
            self.get_logger().warn(
                f"rejected joint_command ({exc.reason}, {self.core.commands.rejected_total} so far): {exc}",
                throttle_duration_sec=1.0)
            return
        self.latency.command(stamp_ns, arrived_s)
        if self.core.commands.accepted == 1:
            # The run starts now (in both modes): discovery and the controllers' start-up are not sim time.
            self.pacer.start_s = self._run_start_s = time.monotonic()
        if self.gate.releases(stamp_ns):
            if self.estimate_maps is not None and self.estimate_maps.waiting:
                # Lockstep: a map waits for the estimate of its instant; the next steps' joint states must not
                # reach a consumer (the tce) before that map does, so the step waits for the estimate too.
                self._command_held = True
            else:
                self._advance_control_period()

    def _awaiting_map_subscribers(self, now: float) -> bool:
        """Lockstep, before the first step: whether a command must wait for the map consumers' subscriptions
        (map_subscribers). When they are all matched (or startup_timeout_s has passed) the initial state and
        its map go out once more, so each has the first map before the first step; the command that arrived
        answers an earlier repeat and waits for the controller's answer to this one."""
        if self.core.sim.step_count or self.core.commands.accepted:
            self._map_subscribers_ready = True
            return False
        matched = self._map_subscriptions() >= self.params["map_subscribers"]
        if matched or now - self._run_start_s > self.params["startup_timeout_s"]:
            if not matched:
                self.get_logger().warn(f"lockstep: {self._map_subscriptions()} of "
                                       f"{self.params['map_subscribers']} heightmap subscriptions matched after "
                                       f"{self.params['startup_timeout_s']} s; starting")
            self._map_subscribers_ready = True
            self._publish_step_outputs(force_all=True, record=False)
            self.initial_state_repeats += 1
        return True

    def _map_subscriptions(self) -> int:
        count = self.pub_heightmap.get_subscription_count()
        return count + (self.pub_truth_map.get_subscription_count() if self.pub_truth_map is not None else 0)

    def _check_lockstep_timeout(self) -> None:
        if self.finished or self.gate.awaiting_tick_ns is None:
            return
        if (self.estimate_maps is not None and self.estimate_maps.waiting
                and time.monotonic() - self.gate.waiting_since_s >= MAP_RESEND_AFTER_S):
            # The estimate a map waits for has not come (the estimator is late or not running): place the
            # waiting maps with the newest estimate there is (counted in late_estimate_maps).
            self._publish_placed(self.estimate_maps.flush())
        if self.core.commands.accepted == 0 and self.core.sim.step_count == 0:
            # Controllers may join after the bridge (DDS discovery): re-send the initial state until the
            # first command arrives. Consumers drop the repeated stamp as not newer.
            self._publish_step_outputs(force_all=True, record=False)
            self.initial_state_repeats += 1
        else:
            self._resend_heightmap_while_waiting(time.monotonic())
        # Before the first command, give DDS discovery time (seconds with LOCALHOST discovery).
        timeout = self.gate.timed_out(time.monotonic(), self.core.commands.accepted)
        if timeout is not None:
            self.get_logger().warn(
                f"lockstep: no joint_command for tick {self.gate.awaiting_tick_ns * 1e-9:.3f} s within "
                f"{timeout} s; advancing with the held command "
                f"({self.gate.timeouts} timeouts)", throttle_duration_sec=1.0)
            self._advance_control_period()

    def _resend_heightmap_while_waiting(self, now: float) -> None:
        """A tick waiting MAP_RESEND_AFTER_S (wall time): send the last maps again, oldest first, once per that
        period (a consumer whose subscription matched after they were published holds its answer for the one
        due at its tick; a newer map alone would release it without that one)."""
        if (not self._recent_heightmaps or now - self.gate.waiting_since_s < MAP_RESEND_AFTER_S
                or now - self._last_map_resend_s < MAP_RESEND_AFTER_S):
            return
        for raw in self._recent_heightmaps:
            self.pub_heightmap.publish(raw)
            self.heightmap_resends += 1
        for raw in self._recent_truth_maps:
            assert self.pub_truth_map is not None
            self.pub_truth_map.publish(raw)
        self._last_map_resend_s = now

    # -- stepping ---------------------------------------------------------------------------------------
    def _advance_control_period(self) -> None:
        self._command_held = False
        self.gate.release()
        for _ in range(self.steps_per_control):
            if self._step_once():
                return
        self.gate.wait_for(self.core.sim.time_ns, time.monotonic())

    def _realtime_tick(self) -> None:
        if self.finished:
            return
        now = time.monotonic()
        if self.core.commands.accepted == 0 and not self._started_without_command:
            # A robot does not walk before its controller runs: physics starts with the first command (or after
            # startup_timeout_s without one); until then the initial state is re-sent at 20 Hz for late joiners.
            if now - self._run_start_s > self.params["startup_timeout_s"]:
                self.get_logger().warn(f"realtime: no joint_command within {self.params['startup_timeout_s']} s; "
                                       "starting with the held command")
                self._started_without_command = True
                self.pacer.start_s = self._run_start_s = now
            elif now - self._last_resend_s >= 0.05:
                self._publish_step_outputs(force_all=True, record=False)
                self.initial_state_repeats += 1
                self._last_resend_s = now
            return
        for _ in range(self.pacer.steps_due(now, self.core.sim.step_count)):
            if self._step_once():
                return

    def _step_once(self) -> bool:
        """One physics step plus the outputs due at it; returns True when the run is finished."""
        state = self.core.step()
        self._publish_step_outputs(state=state)
        if self.core.fall is not None and self._fall_ends_run():
            return True
        if self.duration_steps is not None and self.core.sim.step_count >= self.duration_steps:
            self._finish()
            return True
        return False

    def _publish_step_outputs(self, force_all: bool = False, record: bool = True, state=None) -> None:
        step = self.core.sim.step_count
        stamp_ns = self.core.sim.time_ns
        due = self.schedule.due(step, force_all)
        if due.clock:
            self.pub_clock.publish(self.writers.clock(stamp_ns))
        if state is None:
            state = self.core.sim.robot_state()
        if due.sensors:
            self._publish_sensors(stamp_ns, state)
            self.latency.published(stamp_ns, time.monotonic())
        if due.ground_truth:
            self.pub_odom.publish(self.writers.odometry(stamp_ns, state))
        if due.contacts:
            contacts = self.core.sim.foot_contacts()
            self.pub_contacts.publish(self.writers.contact_state(stamp_ns, contacts))
            if self.foot_sensor is not None:
                if record or self._last_foot_sensors is None:   # a repeat of the initial state: the same reading
                    readings, flags = self.foot_sensor.measure([c.force_n for c in contacts])
                    self._last_foot_sensors = self.writers.foot_sensors(stamp_ns, readings, flags)
                self.pub_foot_sensors.publish(self._last_foot_sensors)
            if record:
                self.core.record_statistics(state, contacts)
        if due.heightmap:
            self._publish_heightmap(stamp_ns, state)

    def _publish_sensors(self, stamp_ns: int, state) -> None:
        self.pub_joints.publish(self.writers.joint_state(stamp_ns, state))
        specific_force, angular_rate = self.core.imu.measure(state)
        self.pub_imu.publish(self.writers.imu(stamp_ns, specific_force, angular_rate))

    def _publish_heightmap(self, stamp_ns: int, state) -> None:
        p = self.params
        yaw = yaw_from_quat_xyzw(state.base_quat_xyzw)
        grid = extract_heightmap(self.core.sim.course, (state.base_position_m[0], state.base_position_m[1]), yaw,
                                 rows=p["heightmap_rows"], cols=p["heightmap_cols"],
                                 resolution_m=p["heightmap_resolution_m"])
        if self.estimate_maps is None:
            self._send_map(self.pub_heightmap, self._recent_heightmaps, self.writers.heightmap(stamp_ns, grid))
            return
        assert self.pub_truth_map is not None
        self._send_map(self.pub_truth_map, self._recent_truth_maps, self.writers.heightmap(stamp_ns, grid))
        true_base = PlanarPose(float(state.base_position_m[0]), float(state.base_position_m[1]),
                               float(state.base_position_m[2]), yaw)
        placed = self.estimate_maps.add_map(stamp_ns, grid, true_base)
        if self.mode == "realtime":
            placed += self.estimate_maps.flush()  # a robot's map does not wait: the newest estimate places it
        self._publish_placed(placed)

    def _on_estimate(self, view: CdrView) -> None:
        assert self.estimate_maps is not None
        try:
            base = base_state_from_odometry_view(view)
            pose = PlanarPose.from_position_quat(base.position, base.quat_xyzw)
        except InputError as exc:
            self._reject_estimate(exc)
            return
        self._publish_placed(self.estimate_maps.add_estimate(view.stamp_ns, pose))

    def _reject_estimate(self, exc: Exception) -> None:
        self.rejected_estimates += 1
        self.get_logger().warn(f"rejected state_estimate ({self.rejected_estimates} so far): {exc}",
                               throttle_duration_sec=1.0)

    def _publish_placed(self, placed: list[PlacedMap]) -> None:
        for item in placed:
            self._send_map(self.pub_heightmap, self._recent_heightmaps,
                           self.writers.heightmap(item.stamp_ns, item.grid))
        if self._command_held and self.estimate_maps is not None and not self.estimate_maps.waiting:
            self._advance_control_period()   # (clears _command_held)

    @staticmethod
    def _send_map(publisher, recent: deque[bytes], raw: bytes) -> None:
        if not recent or stamp_ns_of(recent[-1]) != stamp_ns_of(raw):
            recent.append(raw)  # (the initial state's repeats send the same stamp again)
        publisher.publish(raw)

    # -- end of run -------------------------------------------------------------------------------------
    def _fall_ends_run(self) -> bool:
        """Log the fall once; finish the run on it when stop_on_fall is set (True then)."""
        fall = self.core.fall
        assert fall is not None
        stop = bool(self.params["stop_on_fall"])
        if not self.fall_logged:
            self.fall_logged = True
            self.get_logger().error(
                f"{self.core.sim.description.name} fell {fall.describe()}; "
                + ("stopping the run (stop_on_fall)" if stop else
                   "the run goes on (stop_on_fall is false): what follows is not locomotion"))
        elif stop:
            self.get_logger().error("stop_on_fall set after the fall: stopping the run")
        if stop:
            self.stopped_on_fall = True
            self._finish()
        return stop

    def _finish(self) -> None:
        self.finished = True
        summary = self.final_summary = self.summary()
        self.get_logger().info("run finished: " + json.dumps(summary))
        path = self.params["summary_path"]
        if path:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            Path(path).write_text(json.dumps(summary, indent=2) + "\n")

    def summary(self) -> dict[str, object]:
        summary = self.core.summary(time.monotonic() - self._run_start_s)
        summary.update(mode=self.mode, lockstep_timeouts=self.gate.timeouts,
                       initial_state_repeats=self.initial_state_repeats, heightmap_resends=self.heightmap_resends,
                       commands_before_map_subscribers=self.commands_before_map_subscribers,
                       realtime_overruns=self.pacer.overruns, stop_on_fall=bool(self.params["stop_on_fall"]),
                       stopped_on_fall=self.stopped_on_fall, command_latency_ms=self.latency.summary())
        if self.estimate_maps is not None:
            summary.update(estimate_frame_maps=self.estimate_maps.summary(),
                           rejected_estimates=self.rejected_estimates)
        return summary

    def destroy_node(self) -> None:
        self.core.sim.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: SimBridgeNode(), args, until=lambda node: node.finished, name="sim_bridge")


if __name__ == "__main__":
    raise SystemExit(main())
