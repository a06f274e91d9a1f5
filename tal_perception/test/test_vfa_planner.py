"""VFA planner: one decision per swing (re-decided on a new map or a moved nominal), adaptation around
gaps, flagged pass-through without a usable map, precise errors on malformed gait states and maps."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from tal_core.errors import InputError
from tal_core.heightmap import HeightMapGrid, extract_heightmap
from tal_core.legs import Leg
from tal_core.robot_model import RobotModel
from tal_core.terrain import Course, DefaultGround, GapPatch, Region, StairsPatch
from tal_perception.errors import FecConfigError, VfaInputError
from tal_perception.fec import FootholdEvaluator
from tal_perception.vfa import FootholdSelector, VfaStatus
from tal_perception.vfa_planner import GaitSnapshot, PlannerSettings, VfaPlanner, make_selector

RIGID = {"stiffness_n_per_m": 2e6, "damping_ns_per_m": 400.0}
TROT = {"step_frequency_hz": 1.5, "duty_factor": 0.6, "step_height_m": 0.1}  # swing 0.267 s, stance 0.4 s
SPEED = 0.3  # [m/s] forward


@pytest.fixture(scope="module")
def hips_base(hyq: RobotModel) -> np.ndarray:
    """(4, 3) [m] HAA joints in the base frame."""
    model = RobotModel(hyq.description)
    height = model.nominal_base_height_m
    model.update(model.neutral_q(height), np.zeros(model.nv))
    return model.hip_positions() - np.array([0.0, 0.0, height])


@pytest.fixture
def planner(selector: FootholdSelector, hips_base: np.ndarray, hyq: RobotModel) -> VfaPlanner:
    return VfaPlanner(selector, hips_base, hyq.description.foot_radius_m)


def snapshot(hips_base: np.ndarray, hip_height: float, *, stamp_s: float = 1.0, swing=(True, False, False, True),
             time_left_s: float = 0.2, step_count=(3, 2, 2, 3), base_xy=(0.0, 0.0), yaw: float = 0.0,
             nominal_shift_m=(0.0, 0.0), **overrides) -> GaitSnapshot:
    """A trotting HyQ heading ``yaw``, at ``base_xy`` at 1 s and moving at SPEED, LF and RH swinging:
    Raibert nominals (the hip moved over the time left plus half a stance), lift-off one step behind,
    feet on z = 0. Stamps and times left that advance together keep the nominals in place."""
    c, s = math.cos(yaw), math.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    velocity = rotation @ np.array([SPEED, 0.0, 0.0])
    hips = np.array([*base_xy, 0.0]) + velocity * (stamp_s - 1.0) + hips_base @ rotation.T
    hips[:, 2] = hip_height
    ahead = velocity * (time_left_s + 0.5 * TROT["duty_factor"] / TROT["step_frequency_hz"])
    nominal = hips + ahead
    nominal[:, 2] = 0.0
    nominal[:, :2] += np.asarray(nominal_shift_m)
    liftoff = nominal - velocity / TROT["step_frequency_hz"]
    liftoff[:, 2] = 0.02175  # foot centre on the ground
    fields = {
        "stamp_s": stamp_s, **TROT, "base_twist": np.array([SPEED, 0.0, 0.0, 0.0, 0.0, 0.0]),
        "swing": np.array(swing), "time_to_touchdown_s": np.where(swing, time_left_s, 0.0),
        "step_count": np.array(step_count), "liftoff_position": liftoff, "nominal_foothold": nominal,
        "hip_position": hips,
    }
    fields.update(overrides)
    return GaitSnapshot(**fields)


def course_map(*patches, center=(0.0, 0.0), yaw: float = 0.0, cells: int = 121) -> HeightMapGrid:
    course = Course("test", Region(-3, 3, -3, 3), DefaultGround(height_m=0.0, **RIGID), tuple(patches))
    return extract_heightmap(course, center, yaw, cells, cells, 0.02)


def gap_across_x(x: float, half_width_m: float = 0.06) -> GapPatch:
    return GapPatch(name="gap", region=Region(x - half_width_m, x + half_width_m, -3, 3), depth_m=0.3,
                    start_height_m=0.0, **RIGID)


def test_flat_ground_keeps_the_nominal_with_one_decision_per_swing(planner, hips_base, hip_height) -> None:
    planner.set_map(course_map(), 0.98)
    first = snapshot(hips_base, hip_height)
    decisions = planner.update(first)
    assert [d.leg for d in decisions] == [Leg.LF, Leg.RH]
    for d in decisions:
        assert d.status is VfaStatus.SELECTED and d.safe_candidate_found and d.score == 1.0
        assert d.trigger == "swing_start" and d.step_count == first.step_count[d.leg] and not d.adapted
        np.testing.assert_allclose(d.selected, first.nominal_foothold[d.leg], atol=1e-9)
        assert d.elapsed_s > 0.0
    # Later ticks of the same swings (same map, same nominal): no news, no new evaluation.
    for k in range(1, 5):
        assert planner.update(snapshot(hips_base, hip_height, stamp_s=1.0 + 0.004 * k, time_left_s=0.2 - 0.004 * k)) == []
    assert planner.counters.by_trigger == {"swing_start": 2, "new_map": 0, "nominal_moved": 0, "pair": 0}
    # Stance, then the next swing of LF (step 4): a new decision.
    planner.update(snapshot(hips_base, hip_height, stamp_s=1.3, swing=(False, False, False, False)))
    assert planner.decision(Leg.LF) is None
    nxt = planner.update(snapshot(hips_base, hip_height, stamp_s=1.31, swing=(True, False, False, False),
                                  step_count=(4, 2, 2, 3)))
    assert [(d.leg, d.step_count) for d in nxt] == [(Leg.LF, 4)]


def test_gap_under_the_nominal_moves_the_foothold_to_safe_ground(planner, hips_base, hip_height) -> None:
    gait = snapshot(hips_base, hip_height)
    lf_nominal = gait.nominal_foothold[Leg.LF]
    grid = course_map(gap_across_x(lf_nominal[0]))
    planner.set_map(grid, 1.0)
    lf = {d.leg: d for d in planner.update(gait)}[Leg.LF]
    assert lf.status is VfaStatus.SELECTED and lf.safe_candidate_found and lf.adapted
    assert lf.selected[2] == pytest.approx(0.0)  # on the ground, not in the gap (-0.3 m)
    assert abs(lf.selected[0] - lf_nominal[0]) >= 0.06 + 0.03  # beyond the gap edge and the margins
    assert lf.selected[1] == pytest.approx(lf_nominal[1], abs=0.02)


def test_robot_heading_comes_from_the_hips(planner, hips_base, hip_height) -> None:
    """Walking along +y (yaw pi/2) towards a gap across y: the foothold moves along y, off the gap."""
    gait = snapshot(hips_base, hip_height, yaw=math.pi / 2, base_xy=(1.0, -0.5))
    lf_nominal = gait.nominal_foothold[Leg.LF]
    gap = GapPatch(name="gap", region=Region(-3, 3, lf_nominal[1] - 0.06, lf_nominal[1] + 0.06), depth_m=0.3,
                   start_height_m=0.0, **RIGID)
    planner.set_map(course_map(gap, center=(1.0, -0.5), yaw=math.pi / 2), 1.0)
    lf = {d.leg: d for d in planner.update(gait)}[Leg.LF]
    assert lf.adapted and lf.selected[2] == pytest.approx(0.0)
    assert abs(lf.selected[1] - lf_nominal[1]) >= 0.09 and lf.selected[0] == pytest.approx(lf_nominal[0], abs=0.02)


def test_missing_or_stale_map_passes_the_nominal_through_flagged(planner, hips_base, hip_height) -> None:
    gait = snapshot(hips_base, hip_height)
    for d in planner.update(gait):
        assert d.status is VfaStatus.NO_MAP and not d.safe_candidate_found and d.score == 0.0
        np.testing.assert_array_equal(d.selected, gait.nominal_foothold[d.leg])
    # A map 1 s older than the gait state (max age 0.5 s): re-decided (new map), stale.
    planner.set_map(course_map(), 0.0)
    stale = planner.update(snapshot(hips_base, hip_height, stamp_s=1.004, time_left_s=0.196))
    assert planner.counters.by_trigger["new_map"] == 2 and planner.counters.by_status["stale_map"] == 2
    assert [d.status for d in stale] == [VfaStatus.STALE_MAP] * 2
    # A fresh map: evaluated.
    planner.set_map(course_map(), 1.0)
    fresh = planner.update(snapshot(hips_base, hip_height, stamp_s=1.008, time_left_s=0.192))
    assert [d.status for d in fresh] == [VfaStatus.SELECTED] * 2 and all(d.score == 1.0 for d in fresh)


def test_unknown_cells_are_never_selected(planner, hips_base, hip_height) -> None:
    gait = snapshot(hips_base, hip_height)
    heights = np.array(course_map().heights)
    lf = gait.nominal_foothold[Leg.LF]
    row, col = int(round(lf[0] / 0.02)) + 60, int(round(lf[1] / 0.02)) + 60
    heights[row - 4:row + 5, col - 4:col + 5] = np.nan  # 9 x 9 unknown cells around LF's nominal
    grid = HeightMapGrid(center_xy=(0.0, 0.0), yaw=0.0, resolution_m=0.02, heights=heights)
    planner.set_map(grid, 1.0)
    decision = {d.leg: d for d in planner.update(gait)}[Leg.LF]
    assert decision.safe_candidate_found and decision.adapted and np.isfinite(decision.selected).all()
    assert np.max(np.abs(decision.selected[:2] - lf[:2])) >= 5 * 0.02  # out of the block and its margin
    # Nothing known at all: no safe candidate, the nominal passes through flagged, nothing raises.
    planner.set_map(HeightMapGrid(center_xy=(0.0, 0.0), yaw=0.0, resolution_m=0.02,
                                  heights=np.full((121, 121), np.nan)), 1.002)
    blind = planner.update(snapshot(hips_base, hip_height, stamp_s=1.004, time_left_s=0.196))
    assert {d.status for d in blind} == {VfaStatus.NO_SAFE_CANDIDATE}
    assert not any(d.safe_candidate_found for d in blind) and all(d.score == 1.0 for d in blind)


def test_new_map_or_moved_nominal_re_decides_during_the_swing(planner, hips_base, hip_height) -> None:
    gait = snapshot(hips_base, hip_height, time_left_s=0.26)
    planner.set_map(course_map(), 1.0)
    planner.update(gait)
    # A newer, identical map: re-evaluated, nothing changed, nothing to report.
    planner.set_map(course_map(), 1.02)
    assert planner.update(snapshot(hips_base, hip_height, stamp_s=1.02, time_left_s=0.24)) == []
    assert planner.counters.by_trigger["new_map"] == 2
    # A map showing a gap under LF's nominal: re-decided and reported (adapted) for LF only.
    planner.set_map(course_map(gap_across_x(gait.nominal_foothold[Leg.LF, 0])), 1.04)
    news = planner.update(snapshot(hips_base, hip_height, stamp_s=1.04, time_left_s=0.22))
    assert [(d.leg, d.trigger, d.adapted) for d in news] == [(Leg.LF, "new_map", True)]
    # The nominal moves 3 cm sideways (> 2 cm threshold) on flat ground: re-decided, follows it.
    planner.set_map(course_map(), 1.044)
    planner.update(snapshot(hips_base, hip_height, stamp_s=1.044, time_left_s=0.216))
    moved = snapshot(hips_base, hip_height, stamp_s=1.048, time_left_s=0.212, nominal_shift_m=(0.0, 0.03))
    news = planner.update(moved)
    assert {d.trigger for d in news} == {"nominal_moved"}
    for d in news:
        np.testing.assert_allclose(d.selected, moved.nominal_foothold[d.leg], atol=1e-9)


def test_late_in_the_swing_a_re_decision_may_not_change_the_foothold_level(planner, hips_base, hip_height) -> None:
    """Past 35 % of the swing (0.267 s: less than 0.173 s left) the swing can no longer re-plan its rise
    to the apex: a new map that puts LF's nominal in a pit (10 cm deep, 0.2 m wide) would move the foothold
    down into it, which is not taken; a move on the same level (a gap, the foot steps beside it) is."""
    gait = snapshot(hips_base, hip_height, time_left_s=0.2)
    nominal = gait.nominal_foothold[Leg.LF]
    planner.set_map(course_map(), 1.0)
    first = {d.leg: d for d in planner.update(gait)}
    pit = GapPatch(name="pit", region=Region(-3, 3, -3, 3), depth_m=0.1, start_height_m=0.0, **RIGID)
    planner.set_map(course_map(pit), 1.04)  # everything 10 cm lower: the same foothold, 10 cm down
    assert planner.update(snapshot(hips_base, hip_height, stamp_s=1.04, time_left_s=0.16)) == []
    assert planner.counters.level_locked == 2  # LF and RH
    assert planner.decision(Leg.LF).selected[2] == first[Leg.LF].selected[2] == 0.0
    # No re-trigger on the next tick (the locked decision has seen this map).
    assert planner.update(snapshot(hips_base, hip_height, stamp_s=1.044, time_left_s=0.156)) == []
    assert planner.counters.level_locked == 2
    # Same level, late: a gap under LF's nominal moves the foothold beside it.
    planner.set_map(course_map(gap_across_x(nominal[0])), 1.08)
    news = planner.update(snapshot(hips_base, hip_height, stamp_s=1.08, time_left_s=0.12))
    assert [(d.leg, d.trigger, d.adapted) for d in news] == [(Leg.LF, "new_map", True)]
    assert news[0].selected[2] == 0.0
    # Early in the swing a change of level is taken (a fresh planner, a new swing).
    fresh = VfaPlanner(planner.selector, hips_base, planner.foot_radius_m)
    fresh.set_map(course_map(), 1.0)
    fresh.update(snapshot(hips_base, hip_height, time_left_s=0.26))
    fresh.set_map(course_map(pit), 1.02)
    news = fresh.update(snapshot(hips_base, hip_height, stamp_s=1.02, time_left_s=0.24))
    assert {d.leg for d in news} == {Leg.LF, Leg.RH} and all(d.selected[2] == pytest.approx(-0.1) for d in news)
    assert fresh.counters.level_locked == 0


def test_swings_with_too_little_time_left_are_not_decided(planner, hips_base, hip_height) -> None:
    planner.set_map(course_map(), 1.0)
    assert planner.update(snapshot(hips_base, hip_height, time_left_s=0.05)) == []
    assert planner.update(snapshot(hips_base, hip_height, stamp_s=1.004, time_left_s=0.046)) == []
    assert planner.counters.late_swings == 2  # LF and RH, each counted once per swing
    assert sum(planner.counters.by_status.values()) == 0


def test_malformed_gait_states_raise_precise_input_errors(hips_base, hip_height) -> None:
    good = snapshot(hips_base, hip_height)
    nominal = good.nominal_foothold.copy()
    nominal[Leg.RH, 1] = np.nan
    cases = [
        ({"nominal_foothold": nominal}, "gait_state_nan", r"nominal_foothold has NaN/inf at \['RH'\]"),
        ({"hip_position": good.hip_position[:3]}, "gait_state_size", r"hip_position must have shape \(4, 3\)"),
        ({"base_twist": [0.3, 0.0, math.inf, 0.0, 0.0, 0.0]}, "gait_state_nan", r"base_twist has NaN/inf at \[2\]"),
        ({"swing": np.array([True, False, False])}, "gait_state_size", r"swing must have 4 values"),
        ({"stamp_s": math.nan}, "gait_state_nan", r"stamp_s must be a finite number"),
        ({"duty_factor": 1.0}, "gait_state_invalid", r"duty_factor in \(0, 1\) \(got 1.0\)"),
        ({"time_to_touchdown_s": np.array([-0.1, 0.0, 0.0, 0.2])}, "gait_state_invalid",
         r"time_to_touchdown_s < 0 for swinging leg\(s\) LF"),
        ({"step_count": np.array([1, 2, -1, 3])}, "gait_state_invalid", r"step_count must be integers >= 0"),
        ({"hip_velocity": np.where(np.arange(4)[:, None] == 2, np.nan, 0.0) * np.ones((4, 3))}, "gait_state_nan",
         r"hip_velocity has NaN/inf at \['LH'\]"),
    ]
    for change, reason, message in cases:
        fields = {f.name: getattr(good, f.name) for f in dataclasses.fields(GaitSnapshot)}
        fields.update(change)
        with pytest.raises(InputError, match=message) as info:
            GaitSnapshot(**fields)
        assert info.value.reason == reason


def test_out_of_order_stamps_are_rejected_and_a_restarted_clock_restarts(planner, hips_base, hip_height) -> None:
    grid = course_map()
    planner.set_map(grid, 1.0)
    with pytest.raises(VfaInputError, match=r"heightmap stamp 0.950000 s is before the previous map's 1.000000 s") as info:
        planner.set_map(grid, 0.95)
    assert info.value.reason == "heightmap_out_of_order" and planner.map_stamp_s == 1.0
    assert planner.set_map(course_map(gap_across_x(0.5)), 1.0) is False  # a repeated map: the first one stays
    assert not np.isnan(planner._grid.heights).any() and planner._grid.heights.min() == 0.0
    planner.update(snapshot(hips_base, hip_height, stamp_s=1.0))
    with pytest.raises(VfaInputError, match=r"gait state stamp 0.996000 s is not after") as info:
        planner.update(snapshot(hips_base, hip_height, stamp_s=0.996))
    assert info.value.reason == "gait_state_out_of_order"
    inf_heights = np.array(grid.heights)
    inf_heights[0, 0] = np.inf
    with pytest.raises(VfaInputError, match=r"1 infinite height\(s\)"):
        planner.set_map(HeightMapGrid(center_xy=(0.0, 0.0), yaw=0.0, resolution_m=0.02, heights=inf_heights), 2.0)
    # The simulation restarted (stamps 1 s back): the planner starts afresh instead of rejecting forever.
    planner.set_map(grid, 0.0)
    assert planner.counters.restarts == 1 and planner.decision(Leg.LF) is None
    assert len(planner.update(snapshot(hips_base, hip_height, stamp_s=0.004))) == 2


def test_selector_and_settings_are_validated(hyq: RobotModel) -> None:
    with pytest.raises(FecConfigError, match=r"selector must be one of \['exact', 'cnn', 'cnn_unverified'\], "
                                                r"got 'learned'"):
        make_selector("learned", hyq, max_map_age_s=0.5)
    with pytest.raises(FecConfigError, match=r"PlannerSettings.max_map_age_s must be > 0, got 0.0"):
        PlannerSettings(max_map_age_s=0.0)
    with pytest.raises(FecConfigError, match=r"PlannerSettings.nominal_shift_threshold_m must be a finite number"):
        PlannerSettings(nominal_shift_threshold_m=math.nan)
    with pytest.raises(FecConfigError, match="level_lock_swing_fraction"):
        PlannerSettings(level_lock_swing_fraction=1.5)
    with pytest.raises(FecConfigError, match="level_lock_dz_m"):
        PlannerSettings(level_lock_dz_m=-0.01)
    planner = VfaPlanner.for_robot(hyq, "exact", PlannerSettings(max_map_age_s=0.2))
    assert isinstance(planner.selector, FootholdSelector) and planner.selector.max_map_age_s == 0.2


def test_the_cnn_selector_moves_the_foothold_off_a_gap_too(hyq: RobotModel, hips_base, hip_height) -> None:
    """The planner with the committed CNN (verified by the exact criteria) on the gap of the exact test."""
    planner = VfaPlanner.for_robot(hyq, "cnn", PlannerSettings())
    gait = snapshot(hips_base, hip_height)
    lf_nominal = gait.nominal_foothold[Leg.LF]
    planner.set_map(course_map(gap_across_x(lf_nominal[0])), 1.0)
    lf = {d.leg: d for d in planner.update(gait)}[Leg.LF]
    assert lf.status is VfaStatus.SELECTED and lf.safe_candidate_found and lf.adapted
    assert lf.selected[2] == pytest.approx(0.0)
    assert abs(lf.selected[0] - lf_nominal[0]) >= 0.06 + 0.03
    # "cnn_unverified": the same network without the exact check of its choice (the thesis' g_hat)
    alone = VfaPlanner.for_robot(hyq, "cnn_unverified", PlannerSettings())
    assert planner.selector.verify and not alone.selector.verify
    alone.set_map(course_map(gap_across_x(lf_nominal[0])), 1.0)
    lf_alone = {d.leg: d for d in alone.update(gait)}[Leg.LF]
    assert lf_alone.adapted and abs(lf_alone.selected[0] - lf_nominal[0]) >= 0.06 + 0.03
    assert alone.selector.counters.verified == 0 < planner.selector.counters.verified


@pytest.mark.parametrize("hysteresis_m, kept", [(0.05, True), (0.0, False)])
def test_a_still_safe_selection_is_kept_when_the_other_side_is_only_slightly_closer(
        selector, hips_base, hyq: RobotModel, hip_height, hysteresis_m: float, kept: bool) -> None:
    """A gap along x centred under LF's nominal (8 cm wide): the first decision takes one side; the nominal
    then moves 2.1 cm towards the other side, which becomes about 2 cm closer. Within the hysteresis the
    swing keeps its target; without it the foot is retargeted across the gap (a jump of ~0.2 m)."""
    planner = VfaPlanner(selector, hips_base, hyq.description.foot_radius_m,
                         PlannerSettings(switch_hysteresis_m=hysteresis_m))
    gait = snapshot(hips_base, hip_height)
    nominal = gait.nominal_foothold[Leg.LF]
    strip = GapPatch(name="gap", region=Region(-3, 3, nominal[1] - 0.04, nominal[1] + 0.04), depth_m=0.3,
                     start_height_m=0.0, **RIGID)
    planner.set_map(course_map(strip), 1.0)
    first = {d.leg: d for d in planner.update(gait)}[Leg.LF]
    side = math.copysign(1.0, first.selected[1] - nominal[1])
    moved = snapshot(hips_base, hip_height, stamp_s=1.004, time_left_s=0.196, nominal_shift_m=(0.0, -side * 0.021))
    news = {d.leg: d for d in planner.update(moved)}
    current = planner.decision(Leg.LF)
    assert current is not None and current.status is VfaStatus.SELECTED
    if kept:
        assert Leg.LF not in news and planner.counters.kept == 1
        np.testing.assert_allclose(current.selected, first.selected, atol=1e-9)
    else:
        assert Leg.LF in news and planner.counters.kept == 0
        assert math.copysign(1.0, current.selected[1] - nominal[1]) == -side  # across the gap


def _pair_planner(selector: FootholdSelector, hips_base: np.ndarray, hyq: RobotModel, cap_m: float) -> VfaPlanner:
    return VfaPlanner(selector, hips_base, hyq.description.foot_radius_m, PlannerSettings(pair_compensation_m=cap_m))


def test_diagonal_partner_is_shifted_against_the_other_legs_adaptation(selector, hips_base, hip_height, hyq) -> None:
    """LF moved off a gap by d: its diagonal partner RH (flat ground) is re-decided around its nominal - d,
    keeps the gait's nominal in ``nominal`` and the trigger "pair"; without the setting RH stays nominal."""
    gait = snapshot(hips_base, hip_height)
    grid = course_map(gap_across_x(gait.nominal_foothold[Leg.LF][0]))
    plain = VfaPlanner(selector, hips_base, hyq.description.foot_radius_m)
    plain.set_map(grid, 1.0)
    plain_rh = {d.leg: d for d in plain.update(gait)}[Leg.RH]
    assert not plain_rh.adapted
    planner = _pair_planner(selector, hips_base, hyq, cap_m=0.3)
    planner.set_map(grid, 1.0)
    decisions = {d.leg: d for d in planner.update(gait)}
    lf, rh = decisions[Leg.LF], decisions[Leg.RH]
    shift = lf.selected[:2] - lf.nominal[:2]
    assert np.linalg.norm(shift) >= 0.09  # LF left the gap
    assert rh.trigger == "pair" and rh.status is VfaStatus.SELECTED
    np.testing.assert_allclose(rh.nominal, gait.nominal_foothold[Leg.RH])
    np.testing.assert_allclose(rh.selected[:2], rh.nominal[:2] - shift, atol=0.011)  # within half a cell
    assert planner.counters.by_trigger["pair"] == 1
    # The same gait state again: nothing new (the compensation is already in place).
    assert planner.update(dataclasses.replace(gait, stamp_s=1.004, time_to_touchdown_s=gait.time_to_touchdown_s
                                              - 0.004 * gait.swing)) == []


