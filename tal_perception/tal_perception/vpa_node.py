"""Node ``vpa``: ViTAL's Vision-based Pose Adaptation (or the TBR baseline), a thin adapter over
``vpa_planner``.

Subscribes: ``gait_state`` (tal_msgs/GaitState, from the wbc: the clock of the updates, the hips and the
commanded twist), ``terrain/heightmap`` (tal_msgs/HeightMap), ``footholds`` (tal_msgs/FootholdArray, the
vfa's selections, used by the TBR baseline).
Publishes: ``body_pose_reference`` (tal_msgs/BodyPoseReference, stamp = the gait state's, frame "world")
every ``update_period_s`` of gait-state time, and ``vpa/diagnostics`` (diagnostic_msgs/DiagnosticArray
every ``diagnostics_period_s`` of node time: updates by status, rejections by reason, update time
median/max).

The update runs in the gait-state callback: with the CNN it took a median of 15.6 ms (p99 26.6 ms) in
``bench/bench_vpa.py``, so 20 Hz is the default; the exact evaluation (median 223 ms) needs
``update_period_s`` >= 0.25 (the thesis ran it at 5 Hz). Bad input (NaN, wrong sizes, wrong frame,
stamps going backwards) is rejected, counted by reason and logged at most once per second; it never
stops the node. A missing or stale map holds the default pose (nominal height, level), flagged with
``optimal`` false and counted. Heightmaps and footholds come into use at the first update ``input_lag_s``
(one control period) after their stamp (``tal_core.ticks.StampedInbox``); with ``map_period_s`` (lockstep:
the bridge's heightmap period) a gait state also waits for the map due at it (``tal_core.ticks.HeldTicks``),
so that lockstep runs repeat themselves bit for bit. Maps that came after the update that should have used
them are counted (``late_maps``). The TBR baseline's footholds are not waited for.
"""

from __future__ import annotations

import math
from collections import Counter, deque

import numpy as np
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from tal_core.errors import InputError
from tal_core.legs import NUM_LEGS
from tal_core.robot_model import RobotModel
from tal_core.ros.cdr import CdrView, subscribe_view
from tal_core.ros.node_utils import declare, ns_from_stamp, run_node, stamp_from_ns, write_summary
from tal_core.ticks import HeldTicks, StampedInbox, TickAnswers
from tal_msgs.msg import BodyPoseReference, FootholdArray, GaitState, HeightMap

from .errors import VfaInputError
from .vfa_node import FRAME, gait_snapshot_from_view, grid_from_message
from .vpa_planner import SOURCES, PosePlanner, PoseReference
from .vpa_settings import LEG_WEIGHTINGS, SWING_HIP_MODELS, CostKind, VpaSettings

TIMING_WINDOW = 1000  # updates kept for the timing statistics (the latest ones)


def pose_message(reference: PoseReference) -> BodyPoseReference:
    """tal_msgs/BodyPoseReference of a reference (header filled by the caller)."""
    return BodyPoseReference(
        source=reference.source, base_height=float(reference.base_height_m), roll=float(reference.roll_rad),
        pitch=float(reference.pitch_rad), hip_height=[float(v) for v in reference.hip_heights_m],
        safe_footholds=[int(v) for v in reference.safe_footholds], horizon=float(reference.horizon_s),
        optimal=bool(reference.optimal))


class VpaNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("vpa", **kwargs)
        robot = declare(self, "robot", "hyq", "robot YAML: shipped name or path")
        source = declare(self, "source", "vpa", f"pose reference source: one of {', '.join(SOURCES)} (tbr: the "
                         "thesis' baseline)", choices=SOURCES)
        use_cnn = declare(self, "use_cnn", True, "VPA: CNN pose evaluation (committed weights) instead of the "
                          "exact one")
        period = declare(self, "update_period_s", 0.05, "[s] gait-state time between updates (0.05: 20 Hz)",
                         low=0.004, high=10.0)
        cost = declare(self, "cost", "int", "pose optimiser cost: sum, prod or int (C_int with cost_margin_m)",
                       choices=[c.value for c in CostKind])
        settings = VpaSettings(
            cost=CostKind(cost),
            cost_margin_m=declare(self, "cost_margin_m", 0.025, "[m] C_int margin", low=0.0, high=0.2),
            horizon=declare(self, "horizon", 2, "[-] receding horizon stages N_h", low=1, high=5),
            max_map_age_s=declare(self, "max_map_age_s", 0.5, "[s] a heightmap older than this (gait-state time) "
                                  "is stale: default pose held", low=0.001, high=60.0),
            swing_hip_model=declare(self, "swing_hip_model", "level", "exact evaluation: the hip during the swing, "
                                    "level (thesis) or terrain (follows the terrain from lift-off to touchdown)",
                                    choices=SWING_HIP_MODELS),
            leg_weighting=declare(self, "leg_weighting", "none", "optimiser: none (thesis) or peak (each leg's "
                                  "curve divided by its peak)", choices=LEG_WEIGHTINGS))
        tbr_height = declare(self, "tbr_height_m", 0.0, "[m] TBR: base height above the footholds' plane "
                             "(0: the robot's nominal height)", low=0.0, high=2.0)
        self.diagnostics_period_s = declare(self, "diagnostics_period_s", 1.0, "[s] diagnostics period (node "
                                            "clock)", low=0.05, high=60.0)
        input_lag = round(declare(self, "input_lag_s", 0.004, "[s] a heightmap or foothold is used from the first "
                                  "update this long after its stamp (the control period)", low=0.0, high=1.0) * 1e9)
        map_period = round(declare(self, "map_period_s", 0.0, "[s] the heightmap's publishing period on the sim-time "
                                   "grid: an update waits for the map due at it (lockstep); 0: maps are used as "
                                   "they arrive", low=0.0, high=10.0) * 1e9)
        self.maps_inbox = StampedInbox(input_lag, period_ns=map_period)
        self.footholds_inbox = StampedInbox(input_lag)
        self.held = HeldTicks([self.maps_inbox])
        self.answers = TickAnswers()  # a wbc re-sends a gait state whose answer is overdue
        self.summary_path = declare(self, "summary_path", "", "JSON file for the counters written at shutdown "
                                    "('' = none)",
                                    on_change=lambda value: setattr(self, "summary_path", value))
        # The CNN is small: a second intra-op thread only contends with the other nodes (2 threads on the
        # loaded 2-core machine took 258 ms per update instead of 11-20 ms).
        torch.set_num_threads(declare(self, "torch_threads", 1, "[-] torch intra-op threads", low=1, high=64))
        self.planner = PosePlanner(RobotModel.from_name(robot), source, use_cnn=use_cnn, update_period_s=period,
                                   tbr_height_m=tbr_height or None, settings=settings)
        self.source = source
        self.rejections: Counter[str] = Counter()
        self.by_status: Counter[str] = Counter()
        self.update_ms: deque[float] = deque(maxlen=TIMING_WINDOW)
        self.max_update_ms = 0.0
        self.published = 0
        self._targets: np.ndarray | None = None

        self.pub_pose = self.create_publisher(BodyPoseReference, "body_pose_reference", 10)
        self.pub_diag = self.create_publisher(DiagnosticArray, "vpa/diagnostics", 10)
        # 250 Hz in, an update every update_period_s: only the gait states the planner uses are deserialised.
        subscribe_view(self, GaitState, "gait_state", self._on_gait_state, 10,
                       wants=lambda stamp: self.planner.wants(stamp) or stamp == self.answers.answered_ns,
                       on_error=lambda exc: self._reject("gait_state", str(exc)))
        self.create_subscription(HeightMap, "terrain/heightmap", self._on_heightmap, 10)
        self.create_subscription(FootholdArray, "footholds", self._on_footholds, 10)
        self.create_timer(self.diagnostics_period_s, self._publish_diagnostics)
        self.get_logger().info(f"vpa ready: robot '{robot}', source '{source}'"
                               + (f", {'CNN' if use_cnn else 'exact'} evaluation, cost {cost}" if source == "vpa"
                                  else "") + f", every {period} s")

    # -- inputs -------------------------------------------------------------------------------------
    def _reject(self, reason: str, message: str) -> None:
        self.rejections[reason] += 1
        self.get_logger().warn(f"rejected ({reason}, {self.rejections[reason]} so far): {message}",
                               throttle_duration_sec=1.0)

    def _on_heightmap(self, msg: HeightMap) -> None:
        try:
            grid, stamp_s = grid_from_message(msg)
        except VfaInputError as exc:
            self._reject(exc.reason, str(exc))
            return
        self.maps_inbox.add(ns_from_stamp(msg.header.stamp), (grid, stamp_s))
        for _, gait_state in self.held.arrived():
            self._update(gait_state)

    def _on_footholds(self, msg: FootholdArray) -> None:
        valid = []
        for foothold in msg.footholds:
            point = (foothold.selected.x, foothold.selected.y, foothold.selected.z)
            if 0 <= foothold.leg < NUM_LEGS and all(math.isfinite(v) for v in point):
                valid.append((int(foothold.leg), point))
            else:
                self._reject("foothold_invalid", f"foothold of leg {foothold.leg} at {point} (legs 0-3, finite [m])")
        if valid:  # a vfa answering every gait state sends empty arrays too
            self.footholds_inbox.add(ns_from_stamp(msg.header.stamp), valid)

    def _use_inputs(self, stamp_ns: int) -> None:
        """The heightmaps and footholds due at the gait state stamped ``stamp_ns``, oldest first."""
        for _, (grid, stamp_s) in self.maps_inbox.due(stamp_ns):
            try:
                self.planner.set_map(grid, stamp_s)
            except VfaInputError as exc:
                self._reject(exc.reason, str(exc))
        for _, footholds in self.footholds_inbox.due(stamp_ns):
            for leg, point in footholds:
                self.planner.set_foothold(leg, point)

    def _on_gait_state(self, view: CdrView) -> None:
        stamp_ns = view.stamp_ns
        repeat, again = self.answers.seen(stamp_ns)
        if again is not None:
            self.pub_pose.publish(again)
        if repeat:
            return
        for _, gait_state in self.held.offer(stamp_ns, view):
            self._update(gait_state)

    def _update(self, view: CdrView) -> None:
        """One gait state whose maps are here: the planner's update, and the reference it gives."""
        self._use_inputs(view.stamp_ns)
        try:
            snapshot = gait_snapshot_from_view(view)
            targets = view.vectors("target_foothold").copy()
            reference = self.planner.update(snapshot, targets if np.isfinite(targets).all() else None)
        except VfaInputError as exc:
            self._reject(exc.reason, str(exc))
            return
        except InputError as exc:  # the VPA's or TBR's own input checks (e.g. collinear footholds)
            self._reject("pose_input", str(exc))
            return
        if reference is None:
            return
        self.by_status[reference.status] += 1
        elapsed_ms = reference.elapsed_s * 1e3
        self.update_ms.append(elapsed_ms)
        self.max_update_ms = max(self.max_update_ms, elapsed_ms)
        if reference.status not in ("ok", "tbr"):
            self.get_logger().warn(f"{reference.status}: pose held", throttle_duration_sec=1.0)
        out = pose_message(reference)
        out.header.stamp = stamp_from_ns(view.stamp_ns)
        out.header.frame_id = FRAME
        self.pub_pose.publish(out)
        self.answers.answered(view.stamp_ns, out)
        self.published += 1

    # -- outputs ------------------------------------------------------------------------------------
    def counters(self) -> dict[str, int | float | str]:
        timing = np.array(self.update_ms)
        return {
            "source": self.source, "published": self.published, "restarts": self.planner.restarts,
            "late_maps": self.maps_inbox.late, "missed_maps": self.maps_inbox.missed,
            "updates_held_for_maps": self.held.held_ticks,
            "updates_released_without_map": self.held.released_late,
            "answers_resent": self.answers.resent,
            **{f"status_{k}": v for k, v in sorted(self.by_status.items())},
            **{f"rejected_{k}": v for k, v in sorted(self.rejections.items())},
            "update_time_median_ms": round(float(np.median(timing)), 3) if timing.size else 0.0,
            "update_time_max_ms": round(float(timing.max()), 3) if timing.size else 0.0,
            "update_time_max_ever_ms": round(self.max_update_ms, 3),
        }

    def _publish_diagnostics(self) -> None:
        values = self.counters()
        rejected = sum(self.rejections.values())
        held = sum(v for k, v in self.by_status.items() if k not in ("ok", "tbr"))
        status = DiagnosticStatus(name=self.get_fully_qualified_name(), hardware_id="tal")
        status.level = DiagnosticStatus.OK if rejected == 0 and held == 0 else DiagnosticStatus.WARN
        status.message = "ok" if status.level == DiagnosticStatus.OK else f"{rejected} rejected, {held} held"
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)

    def destroy_node(self) -> None:
        write_summary(self.summary_path, self.counters())
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: VpaNode(), args, name="vpa")


if __name__ == "__main__":
    raise SystemExit(main())
