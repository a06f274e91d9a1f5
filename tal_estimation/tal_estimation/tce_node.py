"""Node ``tce``: Terrain Compliance Estimator, publishing ``terrain_impedance`` at the control rate.

Subscribes: joint_states (positions, velocities, measured torques), the base state (``ground_truth/odom`` or
``state_estimate``, parameter base_source: the thesis measured the base with motion capture, so experiments that
reproduce it use ground truth), terrain/heightmap or ground_truth/heightmap (heightmap_topic: the undeformed
surface under the feet, in the frame of the base state). When it ticks and what a tick does is
``tal_estimation.tce_driver.TceDriver`` (shared with the offline runners): ticks lie on the sim-time grid k *
control_period_s and wait for the base state of their own stamp (ground truth comes at the control rate, the
estimate every estimate_period_s; wait_for_base false: the latest as it arrives), up to max_defer_s past the
tick on the wall clock, and with heightmap_period_s for the heightmap of their grid point; a tick's joint
torques are the mean over the samples since the previous tick (average_torque); a base state older than
``stale_state_periods`` skips the tick; feet outside the heightmap give no sample (counted). This node converts
messages and publishes. Thresholds, stale_state_periods and summary_path are live parameters.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import JointState

from tal_core.errors import InputError
from tal_core.heightmap import GridHeights
from tal_core.legs import LEGS
from tal_core.robot_model import RobotModel
from tal_core.ros.cdr import CdrView, subscribe_view
from tal_core.ros.conversions import JointStateReader, base_state_from_odometry_view, heightmap_grid
from tal_core.ros.node_utils import declare, ns_from_stamp, run_node, write_summary
from tal_core.ticks import TickAnswers
from tal_msgs.msg import HeightMap, TerrainImpedance

from .live_settings import with_field
from .messages import ImpedanceWriter
from .tce import PENETRATION_REFERENCES, TceSettings, TerrainComplianceEstimator
from .tce_driver import TceDriver, TceTick


class TceNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("tce", **kwargs)
        robot = declare(self, "robot", "hyq", "robot YAML: shipped name or path")
        base_source = declare(self, "base_source", "ground_truth", "base state: ground_truth or estimate",
                              choices=("ground_truth", "estimate"))
        period = declare(self, "control_period_s", 0.004, "[s] estimation tick", low=0.0005, high=0.1)
        stale_periods = declare(self, "stale_state_periods", 3, "[-] older base state: skip the tick",
                                low=1, high=1000, on_change=self._set_stale_periods)
        estimate_period = declare(self, "estimate_period_s", 0.003,
                                  "[s] with base_source estimate: the estimator's tick (the base state a tick "
                                  "waits for)", low=0.0005, high=0.1)
        wait_for_base = declare(self, "wait_for_base", True,
                                "a tick waits for the base state of its own stamp (false: the latest as it arrives)")
        max_defer = declare(self, "max_defer_s", 0.0,
                            "[s] sim time a tick waits for its base state past the next joint sample (0: lockstep; "
                            "on the wall clock the next sample comes 1 ms later)", low=0.0, high=0.1)
        heightmap_topic = declare(self, "heightmap_topic", "terrain/heightmap",
                                  "the undeformed terrain: terrain/heightmap (the robot's map, in the frame of the "
                                  "state it uses) or ground_truth/heightmap (the simulator's world-frame map, for a "
                                  "TCE on the ground-truth base when the robot's map is in the estimate's frame)",
                                  choices=("terrain/heightmap", "ground_truth/heightmap"))
        heightmap_period = declare(self, "heightmap_period_s", 0.0,
                                   "[s] the heightmap's publishing period on the sim-time grid: a tick waits for "
                                   "the map of its grid point (lockstep); 0: maps are used as they arrive",
                                   low=0.0, high=10.0)
        average_torque = declare(self, "average_torque", True,
                                 "a tick's joint torques are the mean of the samples since the previous tick (the "
                                 "interval of its finite-differenced accelerations); false: its own sample's")
        settings = TceSettings(
            window=declare(self, "window", 250, "[-] samples per leg (thesis: 250 at 250 Hz)", low=2, high=100000),
            min_samples=declare(self, "min_samples", 50, "[-] stance samples before a first estimate", low=1,
                                high=100000, on_change=self._setting("min_samples")),
            contact_force_threshold_n=declare(self, "contact_force_threshold_n", 30.0,
                                              "[N] normal force above which a foot is in contact", low=0.0,
                                              high=1e4, on_change=self._setting("contact_force_threshold_n")),
            estimate_damping=declare(self, "estimate_damping", True,
                                     "fit damping too (thesis: no; removes the stiffness bias on soft ground)",
                                     on_change=self._setting("estimate_damping")),
            estimate_tangential=declare(self, "estimate_tangential", False,
                                        "also fit a tangential stiffness per leg (pooled t1/t2)"),
            relief_radius_m=declare(self, "relief_radius_m", 0.04,
                                    "[m] radius around the foot centre over which the surface relief is taken",
                                    low=0.0, high=1.0, on_change=self._setting("relief_radius_m")),
            max_surface_relief_m=declare(self, "max_surface_relief_m", 0.01,
                                         "[m] more relief under the foot (an edge): the stance sample is left out",
                                         low=0.0, high=10.0, on_change=self._setting("max_surface_relief_m")),
            rigid_stiffness_n_per_m=declare(self, "rigid_stiffness_n_per_m", 5e4,
                                            "[N/m] std(F)/std(p) from which a window counts as rigid ground",
                                            low=0.0, high=1e9, on_change=self._setting("rigid_stiffness_n_per_m")),
            min_force_variation_n=declare(self, "min_force_variation_n", 30.0,
                                          "[N] force std a window needs to be called rigid", low=0.0, high=1e4,
                                          on_change=self._setting("min_force_variation_n")),
            max_penetration_offset_m=declare(self, "max_penetration_offset_m", 0.01,
                                             "[m] a window whose offset fit puts its penetrations further off than "
                                             "this is not confident (a base-height or map error)", low=0.0,
                                             high=10.0, on_change=self._setting("max_penetration_offset_m")),
            penetration_reference=declare(self, "penetration_reference", "surface",
                                          "where penetration is measured from: surface (the map under the foot and "
                                          "the base state; thesis, motion capture) or touchdown (each stance's "
                                          "first sample; for a base estimate that drifts in height)",
                                          choices=PENETRATION_REFERENCES,
                                          on_change=self._setting("penetration_reference")),
            base_drift_fit=declare(self, "base_drift_fit", False,
                                   "with the touchdown reference: fit the base estimate's vertical drift within "
                                   "the window too (F = k p + d dp/dt + g t + c), so a drifting estimate does "
                                   "not bias the stiffness", on_change=self._setting("base_drift_fit")))
        self.model = RobotModel.from_name(robot)
        base_period = (period if base_source == "ground_truth" else estimate_period) if wait_for_base else None
        self.driver = TceDriver(self.model, settings, period_s=period, stale_state_periods=stale_periods,
                                on_reject=lambda exc: self._reject("joint_states", exc),
                                base_period_s=base_period, max_defer_s=max_defer,
                                heightmap_period_s=heightmap_period, average_torque=average_torque)
        self.joint_index = {name: i for i, name in enumerate(self.model.description.joint_names)}
        self.rejected_inputs = 0
        self.summary_path = declare(self, "summary_path", "", "JSON file for the end-of-run summary (final "
                                    "estimates, 10 Hz estimate history); empty: none",
                                    on_change=lambda value: setattr(self, "summary_path", value))
        self.history: list[list[float]] = []    # [t [s], k x4 [N/m], valid x4] every HISTORY_DECIMATION ticks
        self.pub = self.create_publisher(TerrainImpedance, "terrain_impedance", 10)
        self._writer = ImpedanceWriter()
        topic = "ground_truth/odom" if base_source == "ground_truth" else "state_estimate"
        # The bridge repeats its first state until the first command: the answer to it may have been published
        # before DDS matched our writer with the wbc's reader (a lockstep wbc waits for it), so a repeated joint
        # state gets the last answer again (the wbc drops repeats).
        self.answers = TickAnswers()
        # Joint and base states are read in place from their serialised bytes (tal_core.ros.cdr.CdrReader).
        self.read_joints = JointStateReader(self.joint_index, efforts=True)
        subscribe_view(self, JointState, "joint_states", self._on_joints, 10,
                       wants=lambda stamp: self.driver.wants_joints(stamp) or stamp == self.answers.answered_ns,
                       on_error=lambda exc: self._reject("joint_states", exc))
        subscribe_view(self, Odometry, topic, self._on_base, 10, on_error=lambda exc: self._reject("base state", exc))
        self.create_subscription(HeightMap, heightmap_topic, self._on_heightmap, 10)

    @property
    def tce(self) -> TerrainComplianceEstimator:
        return self.driver.tce

    @property
    def ticks(self) -> int:
        return self.driver.ticks

    @property
    def samples_outside_map(self) -> int:
        return self.driver.samples_outside_map

    def _setting(self, name: str) -> Callable[[Any], None]:
        """on_change of a parameter that is the TCE setting ``name``."""
        return lambda value: self.driver.reconfigure(with_field(self.driver.settings, name, value))

    def _set_stale_periods(self, value: int) -> None:
        self.driver.stale_state_periods = value

    def _reject(self, what: str, exc: Exception) -> None:
        self.rejected_inputs += 1
        self.get_logger().warn(f"rejected {what} ({self.rejected_inputs} so far): {exc}", throttle_duration_sec=1.0)

    def _on_base(self, view: CdrView) -> None:
        try:
            base = base_state_from_odometry_view(view)
        except InputError as exc:
            self._reject("base state", exc)
            return
        for tick in self.driver.set_base(view.stamp_ns, base):
            self._publish(tick)

    def _on_heightmap(self, msg: HeightMap) -> None:
        try:
            grid = heightmap_grid(msg)
        except InputError as exc:
            self._reject("heightmap", exc)
            return
        for tick in self.driver.add_heightmap(ns_from_stamp(msg.header.stamp), GridHeights(grid)):
            self._publish(tick)

    def _on_joints(self, view: CdrView) -> None:
        stamp_ns = view.stamp_ns
        repeat, again = self.answers.seen(stamp_ns)
        if again is not None:
            self.pub.publish(again)
        if repeat:
            return
        for tick in self.driver.add_joints_all(stamp_ns, lambda: self.read_joints(view)):
            self._publish(tick)

    def _publish(self, tick: TceTick | None) -> None:
        if tick is None:
            return
        stamp = tick.stamp_ns
        assert stamp is not None
        answer = self._writer(stamp, tick)
        self.answers.answered(stamp, answer)
        self.pub.publish(answer)
        if (self.ticks - 1) % HISTORY_DECIMATION == 0:
            self.history.append([stamp * 1e-9] + [e.stiffness_n_per_m for e in tick.estimates]
                                + [float(e.valid) for e in tick.estimates])

    def summary(self) -> dict:
        """Final per-leg estimates, counters and the estimate history (NaN as null)."""
        def clean(value: float) -> float | None:
            return value if math.isfinite(value) else None

        estimates = self.tce.estimates
        return {
            "ticks": self.ticks, "rejected_inputs": self.rejected_inputs,
            "stale_ticks": self.driver.stale_ticks, "late_base_ticks": self.driver.late_base_ticks,
            "samples_outside_map": self.samples_outside_map,
            "answers_resent": self.answers.resent, "late_heightmaps": self.driver.late_heightmaps,
            "missed_heightmaps": self.driver.missed_heightmaps,
            "late_heightmap_ticks": self.driver.late_heightmap_ticks,
            "ticks_without_acceleration": self.driver.ticks_without_acceleration,
            "lost_ticks": self.driver.lost_ticks,
            "edge_samples_per_leg": self.tce.edge_samples.tolist(),
            "window_restarts_per_leg": self.tce.normal.restarts.tolist(),
            "final": {leg.name: {"stiffness_n_per_m": clean(e.stiffness_n_per_m),
                                 "damping_ns_per_m": clean(e.damping_ns_per_m), "confidence": e.confidence,
                                 "valid": e.valid, "samples": e.samples} for leg, e in zip(LEGS, estimates)},
            "history_columns": ["t_s"] + [f"k_{leg.name}" for leg in LEGS] + [f"valid_{leg.name}" for leg in LEGS],
            "history": [[clean(v) for v in row] for row in self.history],
        }

    def destroy_node(self) -> None:
        write_summary(self.summary_path, self.summary(), indent=None)
        super().destroy_node()


HISTORY_DECIMATION = 25
"""Ticks between two rows of the summary's estimate history (10 Hz at 250 Hz)."""


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: TceNode(), args, name="tce")


if __name__ == "__main__":
    raise SystemExit(main())
