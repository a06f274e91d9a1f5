"""Node ``vfa``: ViTAL's Vision-based Foothold Adaptation, a thin adapter over ``vfa_planner``.

Subscribes: ``gait_state`` (tal_msgs/GaitState, from the wbc), ``terrain/heightmap`` (tal_msgs/HeightMap).
Publishes: ``footholds`` (tal_msgs/FootholdArray: the new or changed decisions of one gait-state tick,
header stamp = that gait state's stamp, frame "world"; nothing when there is no news, or with
answer_every_gait_state an empty array, so that a wbc can wait for the answer to each tick) and
``vfa/diagnostics`` (diagnostic_msgs/DiagnosticArray, every ``diagnostics_period_s`` of node time:
decisions by status and trigger, rejections by reason, selection time median/max).

The selection runs in the gait-state callback (the exact lazy selection took a median of 2-6 ms per
swinging leg in the closed loop on this loaded machine, at most ~13 ms; it is measured and reported).
Bad input (NaN, wrong array sizes, wrong frame, stamps
going backwards) is rejected, counted by reason and logged at most once per second; it never stops
the node. A heightmap comes into use at the first gait state ``map_lag_s`` (one control period) after its
stamp (``tal_core.ticks.StampedInbox``: one stamped with the tick itself may arrive before or after that
tick's gait state). With ``map_period_s`` (lockstep: the bridge's heightmap period) a gait state also waits
for the map due at it (``tal_core.ticks.HeldTicks``): DDS gives no order between topics, and a large map can
come after the next gait state, so lockstep runs repeat themselves bit for bit; maps that came after the
gait state that should have used them are counted (``late_maps``). A heightmap with the stamp of the one in
use is a duplicate: ignored, counted apart. A clock
that jumps back by more than 0.5 s (a restarted simulation) restarts the planner. A missing or stale
map, or a patch without a safe candidate, publishes the nominal foothold with ``safe_candidate_found``
false (see ``vfa_planner``).
"""

from __future__ import annotations

from collections import Counter, deque

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point
from rclpy.node import Node

from tal_core.errors import InputError
from tal_core.heightmap import HeightMapGrid
from tal_core.robot_model import RobotModel
from tal_core.ros.cdr import CdrView, subscribe_view
from tal_core.ros.conversions import heightmap_grid
from tal_core.ros.node_utils import declare, ns_from_stamp, run_node, stamp_from_ns, write_summary
from tal_core.ticks import CLOCK_RESET_NS, HeldTicks, StampedInbox, TickAnswers
from tal_msgs.msg import Foothold, FootholdArray, GaitState, HeightMap

from .errors import VfaInputError
from .vfa import VfaStatus
from .vfa_planner import SELECTORS, FootholdDecision, GaitSnapshot, PlannerSettings, VfaPlanner

FRAME = "world"
TIMING_WINDOW = 1000  # selections kept for the timing statistics (the latest ones)


def gait_snapshot_from_view(view: CdrView) -> GaitSnapshot:
    """GaitSnapshot (plain arrays, world frame) of a serialised tal_msgs/GaitState read in place
    (``tal_core.ros.cdr.CdrView``: no Python message with a Point object per position); VfaInputError on bad
    content."""
    frame = view.per_layout("frame_id", lambda msg: msg.header.frame_id)
    if frame != FRAME:
        raise VfaInputError("gait_state_frame", f"gait_state frame_id must be '{FRAME}', got '{frame}'")
    return GaitSnapshot(
        stamp_s=view.stamp_ns * 1e-9, step_frequency_hz=float(view.array("step_frequency")[0]),
        duty_factor=float(view.array("duty_factor")[0]), step_height_m=float(view.array("step_height")[0]),
        base_twist=np.concatenate([view.vector("base_twist.linear"), view.vector("base_twist.angular")]),
        swing=view.array("swing").astype(bool), time_to_touchdown_s=view.array("time_to_touchdown").astype(float),
        step_count=view.array("step_count").astype(np.int64),
        liftoff_position=view.vectors("liftoff_position").copy(),
        nominal_foothold=view.vectors("nominal_foothold").copy(), hip_position=view.vectors("hip_position").copy(),
        hip_velocity=view.vectors("hip_velocity").copy())


