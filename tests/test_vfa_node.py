"""The vfa node in a real rclpy graph: it adapts footholds around a gap in the heightmap, passes the
nominal through flagged without a map, rejects (and counts) bad messages without stopping, reports on
vfa/diagnostics and refuses invalid parameters at start-up."""

from __future__ import annotations

import math

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from vital_fakes import MS, FakeWbc

from tal_core.ros.node_utils import ns_from_stamp
from tal_msgs.msg import FootholdArray, GaitState
from tal_perception.errors import FecConfigError
from tal_perception.vfa_node import VfaNode

pytestmark = pytest.mark.ros

def start(context, **overrides):
    vfa = VfaNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
    wbc = FakeWbc(context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(vfa)
    executor.add_node(wbc.node)
    return vfa, wbc, executor


def stop(executor, *nodes) -> None:
    executor.shutdown()
    for node in nodes:
        node.destroy_node()


def by_leg(msg: FootholdArray) -> dict:
    return {f.leg: f for f in msg.footholds}


def test_passes_the_nominal_through_without_a_map_and_adapts_around_a_gap(context, spin_until) -> None:
    vfa, wbc, executor = start(context, diagnostics_period_s=0.1)
    try:
        assert spin_until(executor, wbc.matched, 20.0)
        # No map yet: one foothold per swinging leg, the nominal, flagged.
        wbc.gait.publish(wbc.gait_state(1000 * MS))
        assert spin_until(executor, lambda: len(wbc.footholds) == 1, 10.0)
        blind = wbc.footholds[0]
        assert ns_from_stamp(blind.header.stamp) == 1000 * MS and blind.header.frame_id == "world"
        assert sorted(by_leg(blind)) == [0, 3]
        for leg, foothold in by_leg(blind).items():
            assert foothold.step_count == 3 and not foothold.safe_candidate_found and foothold.score == 0.0
            assert foothold.safe_candidates == 0
            assert (foothold.selected.x, foothold.selected.y, foothold.selected.z) == pytest.approx(tuple(wbc.nominal(leg)))
        # Later ticks of the same swing without news: nothing published.
        wbc.gait.publish(wbc.gait_state(1004 * MS))
        spin_until(executor, lambda: vfa.gait_states == 2, 5.0)
        # A map with a gap under LF's nominal: both legs re-decided, LF moved off the gap onto the ground.
        # (A map comes into use at the first gait state one control period after its stamp.)
        wbc.maps.publish(wbc.heightmap(1004 * MS, gap_at_x=wbc.nominal(0)[0]))
        assert spin_until(executor, lambda: len(vfa.maps_inbox) == 1, 5.0)
        wbc.gait.publish(wbc.gait_state(1008 * MS))
        assert spin_until(executor, lambda: len(wbc.footholds) == 2, 10.0)
        seen = by_leg(wbc.footholds[1])
        assert ns_from_stamp(wbc.footholds[1].header.stamp) == 1008 * MS and sorted(seen) == [0, 3]
        lf, rh = seen[0], seen[3]
        assert lf.safe_candidate_found and lf.score == 1.0 and lf.safe_candidates >= 1
        assert abs(lf.selected.x - wbc.nominal(0)[0]) >= 0.09 and lf.selected.z == pytest.approx(0.0)
        assert (rh.selected.x, rh.selected.y, rh.selected.z) == pytest.approx(tuple(wbc.nominal(3)))
        # Diagnostics on vfa/diagnostics: decisions by status and the selection time.
        assert spin_until(executor, lambda: any(
            dict((kv.key, kv.value) for kv in d.status[0].values).get("decisions_selected") == "2"
            for d in wbc.diagnostics), 5.0)
        values = {kv.key: kv.value for kv in wbc.diagnostics[-1].status[0].values}
        assert values["decisions_no_map"] == "2" and values["trigger_new_map"] == "2" and values["adapted"] == "1"
        assert 0.0 < float(values["selection_time_median_ms"]) <= float(values["selection_time_max_ms"])
        assert wbc.diagnostics[-1].status[0].name == "/vfa" and wbc.diagnostics[-1].status[0].level == DiagnosticStatus.OK
    finally:
        stop(executor, vfa, wbc.node)


def test_bad_messages_are_counted_and_the_node_keeps_running(context, spin_until) -> None:
    vfa, wbc, executor = start(context)
    try:
        assert spin_until(executor, wbc.matched, 20.0)
        wbc.maps.publish(wbc.heightmap(1000 * MS))
        short = wbc.heightmap(1001 * MS)
        short.heights = short.heights[:-1]
        wbc.maps.publish(short)
        foreign = wbc.heightmap(1002 * MS)
        foreign.header.frame_id = "odom"
        wbc.maps.publish(foreign)
        wbc.maps.publish(wbc.heightmap(990 * MS))  # older than the map in use
        nan_centre = wbc.heightmap(1003 * MS)
        nan_centre.center.x = math.nan
        wbc.maps.publish(nan_centre)
        assert spin_until(executor, lambda: sum(vfa.rejections.values()) == 4 and len(vfa.maps_inbox) == 1,
                          10.0), vfa.rejections
        wbc.gait.publish(wbc.gait_state(1004 * MS))
        assert spin_until(executor, lambda: len(wbc.footholds) == 1, 10.0)
        bad = wbc.gait_state(1008 * MS)
        bad.nominal_foothold[3].y = math.nan
        wbc.gait.publish(bad)
        wbc.gait.publish(wbc.gait_state(1000 * MS))  # before the last gait state
        untimed = wbc.gait_state(1012 * MS)
        untimed.time_to_touchdown[0] = -0.1
        wbc.gait.publish(untimed)
        assert spin_until(executor, lambda: sum(vfa.rejections.values()) == 7, 10.0), vfa.rejections
        assert vfa.rejections == {"heightmap_size": 1, "heightmap_frame": 1, "heightmap_out_of_order": 1,
                                  "heightmap_invalid": 1, "gait_state_nan": 1, "gait_state_out_of_order": 1,
                                  "gait_state_invalid": 1}
        # Still running: a map with a gap under LF arrives, and the next gait state adapts LF.
        wbc.maps.publish(wbc.heightmap(1012 * MS, gap_at_x=wbc.nominal(0)[0]))
        assert spin_until(executor, lambda: len(vfa.maps_inbox) == 1, 10.0)  # topics are not ordered with each other
        wbc.gait.publish(wbc.gait_state(1016 * MS))
        assert spin_until(executor, lambda: len(wbc.footholds) == 2, 10.0)
        assert abs(by_leg(wbc.footholds[1])[0].selected.x - wbc.nominal(0)[0]) >= 0.09
        # A map received before, sent again (a lockstep bridge re-sends its recent maps while a tick waits):
        # a repeat, not an input out of order.
        repeats = vfa.counters()["duplicate_heightmaps"]
        wbc.maps.publish(wbc.heightmap(1000 * MS))
        assert spin_until(executor, lambda: vfa.counters()["duplicate_heightmaps"] == repeats + 1, 10.0)
        assert sum(vfa.rejections.values()) == 7, vfa.rejections
        assert vfa.counters()["rejected_gait_state_nan"] == 1
    finally:
        stop(executor, vfa, wbc.node)


def test_invalid_parameters_are_refused_at_start(context) -> None:
    with pytest.raises(FecConfigError, match=r"selector must be one of \['exact', 'cnn', 'cnn_unverified'\], "
                                                r"got 'learned'"):
        VfaNode(context=context, parameter_overrides=[Parameter("selector", value="learned")])
    with pytest.raises(ValueError, match=r"parameter 'max_map_age_s'"):
        VfaNode(context=context, parameter_overrides=[Parameter("max_map_age_s", value=-1.0)])
    with pytest.raises(ValueError, match=r"parameter 'min_swing_time_left_s'"):
        VfaNode(context=context, parameter_overrides=[Parameter("min_swing_time_left_s", value=1)])  # int, not float


@pytest.mark.slow
def test_closed_loop_on_stairs_the_wbc_takes_adapted_footholds(context, spin_until) -> None:
    """sim_bridge (stairs course) + wbc (ground-truth base) + vfa + cmd_vel_script in one executor: HyQ
    trots from 0.5 m before the first riser; the vfa moves footholds off the step edges and the wbc swings
    to them (its gait_state target of that swing equals the selection). 2 s of sim time: 25-40 s of wall
    time on the loaded 2-core machine (8 of 8 adapted footholds accepted when measured)."""
    from tal_control.cmd_vel_script_node import CmdVelScriptNode
    from tal_control.wbc_node import WbcNode
    from tal_sim_bridge.sim_bridge_node import SimBridgeNode

    bridge = SimBridgeNode(context=context, parameter_overrides=[
        Parameter("duration_s", value=2.0), Parameter("course", value="stairs"), Parameter("initial_x_m", value=0.5),
        Parameter("heightmap_rows", value=121), Parameter("heightmap_cols", value=121)])
    wbc = WbcNode(context=context, parameter_overrides=[Parameter("state_source", value="ground_truth")])
    vfa = VfaNode(context=context)
    script = CmdVelScriptNode(context=context, parameter_overrides=[
        Parameter("profile", value=[0.0, 0.0, 0.0, 0.0, 0.5, 0.3, 0.0, 0.0])])
    probe = rclpy.create_node("probe", context=context)
    footholds: list[FootholdArray] = []
    gaits: list[GaitState] = []
    probe.create_subscription(FootholdArray, "footholds", footholds.append, 100)
    probe.create_subscription(GaitState, "gait_state", gaits.append, 1000)
    executor = SingleThreadedExecutor(context=context)
    nodes = (bridge, wbc, vfa, script, probe)
    for node in nodes:
        executor.add_node(node)
    try:
        assert spin_until(executor, lambda: bridge.finished, 300.0)
        spin_until(executor, lambda: False, 0.3)
        end = bridge.core.sim.robot_state().base_position_m.copy()
    finally:
        stop(executor, *nodes)
    assert bridge.final_summary["lockstep_timeouts"] == 0 and bridge.final_summary["body_ground_contact"] == []
    adapted = [(ns_from_stamp(m.header.stamp), f) for m in footholds for f in m.footholds
               if math.hypot(f.selected.x - f.nominal.x, f.selected.y - f.nominal.y) > 1e-6]
    assert adapted, vfa.counters()

    def accepted(stamp_ns: int, foothold) -> bool:
        return any(ns_from_stamp(g.header.stamp) > stamp_ns and g.swing[foothold.leg]
                   and g.step_count[foothold.leg] == foothold.step_count
                   and math.hypot(g.target_foothold[foothold.leg].x - foothold.selected.x,
                                  g.target_foothold[foothold.leg].y - foothold.selected.y) < 1e-6 for g in gaits)
    assert sum(accepted(stamp, f) for stamp, f in adapted) >= 1
    assert wbc.rejected_inputs == 0 and sum(vfa.rejections.values()) == 0, vfa.rejections
    assert end[0] > 0.7 and end[2] > 0.5  # walked forward onto the first step and still standing


def test_answer_every_gait_state_sends_an_empty_answer_without_news(context, spin_until) -> None:
    """For a wbc that waits for the answer to each tick (lockstep determinism): news or not, one footholds
    message per gait state, stamped with it."""
    vfa, wbc, executor = start(context, answer_every_gait_state=True)
    try:
        assert spin_until(executor, wbc.matched, 20.0)
        for k in range(3):
            wbc.gait.publish(wbc.gait_state((1000 + 4 * k) * MS))
        assert spin_until(executor, lambda: len(wbc.footholds) == 3, 10.0)
        assert [ns_from_stamp(m.header.stamp) for m in wbc.footholds] == [1000 * MS, 1004 * MS, 1008 * MS]
        assert [len(m.footholds) for m in wbc.footholds] == [2, 0, 0]  # the blind decisions, then no news
        assert vfa.counters()["empty_answers"] == 2 and vfa.counters()["published_messages"] == 1
    finally:
        stop(executor, vfa, wbc.node)


def test_a_repeated_gait_state_gets_the_same_answer_and_map_period_holds_a_gait_state_for_its_map(
        context, spin_until) -> None:
    """A wbc re-sends a gait state whose answer is overdue (lost before DDS matched): the vfa sends its answer
    again without deciding again. With map_period_s a gait state waits for the map due at it, however late the
    map comes (lockstep runs repeat themselves)."""
    vfa, wbc, executor = start(context, answer_every_gait_state=True, map_period_s=0.05)
    try:
        assert spin_until(executor, wbc.matched, 20.0)
        wbc.maps.publish(wbc.heightmap(950 * MS))
        assert spin_until(executor, lambda: len(vfa.maps_inbox) == 1, 5.0)
        wbc.gait.publish(wbc.gait_state(1000 * MS))            # its map (950 ms) is here
        assert spin_until(executor, lambda: len(wbc.footholds) == 1, 10.0)
        wbc.gait.publish(wbc.gait_state(1000 * MS))            # re-sent: answered again, not decided again
        assert spin_until(executor, lambda: len(wbc.footholds) == 2, 10.0)
        assert [by_leg(m).keys() for m in wbc.footholds] == [{0, 3}, {0, 3}] and vfa.gait_states == 1
        assert vfa.counters()["answers_resent"] == 1
        wbc.gait.publish(wbc.gait_state(1004 * MS))            # due: the map of 1000 ms, not here yet
        spin_until(executor, lambda: False, 0.5)
        assert len(wbc.footholds) == 2 and vfa.counters()["gait_states_held_for_maps"] == 1
        wbc.maps.publish(wbc.heightmap(1000 * MS, gap_at_x=wbc.nominal(0)[0]))
        assert spin_until(executor, lambda: len(wbc.footholds) == 3, 10.0)
        assert ns_from_stamp(wbc.footholds[2].header.stamp) == 1004 * MS
        lf = by_leg(wbc.footholds[2])[0]                       # the gap map came into use: LF moved off it
        assert abs(lf.selected.x - wbc.nominal(0)[0]) >= 0.09
        assert vfa.counters()["late_maps"] == 0 and vfa.counters()["gait_states_released_without_map"] == 0
    finally:
        stop(executor, vfa, wbc.node)