def test_diagonal_compensation_is_capped_and_undone_when_the_adaptation_goes(selector, hips_base, hip_height,
                                                                              hyq) -> None:
    gait = snapshot(hips_base, hip_height)
    planner = _pair_planner(selector, hips_base, hyq, cap_m=0.05)
    planner.set_map(course_map(gap_across_x(gait.nominal_foothold[Leg.LF][0])), 1.0)
    rh = {d.leg: d for d in planner.update(gait)}[Leg.RH]
    assert np.linalg.norm(rh.selected[:2] - rh.nominal[:2]) == pytest.approx(0.05, abs=0.011)
    # A new map without the gap: LF goes back to its nominal, and so does RH.
    later = snapshot(hips_base, hip_height, stamp_s=1.02, time_left_s=0.18)
    planner.set_map(course_map(), 1.02)
    decisions = {d.leg: d for d in planner.update(later)}
    assert not decisions[Leg.LF].adapted
    np.testing.assert_allclose(planner.decision(Leg.RH).selected[:2], later.nominal_foothold[Leg.RH][:2], atol=1e-9)


def test_pair_compensation_settings_are_validated() -> None:
    with pytest.raises(FecConfigError, match="pair_compensation_m"):
        PlannerSettings(pair_compensation_m=-0.1)
    with pytest.raises(FecConfigError, match="pair_min_adaptation_m"):
        PlannerSettings(pair_min_adaptation_m=float("nan"))