def grid_from_message(msg: HeightMap) -> tuple[HeightMapGrid, float]:
    """HeightMapGrid and stamp [s] of a tal_msgs/HeightMap; VfaInputError (with the reason the ViTAL nodes
    count) on a wrong frame, a size mismatch or a NaN centre, yaw or resolution."""
    if msg.header.frame_id != FRAME:
        raise VfaInputError("heightmap_frame", f"heightmap frame_id must be '{FRAME}', got '{msg.header.frame_id}'")
    if len(msg.heights) != msg.rows * msg.cols:
        raise VfaInputError("heightmap_size", f"heightmap has {len(msg.heights)} heights for "
                            f"{msg.rows} x {msg.cols} cells")
    try:
        grid = heightmap_grid(msg)
    except InputError as exc:
        raise VfaInputError("heightmap_invalid", str(exc)) from None
    return grid, ns_from_stamp(msg.header.stamp) * 1e-9


def foothold_message(decision: FootholdDecision) -> Foothold:
    """tal_msgs/Foothold of a decision. safe_candidates: the count when the selector knows it, otherwise
    a lower bound (1 when a safe candidate was found, 0 when none was or nothing was evaluated)."""
    count = decision.safe_candidates
    if count is None:
        count = 1 if decision.safe_candidate_found else 0
    return Foothold(leg=int(decision.leg), step_count=int(decision.step_count), nominal=_point(decision.nominal),
                    selected=_point(decision.selected), safe_candidate_found=decision.safe_candidate_found,
                    safe_candidates=int(count), score=float(decision.score))


class VfaNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("vfa", **kwargs)
        robot = declare(self, "robot", "hyq", "robot YAML: shipped name or path")
        selector = declare(self, "selector", "exact", f"foothold selector: one of {', '.join(SELECTORS)} "
                           "(exact: lazy exact evaluation of the foothold evaluation criteria)")
        settings = PlannerSettings(
            max_map_age_s=declare(self, "max_map_age_s", 0.5, "[s] a heightmap further than this from the gait "
                                  "state's stamp is stale (nominal passed through)", low=0.001, high=60.0),
            min_swing_time_left_s=declare(self, "min_swing_time_left_s", 0.08, "[s] no (re-)decision with less "
                                          "swing time left (the wbc accepts footholds until 0.05 s)", low=0.0,
                                          high=2.0),
            nominal_shift_threshold_m=declare(self, "nominal_shift_threshold_m", 0.02, "[m] re-decide when the "
                                              "nominal foothold moved this far since the last decision", low=0.0,
                                              high=1.0),
            reevaluate_on_new_map=declare(self, "reevaluate_on_new_map", True, "re-decide when a newer heightmap "
                                          "arrives during a swing"),
            level_lock_swing_fraction=declare(self, "level_lock_swing_fraction", 0.35, "[-] after this fraction "
                                              "of the swing a re-decision may not change the foothold's level "
                                              "(the swing can no longer re-plan its apex)", low=0.0, high=1.0),
            level_lock_dz_m=declare(self, "level_lock_dz_m", 0.02, "[m] a late re-decision moving the foothold "
                                    "height by more than this is not taken", low=0.0, high=1.0),
            pair_compensation_m=declare(self, "pair_compensation_m", 0.0, "[m] largest shift of a swinging "
                                        "diagonal partner's nominal against the other leg's adaptation, so the "
                                        "trot's support line stays under the CoM (0: off, the thesis' VFA; "
                                        "0.08 in ViTAL's stairs runs)", low=0.0, high=0.3),
            predict_hip_descent=declare(self, "predict_hip_descent", False, "evaluate a swing at its hip's "
                                        "predicted height at touchdown (gait_state hip_velocity) when that is "
                                        "lower than now (the way down stairs)"))
        self.diagnostics_period_s = declare(self, "diagnostics_period_s", 1.0, "[s] diagnostics period (node "
                                            "clock: sim time with use_sim_time)", low=0.05, high=60.0)
        self.answer_every_gait_state = declare(self, "answer_every_gait_state", False,
                                               "publish an (empty) footholds answer to every gait state "
                                               "(a wbc with wait_for_footholds waits for it)")
        map_lag_s = declare(self, "map_lag_s", 0.004, "[s] a heightmap is used from the first gait state this "
                            "long after its stamp (the control period)", low=0.0, high=1.0)
        map_period_s = declare(self, "map_period_s", 0.0, "[s] the heightmap's publishing period on the sim-time "
                               "grid: a gait state waits for the map due at it (lockstep); 0: maps are used as "
                               "they arrive", low=0.0, high=10.0)
        self.maps_inbox = StampedInbox(round(map_lag_s * 1e9), period_ns=round(map_period_s * 1e9))
        self.held = HeldTicks([self.maps_inbox])
        self.answers = TickAnswers()  # a wbc re-sends a gait state whose answer is overdue
        self._newest_map_ns: int | None = None
        self.summary_path = declare(self, "summary_path", "", "JSON file for the counters written at shutdown "
                                    "('' = none)",
                                    on_change=lambda value: setattr(self, "summary_path", value))
        self.planner = VfaPlanner.for_robot(RobotModel.from_name(robot), selector, settings)
        self.selector_name = selector
        warm_up_s = self.planner.warm_up()  # the first selections build caches (~30 ms): not in a callback
        self.rejections: Counter[str] = Counter()
        self.selection_ms: deque[float] = deque(maxlen=TIMING_WINDOW)
        self.max_selection_ms = 0.0
        self.gait_states = 0
        self.maps = 0
        self.duplicate_maps = 0
        self.published_messages = 0
        self.published_footholds = 0
        self.empty_answers = 0

        self.pub_footholds = self.create_publisher(FootholdArray, "footholds", 10)
        self.pub_diag = self.create_publisher(DiagnosticArray, "vfa/diagnostics", 10)
        # 250 Hz, read in place (building the Python message, a Point per position, cost more than the
        # selections)
        subscribe_view(self, GaitState, "gait_state", self._on_gait_state, 10,
                       on_error=lambda exc: self._reject("gait_state", str(exc)))
        self.create_subscription(HeightMap, "terrain/heightmap", self._on_heightmap, 10)
        self.create_timer(self.diagnostics_period_s, self._publish_diagnostics)
        self.get_logger().info(f"vfa ready: robot '{robot}', selector '{selector}', maps stale after "
                               f"{settings.max_map_age_s} s, warm-up {warm_up_s * 1e3:.0f} ms")

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
        stamp_ns = ns_from_stamp(msg.header.stamp)
        newest = self._newest_map_ns
        if newest is not None and stamp_ns < newest and stamp_ns + CLOCK_RESET_NS >= newest:
            if self.maps_inbox.seen(stamp_ns):
                # a lockstep bridge re-sends its recent maps while a tick waits (a consumer whose subscription
                # matched late): a repeat, counted with the inbox's, not an input out of order
                self.maps_inbox.add(stamp_ns, (grid, stamp_s))
                return
            self._reject("heightmap_out_of_order", f"heightmap stamp {stamp_ns * 1e-9:.6f} s is before the "
                         f"newest one's {newest * 1e-9:.6f} s")
            return
        self._newest_map_ns = stamp_ns
        self.maps_inbox.add(stamp_ns, (grid, stamp_s))
        for _, gait_state in self.held.arrived():
            self._update(gait_state)

    def _use_maps(self, stamp_ns: int) -> None:
        """The heightmaps due at the gait state stamped ``stamp_ns``, oldest first."""
        for _, (grid, stamp_s) in self.maps_inbox.due(stamp_ns):
            try:
                fresh = self.planner.set_map(grid, stamp_s)
            except VfaInputError as exc:
                self._reject(exc.reason, str(exc))
                continue
            if fresh:
                self.maps += 1
            else:
                self.duplicate_maps += 1  # the simulator repeats its first sample until the wbc answers

    def _on_gait_state(self, view: CdrView) -> None:
        stamp_ns = view.stamp_ns
        repeat, again = self.answers.seen(stamp_ns)
        if again is not None:
            self.pub_footholds.publish(again)
        if repeat:
            return
        for _, gait_state in self.held.offer(stamp_ns, view):
            self._update(gait_state)

    def _update(self, view: CdrView) -> None:
        """One gait state whose maps are here: the selections, and the answer."""
        stamp_ns = view.stamp_ns
        self._use_maps(stamp_ns)
        try:
            decisions = self.planner.update(gait_snapshot_from_view(view))
        except VfaInputError as exc:
            self._reject(exc.reason, str(exc))
            return
        except InputError as exc:  # a selector's own input check (should not happen on a valid snapshot)
            self._reject("selector_input", str(exc))
            return
        self.gait_states += 1
        for decision in decisions:
            self._note(decision)
        if not decisions and not self.answer_every_gait_state:
            return
        out = FootholdArray(footholds=[foothold_message(d) for d in decisions])
        out.header.stamp = stamp_from_ns(stamp_ns)
        out.header.frame_id = FRAME
        self.pub_footholds.publish(out)
        self.answers.answered(stamp_ns, out)
        self.published_messages += 1 if decisions else 0
        self.empty_answers += 0 if decisions else 1
        self.published_footholds += len(decisions)

    def _note(self, decision: FootholdDecision) -> None:
        """Timing statistics of evaluated selections; throttled logs of the flagged outcomes."""
        if decision.status in (VfaStatus.SELECTED, VfaStatus.NO_SAFE_CANDIDATE):
            elapsed_ms = decision.elapsed_s * 1e3
            self.selection_ms.append(elapsed_ms)
            self.max_selection_ms = max(self.max_selection_ms, elapsed_ms)
        if decision.status is not VfaStatus.SELECTED:
            self.get_logger().warn(f"{decision.leg.name} step {decision.step_count}: {decision.status.value}, "
                                   "nominal foothold passed through", throttle_duration_sec=1.0)

    # -- outputs ------------------------------------------------------------------------------------
    def counters(self) -> dict[str, int | float | str]:
        """Every counter of the node and the planner (the diagnostics' key-value pairs)."""
        c = self.planner.counters
        timing = np.array(self.selection_ms)
        return {
            "selector": self.selector_name, "gait_states": self.gait_states, "heightmaps": self.maps,
            "duplicate_heightmaps": self.duplicate_maps + self.maps_inbox.repeats, "late_maps": self.maps_inbox.late,
            "missed_maps": self.maps_inbox.missed,
            "gait_states_held_for_maps": self.held.held_ticks,
            "gait_states_released_without_map": self.held.released_late, "answers_resent": self.answers.resent,
            "published_messages": self.published_messages, "published_footholds": self.published_footholds,
            "empty_answers": self.empty_answers,
            **{f"decisions_{k}": v for k, v in c.by_status.items()},
            **{f"trigger_{k}": v for k, v in c.by_trigger.items()},
            "adapted": c.adapted, "late_swings": c.late_swings, "restarts": c.restarts, "kept": c.kept,
            "level_locked": c.level_locked,
            **{f"rejected_{k}": v for k, v in sorted(self.rejections.items())},
            "selection_time_median_ms": round(float(np.median(timing)), 3) if timing.size else 0.0,
            "selection_time_max_ms": round(float(timing.max()), 3) if timing.size else 0.0,
            "selection_time_max_ever_ms": round(self.max_selection_ms, 3), "selection_time_samples": int(timing.size),
        }

    def _publish_diagnostics(self) -> None:
        values = self.counters()
        rejected = sum(self.rejections.values())
        status = DiagnosticStatus(name=self.get_fully_qualified_name(), hardware_id="tal")
        status.level = DiagnosticStatus.OK if rejected == 0 else DiagnosticStatus.WARN
        status.message = "ok" if rejected == 0 else f"{rejected} inputs rejected"
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)

    def destroy_node(self) -> None:
        write_summary(self.summary_path, self.counters())
        super().destroy_node()


def _point(xyz: np.ndarray) -> Point:
    return Point(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: VfaNode(), args, name="vfa")


if __name__ == "__main__":
    raise SystemExit(main())
