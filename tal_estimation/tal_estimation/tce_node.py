"""Node ``tce``: Terrain Compliance Estimator, publishing ``terrain_impedance`` at the control rate.

Subscribes: joint_states (positions, velocities, measured torques), the base state (``ground_truth/odom``
or ``state_estimate``, parameter base_source: the thesis measured the base with motion capture, so
experiments that reproduce it use ground truth), terrain/heightmap (the undeformed surface under the
feet). Ticks lie on the sim-time grid k * control_period_s and use the latest base state if it is not
older than ``stale_state_periods``; feet outside the heightmap give no sample (counted).
"""

from __future__ import annotations

import math

import numpy as np
from geometry_msgs.msg import Vector3
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import JointState

from tal_core.errors import InputError
from tal_core.legs import LEGS
from tal_core.node_utils import (
    declare,
    ns_from_stamp,
    reaches_tick,
    run_node,
    stamp_from_ns,
    tick_after,
    write_summary,
)
from tal_core.robot_model import RobotModel
from tal_core.ros_conversions import base_state_from_odometry, canonical_joint_state, heightmap_grid
from tal_msgs.msg import HeightMap, TerrainImpedance

from .tce import FiniteDifferenceAcceleration, TceSettings, TerrainComplianceEstimator


class TceNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("tce", **kwargs)
        robot = declare(self, "robot", "hyq", "robot YAML: shipped name or path", read_only=True)
        base_source = declare(self, "base_source", "ground_truth", "base state: ground_truth or estimate",
                              choices=("ground_truth", "estimate"), read_only=True)
        period = declare(self, "control_period_s", 0.004, "[s] estimation tick", low=0.0005, high=0.1,
                         read_only=True)
        self.stale_periods = declare(self, "stale_state_periods", 3, "[-] older base state: skip the tick",
                                     low=1, high=1000)
        settings = TceSettings(
            window=declare(self, "window", 250, "[-] samples per leg (thesis: 250 at 250 Hz)", low=2, high=100000,
                           read_only=True),
            min_samples=declare(self, "min_samples", 50, "[-] stance samples before a first estimate", low=1,
                                high=100000, read_only=True),
            contact_force_threshold_n=declare(self, "contact_force_threshold_n", 30.0,
                                              "[N] normal force above which a foot is in contact", low=0.0,
                                              high=1e4, read_only=True),
            estimate_damping=declare(self, "estimate_damping", True,
                                     "fit damping too (thesis: no; removes the stiffness bias on soft ground)",
                                     read_only=True),
            estimate_tangential=declare(self, "estimate_tangential", False,
                                        "also fit a tangential stiffness per leg (pooled t1/t2)", read_only=True),
            relief_radius_m=declare(self, "relief_radius_m", 0.04,
                                    "[m] radius around the foot centre over which the surface relief is taken",
                                    low=0.0, high=1.0, read_only=True),
            max_surface_relief_m=declare(self, "max_surface_relief_m", 0.01,
                                         "[m] more relief under the foot (an edge): the stance sample is left out",
                                         low=0.0, high=10.0, read_only=True),
            rigid_stiffness_n_per_m=declare(self, "rigid_stiffness_n_per_m", 5e4,
                                            "[N/m] std(F)/std(p) from which a window counts as rigid ground",
                                            low=0.0, high=1e9, read_only=True),
            min_force_variation_n=declare(self, "min_force_variation_n", 30.0,
                                          "[N] force std a window needs to be called rigid", low=0.0, high=1e4,
                                          read_only=True))
        self.model = RobotModel.from_name(robot)
        self.tce = TerrainComplianceEstimator(self.model, settings)
        self.joint_index = {name: i for i, name in enumerate(self.model.description.joint_names)}
        self.period_ns = round(period * 1e9)
        self._next_tick_ns = 0
        self._base: tuple[int, object] | None = None
        self._grid = None
        self._accelerations = FiniteDifferenceAcceleration(max_gap_s=1.5 * period)
        self.rejected_inputs = 0
        self.samples_outside_map = 0
        self.ticks = 0
        self.summary_path = declare(self, "summary_path", "", "JSON file for the end-of-run summary (final "
                                    "estimates, 10 Hz estimate history); empty: none", read_only=True)
        self.history: list[list[float]] = []    # [t [s], k x4 [N/m], valid x4] every HISTORY_DECIMATION ticks
        self.pub = self.create_publisher(TerrainImpedance, "terrain_impedance", 10)
        topic = "ground_truth/odom" if base_source == "ground_truth" else "state_estimate"
        self.create_subscription(JointState, "joint_states", self._on_joints, 10)
        self.create_subscription(Odometry, topic, self._on_base, 10)
        self.create_subscription(HeightMap, "terrain/heightmap", self._on_heightmap, 10)

    def _reject(self, what: str, exc: Exception) -> None:
        self.rejected_inputs += 1
        self.get_logger().warn(f"rejected {what} ({self.rejected_inputs} so far): {exc}", throttle_duration_sec=1.0)

    def _on_base(self, msg: Odometry) -> None:
        try:
            self._base = (ns_from_stamp(msg.header.stamp), base_state_from_odometry(msg))
        except InputError as exc:
            self._reject("base state", exc)

    def _on_heightmap(self, msg: HeightMap) -> None:
        try:
            self._grid = heightmap_grid(msg)
        except InputError as exc:
            self._reject("heightmap", exc)

    def _on_joints(self, msg: JointState) -> None:
        stamp = ns_from_stamp(msg.header.stamp)
        if not reaches_tick(stamp, self._next_tick_ns) or self._base is None or self._grid is None:
            return
        self._next_tick_ns = tick_after(stamp, self.period_ns)
        base_stamp, base = self._base
        if stamp - base_stamp > self.stale_periods * self.period_ns:
            return
        try:
            q_joints, qd_joints = canonical_joint_state(msg, self.joint_index)
            tau = np.full(len(self.joint_index), np.nan)
            for name, effort in zip(msg.name, msg.effort):
                tau[self.joint_index[name]] = effort
            q = self.model.make_q(base.position, base.quat_xyzw, q_joints)
            v = self.model.make_v(base.linear_velocity, base.angular_velocity, qd_joints, base.quat_xyzw)
            grid = self._grid
            samples = self.tce.contact_states(q, v, tau, height=lambda x, y: float(grid.height_at(x, y)),
                                              vdot=self._accelerations.update(stamp * 1e-9, v))
        except (InputError, ValueError) as exc:
            self._reject("joint_states", exc)
            return
        usable = []
        for sample in samples:
            if sample.in_contact and not math.isfinite(sample.penetration_m):
                self.samples_outside_map += 1
                usable.append(type(sample)(False, sample.force_n, sample.normal, 0.0, 0.0))
            else:
                usable.append(sample)
        estimates = self.tce.update(usable)
        out = TerrainImpedance()
        out.header.stamp = stamp_from_ns(stamp)
        out.header.frame_id = "world"
        tangential = self.tce.tangential_estimates
        for leg, (sample, est) in enumerate(zip(usable, estimates)):
            out.stiffness_normal[leg] = est.stiffness_n_per_m
            out.damping_normal[leg] = est.damping_ns_per_m
            out.stiffness_tangential[leg] = tangential[leg].stiffness_n_per_m if tangential else float("nan")
            out.damping_tangential[leg] = tangential[leg].damping_ns_per_m if tangential else float("nan")
            n = sample.normal
            out.normal[leg] = Vector3(x=float(n[0]), y=float(n[1]), z=float(n[2]))
            out.confidence[leg] = est.confidence
            out.samples[leg] = est.samples
            out.valid[leg] = est.valid
        self.pub.publish(out)
        if self.ticks % HISTORY_DECIMATION == 0:
            self.history.append([stamp * 1e-9] + [e.stiffness_n_per_m for e in estimates]
                                + [float(e.valid) for e in estimates])
        self.ticks += 1

    def summary(self) -> dict:
        """Final per-leg estimates, counters and the estimate history (NaN as null)."""
        def clean(value: float) -> float | None:
            return value if math.isfinite(value) else None

        estimates = self.tce.estimates
        return {
            "ticks": self.ticks, "rejected_inputs": self.rejected_inputs,
            "samples_outside_map": self.samples_outside_map,
            "edge_samples_per_leg": self.tce.edge_samples.tolist(),
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