def test_a_descending_hip_is_evaluated_at_its_height_at_touchdown(selector, hips_base, hip_height, hyq) -> None:
    """LF's nominal 0.1 m past a tread edge going down 0.1 m. At touchdown a hip sinking at 0.3 m/s is
    0.06 m lower (0.2 s left): its knee sits further back over the edge, so the planner moves the foothold
    further from the edge than at the current hip height, exactly as for a hip already 0.06 m lower. A
    rising hip keeps its current height, as does every hip with the prediction off (the default)."""
    level = snapshot(hips_base, hip_height)
    edge_x = float(level.nominal_foothold[Leg.LF, 0]) - 0.1
    grid = course_map(StairsPatch(name="down", region=Region(edge_x, edge_x + 2.0, -3, 3), rise_m=0.1, go_m=0.25,
                                  count=3, direction="down", start_height_m=0.0, **RIGID))

    def lf(gait: GaitSnapshot, predict: bool = True) -> np.ndarray:
        planner = VfaPlanner(selector, hips_base, hyq.description.foot_radius_m,
                             PlannerSettings(predict_hip_descent=predict))
        planner.set_map(grid, 1.0)
        decision = {d.leg: d for d in planner.update(gait)}[Leg.LF]
        assert decision.status is VfaStatus.SELECTED
        return decision.selected

    sinking = np.zeros((4, 3))
    sinking[:, 2] = -0.3
    descending = dataclasses.replace(level, hip_velocity=sinking)
    np.testing.assert_allclose(lf(descending), lf(snapshot(hips_base, hip_height - 0.06), predict=False))
    assert lf(descending)[0] > lf(level)[0] + 0.04
    np.testing.assert_allclose(lf(descending, predict=False), lf(level))
    assert not PlannerSettings().predict_hip_descent
    np.testing.assert_allclose(lf(dataclasses.replace(level, hip_velocity=-sinking)), lf(level))
    assert np.all(level.hip_velocity == 0.0)  # a gait state without hip velocities: zeros


