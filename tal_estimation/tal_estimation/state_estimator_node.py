"""Node ``state_estimator``: attitude observer + leg odometry + Kalman filter at 333 Hz (sim time).

Subscribes: ``joint_states`` (positions, velocities, measured torques; without velocities when
joint_velocities_optional, without efforts when contact_source is a sensor), ``imu`` (1 kHz, specific force
and angular rate), ``foot_contacts`` (tal_msgs/ContactState, contact_source force_sensor: the norm of each
``force``, raw or [N] per foot_force_scale/offset; contact_flags: ``in_contact``), ``terrain_impedance``
(leg_odometry terrain_aware), ``imu/mag`` (use_magnetometer),
``ground_truth/odom`` (only with initial_pose_source ground_truth, for the first pose, or with
summary_path, to report the drift at shutdown; never fed into the filter).
Publishes: ``state_estimate`` (nav_msgs/Odometry, pose in world, twist in base, covariances) and
``contact_estimate`` (tal_msgs/ContactState) at the ticks k * period_s, and ``state_estimator/diagnostics``
(diagnostic_msgs/DiagnosticArray, counters) once per second of sim time.

When it ticks, which samples a tick uses, what it rejects and when it restarts is
``tal_estimation.streaming.StreamingEstimator`` (shared with the offline runners): a tick at stamp J runs
once the joint state of J and the IMU sample of J have arrived (in any order), with the mean of the IMU
samples in (previous tick, J], so lockstep runs are deterministic. Bad input (NaN, saturated IMU,
missing/unknown joints, stamps going backwards) is rejected and counted by reason; a gap of more than
max_gap_periods re-initialises the velocity filter; a clock that jumps back by more than 0.5 s (restarted
simulation) restarts the estimator. This node converts messages, publishes and reports. Noise figures,
limits, gains, the contact threshold, initial_xy_m and summary_path are live parameters.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState, MagneticField

from tal_core.errors import InputError
from tal_core.robot_model import RobotModel
from tal_core.ros.cdr import CdrView, subscribe_view
from tal_core.ros.conversions import JointStateReader, base_state_from_odometry_view
from tal_core.ros.node_utils import declare, ns_from_stamp, run_node, stamp_from_ns, write_summary
from tal_core.rotations import rotation_from_quat_xyzw
from tal_msgs.msg import ContactState, TerrainImpedance

from .attitude import AttitudeSettings
from .drift_statistics import DriftStatistics, StampMatcher
from .leg_odometry import CONTACT_SOURCES, LEG_ODOMETRY_MODES, VERTICAL_NORMALS, LegImpedance, LegOdometrySettings
from .live_settings import with_field
from .messages import EstimateWriters, foot_contact_values
from .state_estimator import StateEstimate, StateEstimator, StateEstimatorSettings
from .streaming import EstimatorOutput, StreamingEstimator

GYRO_VARIANCE_RAD2_S2 = 1e-4  # [rad^2/s^2] reported variance of the bias-corrected angular rate

SENSOR_QUEUE = 200
"""Queued samples of each 1 kHz input (0.2 s): every IMU sample enters the filter, so a busy machine delays
them rather than drops them."""


class StateEstimatorNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("state_estimator", **kwargs)
        robot = declare(self, "robot", "hyq", "robot YAML: shipped name or path")
        period = declare(self, "period_s", 0.003, "[s] estimator tick (333 Hz)", low=0.0005, high=0.1)
        mode = declare(self, "leg_odometry", "rigid", "rigid (thesis: force threshold, static feet) or "
                       "terrain_aware (continuous contact weight, feet sink per terrain_impedance)",
                       choices=LEG_ODOMETRY_MODES)
        fraction = declare(self, "contact_threshold_weight_fraction", 0.1,
                           "[-] contact force threshold as a fraction of the robot's weight", low=0.001, high=0.99,
                           on_change=self._setting("leg_odometry.contact_threshold_weight_fraction"))
        self.contact_source = declare(
            self, "contact_source", "torque", "torque (force from the joint efforts), force_sensor (foot_contacts "
            "force norms, raw or N, thresholded with hysteresis) or contact_flags (foot_contacts in_contact); "
            "with a sensor, joint efforts are optional", choices=CONTACT_SOURCES)
        hysteresis = declare(self, "contact_hysteresis_fraction", 0.3, "[-] force_sensor: a contact ends below "
                             "(1 - this) x the threshold", low=0.001, high=0.999,
                             on_change=self._setting("leg_odometry.contact_hysteresis_fraction"))
        impedance_confidence = declare(self, "impedance_min_confidence", 0.1, "[-] terrain_aware: a leg whose TCE "
                                       "confidence is below this is treated as on rigid ground", low=0.0, high=1.0,
                                       on_change=self._setting("leg_odometry.min_confidence"))
        force_scale = declare(self, "foot_force_scale", [1.0] * 4, "[N per sensor unit] force_sensor calibration "
                              "per leg (LF, RF, LH, RH): force = scale * (raw - offset)",
                              on_change=self._setting("leg_odometry.foot_force_scale", tuple))
        force_offset = declare(self, "foot_force_offset", [0.0] * 4, "[sensor units] force_sensor reading of an "
                               "unloaded foot, per leg (LF, RF, LH, RH)",
                               on_change=self._setting("leg_odometry.foot_force_offset", tuple))
        self.velocities_optional = declare(self, "joint_velocities_optional", False, "accept joint_states without "
                                           "velocities and derive them (finite difference + low-pass)")
        self.init_source = declare(self, "initial_pose_source", "ground_truth",
                                   "ground_truth (first ground_truth/odom message aligns the world frame, as a "
                                   "motion-capture start) or standing (level, feet on z = 0 under initial_xy_m)",
                                   choices=("ground_truth", "standing"))
        initial_xy = declare(self, "initial_xy_m", [0.0, 0.0], "[m] world x, y of the base when standing (at "
                             "the next start or restart)", on_change=self._set_initial_xy)
        use_mag = declare(self, "use_magnetometer", False, "fuse imu/mag (heading) in the attitude observer")
        field = declare(self, "magnetic_field_world", [2.3e-5, 0.0, -4.1e-5],
                        "[T] Earth's field in the world frame (for use_magnetometer)")
        impedance_period = declare(self, "impedance_period_s", 0.0,
                                   "[s] the tce's period: a tick uses the terrain impedance of the tce tick at least "
                                   "one such period before it and waits for it (lockstep: runs on the estimate repeat "
                                   "bit for bit); 0: the latest impedance as it arrives", low=0.0, high=1.0)
        impedance_defer = declare(self, "impedance_max_defer_s", 0.0,
                                  "[s] with impedance_period_s: a tick waits for its impedance until a joint sample "
                                  "this far past it (0: the next tick's sample), then runs without it (counted)",
                                  low=0.0, high=1.0)
        settings = StateEstimatorSettings(
            period_s=period,
            accel_noise_m_s2=declare(self, "accel_noise_m_s2", 0.5, "[m/s^2] KF acceleration input std",
                                     low=1e-6, high=100.0, on_change=self._setting("accel_noise_m_s2")),
            leg_velocity_noise_m_s=declare(self, "leg_velocity_noise_m_s", 0.05, "[m/s] one leg's velocity std",
                                           low=1e-6, high=100.0, on_change=self._setting("leg_velocity_noise_m_s")),
            vertical_crossover_rad_s=declare(
                self, "vertical_crossover_rad_s", 0.0, "[rad/s] > 0: the published height and vertical velocity "
                "follow the IMU above this crossover and the KF below it (a TCE on the estimate then sees the base's "
                "own motion within a stance, not the modelled sinking); 0: the KF's", low=0.0, high=100.0,
                on_change=self._setting("vertical_crossover_rad_s")),
            leg_velocity_gate_m_s=declare(
                self, "leg_velocity_gate_m_s", 0.08, "[m/s] > 0: a supporting leg whose implied base velocity is "
                "further than this from the KF's prediction is left out of the tick's velocity measurement (a "
                "landing or slipping foot); 0: off", low=0.0, high=100.0,
                on_change=self._setting("leg_velocity_gate_m_s")),
            max_gap_periods=declare(self, "max_gap_periods", 10, "[-] a larger gap re-initialises the velocity",
                                    low=1, high=100000, on_change=self._setting("max_gap_periods")),
            accel_range_m_s2=declare(self, "accel_range_m_s2", 392.0, "[m/s^2] IMU accelerometer range "
                                     "(samples at or beyond it are rejected as saturated)", low=1.0, high=1e4,
                                     on_change=self._setting("accel_range_m_s2")),
            gyro_range_rad_s=declare(self, "gyro_range_rad_s", 34.9, "[rad/s] IMU gyro range", low=0.1,
                                     high=1e3, on_change=self._setting("gyro_range_rad_s")),
            joint_velocity_cutoff_hz=declare(self, "joint_velocity_cutoff_hz", 40.0, "[Hz] low-pass cut-off of "
                                             "derived joint velocities", low=0.1, high=1e4,
                                             on_change=self._setting("joint_velocity_cutoff_hz")),
            tick_tolerance_s=declare(self, "tick_tolerance_s", 1e-4, "[s] how early a joint sample may be and "
                                     "still take a tick (the stamps' jitter; below half the period)",
                                     low=0.0, high=0.05, on_change=self._setting("tick_tolerance_s")),
            attitude=AttitudeSettings(
                k_p=declare(self, "attitude_k_p", 1.0, "[rad/s] NLO injection gain", low=1e-6, high=100.0,
                            on_change=self._setting("attitude.k_p")),
                k_i=declare(self, "attitude_k_i", 0.3, "[1/s^2] NLO gyro-bias gain", low=1e-6, high=100.0,
                            on_change=self._setting("attitude.k_i"))),
            leg_odometry=LegOdometrySettings(mode=mode, contact_threshold_weight_fraction=fraction,
                                             contact_source=self.contact_source,
                                             contact_hysteresis_fraction=hysteresis,
                                             min_confidence=impedance_confidence,
                                             foot_force_scale=tuple(force_scale),
                                             foot_force_offset=tuple(force_offset)))
        self.summary_path = declare(self, "summary_path", "", "JSON written at shutdown (counters, drift "
                                    "against ground truth when available); empty: none",
                                    on_change=self._set_summary_path)
        if len(initial_xy) != 2 or len(field) != 3:
            raise ValueError("initial_xy_m needs 2 values and magnetic_field_world 3")
        self.model = RobotModel.from_name(robot)
        self.stream = StreamingEstimator(
            self.model, settings, magnetic_field_world=np.array(field, float) if use_mag else None,
            wait_for_initial_pose=self.init_source == "ground_truth",
            initial_xy=(float(initial_xy[0]), float(initial_xy[1])),
            # Only the terrain-aware odometry subscribes to the impedance: the rigid one must not wait for it.
            impedance_period_s=impedance_period if mode == "terrain_aware" else 0.0,
            impedance_max_defer_s=impedance_defer,
            on_reject=self._log_rejection,
            on_restart=self._log_restart)
        self.joint_index = {name: i for i, name in enumerate(self.model.description.joint_names)}
        self.period_ns = self.stream.period_ns
        self._last_output: tuple[bytes, bytes | None] | None = None  # serialised: repeated on a repeated sample
        self.writers = EstimateWriters(GYRO_VARIANCE_RAD2_S2)
        self._truth_subscription = None
        self._vs_truth = DriftStatistics(align_start=True)  # constant memory: the node may run for hours
        self._truth_pairs = StampMatcher()  # estimate and truth at their common stamps, in any arrival order

        self.pub_state = self.create_publisher(Odometry, "state_estimate", 10)
        self.pub_contact = self.create_publisher(ContactState, "contact_estimate", 10)
        self.pub_diag = self.create_publisher(DiagnosticArray, "state_estimator/diagnostics", 10)
        # The inputs are read in place from their serialised bytes (tal_core.ros.cdr.CdrReader): no Python
        # message is built for the 1 kHz IMU and joint states, the ground truth or the impedance.
        self.read_joints = JointStateReader(self.joint_index, velocities_optional=self.velocities_optional,
                                            efforts=True, efforts_optional=self.contact_source != "torque")
        subscribe_view(self, JointState, "joint_states", self._on_joints, SENSOR_QUEUE, wants=self.stream.wants_joints,
                       on_error=lambda exc: self._reject("joints", str(exc)))
        subscribe_view(self, Imu, "imu", self._on_imu, SENSOR_QUEUE, on_error=lambda exc: self._reject("imu", str(exc)))
        if mode == "terrain_aware":
            subscribe_view(self, TerrainImpedance, "terrain_impedance", self._on_impedance, 10,
                           on_error=lambda exc: self._reject("terrain_impedance", str(exc)))
        if use_mag:
            self.create_subscription(MagneticField, "imu/mag", self._on_mag, 10)
        if self.contact_source != "torque":
            self.create_subscription(ContactState, "foot_contacts", self._on_foot_contacts, 50)
        if self.init_source == "ground_truth" or self.summary_path:
            self._subscribe_truth()
        self.get_logger().info(f"state_estimator ready: robot '{robot}', {1.0 / period:.0f} Hz, leg odometry "
                               f"{mode}, contact from {self.contact_source}, initial pose from {self.init_source}")

    # -- counters of the streaming tick (diagnostics, summary, tests) ---------------------------------------
    @property
    def estimator(self) -> StateEstimator:
        return self.stream.estimator

    @property
    def rejections(self) -> Counter[str]:
        return self.stream.rejections

    @property
    def ticks(self) -> int:
        return self.stream.ticks

    @property
    def restarts(self) -> int:
        return self.stream.restarts

    # -- live parameters ------------------------------------------------------------------------------------
    def _setting(self, name: str, convert: Callable[[Any], Any] | None = None) -> Callable[[Any], None]:
        """on_change of a parameter that is the estimator setting ``name`` (dotted for nested settings),
        ``convert`` turning the parameter value into the setting's type."""
        return lambda value: self.stream.reconfigure(
            with_field(self.stream.settings, name, value if convert is None else convert(value)))

    def _set_initial_xy(self, value: list[float]) -> None:
        if len(value) != 2:
            raise ValueError(f"initial_xy_m needs 2 values, got {len(value)}")
        self.stream.initial_xy = (float(value[0]), float(value[1]))

    def _set_summary_path(self, value: str) -> None:
        self.summary_path = value
        if value:
            self._subscribe_truth()  # the drift needs ground truth

    def _subscribe_truth(self) -> None:
        if self._truth_subscription is None:
            self._truth_subscription = subscribe_view(self, Odometry, "ground_truth/odom", self._on_truth, 10,
                                                      on_error=lambda exc: self._reject("ground_truth", str(exc)))

    # -- logging --------------------------------------------------------------------------------------------
    def _reject(self, reason: str, message: str) -> None:
        self.rejections[reason] += 1
        self._log_rejection(reason, message)

    def _log_rejection(self, reason: str, message: str) -> None:
        self.get_logger().warn(f"rejected ({reason}, {self.rejections[reason]} so far): {message}",
                               throttle_duration_sec=1.0)

    def _log_restart(self, stamp_ns: int) -> None:
        self.get_logger().warn(f"time jumped back to {stamp_ns * 1e-9:.3f} s: restarting the estimator")
        self._last_output = None
        self._truth_pairs = StampMatcher()

    # -- inputs ---------------------------------------------------------------------------------------------
    def _on_truth(self, view: CdrView) -> None:
        try:
            base = base_state_from_odometry_view(view)
        except InputError as exc:
            self._reject("ground_truth", str(exc))
            return
        stamp = view.stamp_ns
        if self.summary_path:
            self._add_drift(stamp, self._truth_pairs.add_reference(stamp, base))
        if self.init_source == "ground_truth" and not self.stream.has_initial_pose:
            self._output(self.stream.set_initial_pose(base.position, rotation_from_quat_xyzw(base.quat_xyzw)))

    def _on_mag(self, msg: MagneticField) -> None:
        field = np.array([msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z])
        if np.all(np.isfinite(field)) and np.linalg.norm(field) > 0.0:
            self.stream.magnetic_field = field
        else:
            self._reject("mag", "magnetic field has NaN/inf or is zero")

    def _on_impedance(self, view: CdrView) -> None:
        k = view.array("stiffness_normal").astype(float)
        d = view.array("damping_normal").astype(float)
        normals = view.vectors("normal")
        norms = np.linalg.norm(normals, axis=1)
        if not np.all(np.isfinite(normals)) or np.any(norms < 0.5):
            self._reject("terrain_impedance", "normals must be finite unit vectors")
            return
        valid = view.array("valid").astype(bool) & np.isfinite(k) & np.isfinite(d) & (k > 0) & (d > 0)
        # The odometry models sinking only from a confident soft-ground fit (not from a rigid lower bound).
        confidence = np.nan_to_num(view.array("confidence").astype(float), nan=0.0)
        self._output(self.stream.add_impedance(view.stamp_ns, LegImpedance(
            k, d, normals / norms[:, None], valid, confidence, view.array("rigid").astype(bool))))

    def _on_imu(self, view: CdrView) -> None:
        self._output(self.stream.add_imu(view.stamp_ns, view.vector("linear_acceleration").copy(),
                                         view.vector("angular_velocity").copy()))

    def _on_foot_contacts(self, msg: ContactState) -> None:
        try:
            values = foot_contact_values(msg, self.contact_source)
        except InputError as exc:
            self._reject("contacts", str(exc))
            return
        self._output(self.stream.add_contacts(ns_from_stamp(msg.header.stamp), values))

    def _on_joints(self, view: CdrView) -> None:
        self._output(self.stream.add_joints(view.stamp_ns, lambda: self.read_joints(view)))

    def _output(self, outputs: list[EstimatorOutput]) -> None:
        for out in outputs:
            if out.kind == "repeat":
                # A repeated sample (the driver waits for its first command; our answer may have gone out
                # before DDS matched the controller): publish the same estimate again.
                for publisher, msg in zip((self.pub_state, self.pub_contact), self._last_output or ()):
                    if msg is not None:
                        publisher.publish(msg)
            elif out.kind == "initial":
                self._publish_initial(out.stamp_ns)
            else:
                assert out.estimate is not None
                self._publish(out.stamp_ns, out.estimate)
                self._compare_with_truth(out.stamp_ns, out.estimate)
                if self.ticks % max(1, round(1e9 / self.period_ns)) == 0:
                    self._publish_diagnostics(out.stamp_ns)

    # -- outputs --------------------------------------------------------------------------------------------
    def _publish_initial(self, stamp: int) -> None:
        """The initial state (at rest), so a controller can compute its first tick."""
        est = self.estimator
        assert est.kf is not None and est.attitude is not None
        x = est.kf.x.ravel()
        odom = self.writers.odometry(stamp, x[:3], est.attitude.world_R_base, x[3:], np.zeros(3), est.kf.P[:3, :3],
                                     est.kf.P[3:, 3:], est.attitude.attitude_covariance)
        self.pub_state.publish(odom)
        self._last_output = (odom, None)

    def _publish(self, stamp: int, e: StateEstimate) -> None:
        odom = self.writers.odometry(stamp, e.position, e.world_R_base, e.linear_velocity, e.angular_velocity_base,
                                     e.position_covariance, e.velocity_covariance, e.attitude_covariance)
        self.pub_state.publish(odom)
        contact = None
        if self.pub_contact.get_subscription_count():  # built only for a listener (333 Hz)
            impedance = self.stream.impedance
            normals = impedance.normal if impedance is not None else VERTICAL_NORMALS
            contact = self.writers.contacts(stamp, e, normals,
                                            self.estimator.settings.leg_odometry.mode == "terrain_aware")
            self.pub_contact.publish(contact)
        self._last_output = (odom, contact)

    def _publish_diagnostics(self, stamp: int) -> None:
        status = DiagnosticStatus(name="state_estimator", hardware_id="tal")
        rejected = sum(self.rejections.values())
        status.level = DiagnosticStatus.OK if rejected == 0 else DiagnosticStatus.WARN
        status.message = "ok" if rejected == 0 else f"{rejected} inputs rejected"
        values = {"ticks": self.ticks, "restarts": self.restarts, "held_imu_ticks": self.stream.held_imu_ticks,
                  "reinitialisations": self.estimator.reinitialisations, "gated_legs": self.estimator.gated_legs,
                  **{f"rejected_{k}": v for k, v in sorted(self.rejections.items())}}
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = stamp_from_ns(stamp)
        self.pub_diag.publish(msg)

    def _compare_with_truth(self, stamp: int, e: StateEstimate) -> None:
        if self.summary_path:
            self._add_drift(stamp, self._truth_pairs.add_estimate(stamp, e))

    def _add_drift(self, stamp: int, pair: tuple | None) -> None:
        if pair is not None:
            e, truth = pair
            self._vs_truth.add(stamp * 1e-9, e.position - truth.position, e.linear_velocity - truth.linear_velocity)

    def summary(self) -> dict:
        """Counters and, when ground truth was seen, drift [m] and velocity RMSE [m/s] per axis."""
        out: dict = {"ticks": self.ticks, "restarts": self.restarts, "held_imu_ticks": self.stream.held_imu_ticks,
                     "duplicates": self.stream.duplicates,
                     "late_impedance_ticks": self.stream.late_impedance_ticks,
                     "impedance_repeats": self.stream.impedance_repeats,
                     "reinitialisations": self.estimator.reinitialisations, "gated_legs": self.estimator.gated_legs,
                     "rejected": dict(self.rejections),
                     "leg_odometry": self.estimator.settings.leg_odometry.mode}
        out.update(self._vs_truth.summary(decimals=4))
        return out

    def destroy_node(self) -> None:
        write_summary(self.summary_path, self.summary())
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: StateEstimatorNode(), args, name="state_estimator")


if __name__ == "__main__":
    raise SystemExit(main())