class _OneLegAtATime:
    """A selector seen through ``select`` alone (no ``select_legs``): the planner's one-leg-per-call path."""

    def __init__(self, selector) -> None:
        self.select = selector.select


class _BatchSpy:
    """A selector whose ``select_legs`` calls are recorded (number of legs per call)."""

    def __init__(self, selector) -> None:
        self.select = selector.select
        self.batches: list[int] = []
        self._select_legs = selector.select_legs

    def select_legs(self, requests, grid, **kwargs):
        self.batches.append(len(requests))
        return self._select_legs(requests, grid, **kwargs)


def _trot_ticks(hips_base: np.ndarray, hip_height: float, ticks: int, yaw: float) -> list[GaitSnapshot]:
    """``ticks`` gait states 4 ms apart of the trot of ``snapshot`` heading ``yaw``: LF + RH swing, then RF +
    LH (each pair 0.267 s of a 0.667 s cycle), the nominals swaying +-5 cm sideways at 3 Hz (re-decisions on
    "nominal_moved")."""
    period, swing_s = 1.0 / TROT["step_frequency_hz"], (1.0 - TROT["duty_factor"]) / TROT["step_frequency_hz"]
    states = []
    for k in range(ticks):
        t = 1.0 + 0.004 * k
        phase = (t - 1.0) % period
        first_pair = phase < 0.5 * period
        in_swing = phase if first_pair else phase - 0.5 * period
        swinging = in_swing < swing_s
        swing = (swinging and first_pair, swinging and not first_pair, swinging and not first_pair,
                 swinging and first_pair)
        cycle = int((t - 1.0) // period)
        counts = (3 + cycle, 2 + cycle, 2 + cycle, 3 + cycle)
        sway = 0.05 * math.sin(2.0 * math.pi * 3.0 * (t - 1.0))
        c, s = math.cos(yaw), math.sin(yaw)
        states.append(snapshot(hips_base, hip_height, stamp_s=t, swing=swing, step_count=counts, yaw=yaw,
                               time_left_s=max(swing_s - in_swing, 0.0), nominal_shift_m=(-s * sway, c * sway)))
    return states


@pytest.mark.parametrize("pair_compensation_m", [0.0, 0.05])
def test_batched_cnn_decisions_equal_one_leg_at_a_time(hyq: RobotModel, hips_base, hip_height,
                                                      pair_compensation_m: float) -> None:
    """The planner with the CNN selector decides the legs of one tick in one ``select_legs`` call; on a trot
    over stairs and gaps, with maps (aligned with the heading and not) arriving every 40 ms, the decisions
    and counters equal those of the same planner calling ``select`` one leg at a time."""
    from tal_perception.vfa_cnn import CnnFootholdSelector

    cnn = CnnFootholdSelector(FootholdEvaluator(hyq), verify=True)
    settings = PlannerSettings(pair_compensation_m=pair_compensation_m)
    spy = _BatchSpy(cnn)
    planners = [VfaPlanner(selector, hips_base, hyq.description.foot_radius_m, settings)
                for selector in (spy, _OneLegAtATime(cnn))]
    yaw = 0.3
    stairs = StairsPatch(name="stairs", region=Region(0.42, 3, -3, 3), rise_m=0.08, go_m=0.21, count=3,
                         direction="up", start_height_m=0.0, **RIGID)
    courses = [(stairs, gap_across_x(-0.25, 0.05)), (stairs, gap_across_x(-0.17, 0.04), gap_across_x(0.66, 0.03))]
    outputs: list[list[list[tuple]]] = [[], []]
    for k, gait in enumerate(_trot_ticks(hips_base, hip_height, 170, yaw)):
        if k % 10 == 0:  # a new map every 40 ms, alternating terrain and map heading (aligned / interpolated)
            grid = course_map(*courses[(k // 10) % 2], center=tuple(gait.hip_position.mean(axis=0)[:2]),
                              yaw=yaw if (k // 20) % 2 == 0 else 0.0)
        for planner, out in zip(planners, outputs):
            if k % 10 == 0:
                planner.set_map(grid, gait.stamp_s - 0.01)
            out.append([(d.leg, d.step_count, d.trigger, d.status, d.safe_candidate_found, d.safe_candidates,
                         d.score, d.map_stamp_s, tuple(d.nominal), tuple(d.selected)) for d in planner.update(gait)])
    batched, single = outputs
    assert batched == single
    assert dataclasses.asdict(planners[0].counters) == dataclasses.asdict(planners[1].counters)
    counters = planners[0].counters
    assert counters.adapted > 0 and counters.by_trigger["new_map"] > 0 and counters.by_trigger["nominal_moved"] > 0
    assert counters.kept > 0 and counters.level_locked > 0  # the hysteresis and the level lock were exercised
    assert sum(len(news) for news in batched) > 20
    assert spy.batches.count(2) > 10  # the swinging pair decided together
