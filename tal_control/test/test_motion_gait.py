"""Gait parameters and scheduler: phase offsets, duty factor, swing sets, load ramps, gait switches."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from tal_control.errors import MotionConfigError
from tal_control.motion.gait import CRAWL, STAND, TROT, GaitParameters, GaitScheduler
from tal_core.errors import InputError
from tal_core.legs import Leg

DT = 0.004  # [s] 250 Hz control tick


def run(scheduler: GaitScheduler, t_end: float, t_start: float = 0.0, switch: dict | None = None):
    """Phases at every tick in [t_start, t_end); ``switch`` maps a tick time to a gait to request."""
    phases = []
    for k in range(int(round((t_end - t_start) / DT))):
        t = t_start + k * DT
        if switch:
            for t_switch, gait in list(switch.items()):
                if t >= t_switch:
                    scheduler.set_gait(gait)
                    del switch[t_switch]
        phases.append(scheduler.update(t))
    return phases


def liftoff_times(phases, leg: Leg) -> list[float]:
    return [p.t_s for p in phases if p.liftoff_event[leg]]


def test_presets_match_the_design():
    assert CRAWL.phase_offsets == (0.25, 0.75, 0.0, 0.5)  # LF, RF, LH, RH: LH, LF, RH, RF sequence
    assert CRAWL.duty_factor == 0.8 and CRAWL.step_frequency_hz == 0.5
    assert CRAWL.max_simultaneous_swings == 1 and CRAWL.is_statically_stable
    assert TROT.phase_offsets[Leg.LF] == TROT.phase_offsets[Leg.RH] == 0.0
    assert TROT.phase_offsets[Leg.RF] == TROT.phase_offsets[Leg.LH] == 0.5
    assert 1.4 <= TROT.step_frequency_hz <= 1.7 and 0.55 <= TROT.duty_factor <= 0.65
    assert TROT.max_simultaneous_swings == 2 and not TROT.is_statically_stable
    assert STAND.is_standing and STAND.swing_duration_s == 0.0
    assert CRAWL.swing_duration_s == pytest.approx(0.4) and CRAWL.stance_duration_s == pytest.approx(1.6)


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"name": "gallop"}, "gait name 'gallop'"),
        ({"step_frequency_hz": 0.0}, "step_frequency_hz must be > 0"),
        ({"step_frequency_hz": math.nan}, "step_frequency_hz must be finite"),
        ({"duty_factor": 1.0}, "duty_factor must be 1 exactly for 'stand'"),
        ({"duty_factor": -0.2}, r"duty_factor must be in \(0, 1\]"),
        ({"step_height_m": 0.0}, "step_height_m must be > 0"),
        ({"loading_time_s": 0.9}, "loading_time_s must be in"),
        ({"phase_offsets": (0.0, 0.5, 1.0, 0.5)}, "phase_offsets must be 4 values in"),
        ({"phase_offsets": (0.0, 0.5)}, "phase_offsets must be 4 values in"),
    ],
)
def test_invalid_parameters_are_rejected_with_the_field_name(changes, match):
    with pytest.raises(MotionConfigError, match=match):
        dataclasses.replace(CRAWL, **changes)


def test_stand_requires_duty_one():
    with pytest.raises(MotionConfigError, match="duty_factor must be 1"):
        dataclasses.replace(STAND, duty_factor=0.9)


@pytest.mark.parametrize("gait", [CRAWL, TROT])
def test_duty_factor_and_phase_offsets(gait: GaitParameters):
    period = gait.cycle_duration_s
    phases = run(GaitScheduler(gait), 6 * period)
    steady = [p for p in phases if p.t_s >= period]  # after the preparation cycle
    swing = np.array([p.swing for p in steady])
    np.testing.assert_allclose(1.0 - swing.mean(axis=0), gait.duty_factor, atol=0.01)
    # lift-offs happen at the leg's phase offset of every cycle, counted from the gait start
    for leg in Leg:
        times = np.array(liftoff_times(phases, leg))
        expected = (np.arange(1, 6) + gait.phase_offsets[leg]) * period
        np.testing.assert_allclose(times, expected, atol=DT + 1e-9)
        durations = [p.swing_duration_s[leg] for p in steady if p.swing[leg]]
        np.testing.assert_allclose(durations, gait.swing_duration_s)
    for p in steady:
        assert np.all((0.0 <= p.phase) & (p.phase < 1.0))
        expected_swing = p.phase < 1.0 - gait.duty_factor
        np.testing.assert_array_equal(p.swing, expected_swing)


def test_crawl_sequence_and_single_swing():
    phases = run(GaitScheduler(CRAWL), 10.0)
    assert max(p.swing.sum() for p in phases) == 1
    first = {leg: liftoff_times(phases, leg)[0] for leg in Leg}
    assert sorted(first, key=first.get) == [Leg.LH, Leg.LF, Leg.RH, Leg.RF]
    np.testing.assert_allclose(np.diff(sorted(first.values())), CRAWL.cycle_duration_s / 4, atol=1e-9)
    np.testing.assert_array_equal(phases[-1].step_count, [4, 4, 4, 4])


def test_trot_diagonal_pairs_swing_together():
    phases = run(GaitScheduler(TROT), 5.0)
    swing = np.array([p.swing for p in phases])
    np.testing.assert_array_equal(swing[:, Leg.LF], swing[:, Leg.RH])
    np.testing.assert_array_equal(swing[:, Leg.RF], swing[:, Leg.LH])
    assert swing.sum(axis=1).max() == 2
    assert not np.any(swing[:, Leg.LF] & swing[:, Leg.RF])  # the pairs alternate
    lf, rf = liftoff_times(phases, Leg.LF), liftoff_times(phases, Leg.RF)
    np.testing.assert_allclose(np.array(rf[: len(lf)]) - np.array(lf[: len(rf)]),
                               TROT.cycle_duration_s / 2, atol=DT + 1e-9)


def test_swing_progress_and_timers():
    phases = run(GaitScheduler(CRAWL), 6.0)
    for p in phases:
        for leg in Leg:
            if p.swing[leg]:
                assert 0.0 <= p.swing_progress[leg] <= 1.0
                assert p.time_to_touchdown_s[leg] == pytest.approx(
                    (1.0 - p.swing_progress[leg]) * CRAWL.swing_duration_s)
                assert p.time_to_liftoff_s[leg] == 0.0 and p.load_factor[leg] == 0.0
            else:
                assert p.swing_progress[leg] == 0.0 and p.time_to_touchdown_s[leg] == 0.0
                assert p.time_to_liftoff_s[leg] > 0.0
    # the timers agree with the events that follow
    p = phases[600]  # t = 2.4 s
    for leg in Leg:
        if p.stance[leg]:
            next_liftoff = [q.t_s for q in phases if q.t_s > p.t_s and q.liftoff_event[leg]][0]
            assert next_liftoff == pytest.approx(p.t_s + p.time_to_liftoff_s[leg], abs=DT)


def test_load_factor_ramps():
    gait = CRAWL
    phases = run(GaitScheduler(gait), 8.0)
    load = np.array([p.load_factor for p in phases])
    assert np.all((0.0 <= load) & (load <= 1.0))
    # continuous: at most one ramp step per tick
    assert np.max(np.abs(np.diff(load, axis=0))) <= DT / gait.loading_time_s + 1e-9
    for p in phases:
        for leg in Leg:
            if p.swing[leg]:
                assert p.load_factor[leg] == 0.0
                continue
            since = p.t_s - p.touchdown_time_s[leg]
            expected = min(1.0, since / gait.loading_time_s, p.time_to_liftoff_s[leg] / gait.loading_time_s)
            assert p.load_factor[leg] == pytest.approx(expected)
    # 1 in mid-stance, ramps at the ends: LH touches down at 2.4 s and lifts again at 4.0 s
    by_time = {round(p.t_s, 3): p for p in phases}
    assert by_time[2.452].load_factor[Leg.LH] == pytest.approx(0.52, abs=1e-6)
    assert by_time[3.2].load_factor[Leg.LH] == 1.0
    assert by_time[3.96].load_factor[Leg.LH] == pytest.approx(0.4, abs=1e-6)


def test_stand_is_fully_loaded_and_never_swings():
    phases = run(GaitScheduler(STAND), 3.0)
    for p in phases:
        np.testing.assert_array_equal(p.load_factor, 1.0)
        assert not p.swing.any() and np.all(np.isinf(p.time_to_liftoff_s))
    np.testing.assert_array_equal(phases[-1].step_count, 0)


def test_time_must_increase():
    scheduler = GaitScheduler(TROT)
    scheduler.update(1.0)
    with pytest.raises(InputError, match="not after the previous"):
        scheduler.update(1.0)
    with pytest.raises(InputError, match="must be finite"):
        scheduler.update(math.nan)


def test_stand_to_trot_starts_cleanly_at_a_cycle_boundary():
    scheduler = GaitScheduler(STAND)
    phases = run(scheduler, 6.0, switch={1.3: TROT})
    switch = [p for p in phases if p.gait.name == "trot"][0]
    assert switch.t_s == pytest.approx(2.0, abs=DT)  # next stand-clock boundary (1 Hz)
    assert switch.gait_start_time_s == pytest.approx(2.0)
    first = min(liftoff_times(phases, leg)[0] for leg in Leg)
    # one preparation cycle, then LF + RH lift off together at the trot's phase 0
    assert first == pytest.approx(2.0 + TROT.cycle_duration_s, abs=DT)
    assert liftoff_times(phases, Leg.LF)[0] == liftoff_times(phases, Leg.RH)[0] == first
    load = np.array([p.load_factor for p in phases])
    assert np.max(np.abs(np.diff(load, axis=0))) <= DT / TROT.loading_time_s + 1e-9
    assert np.all(load[[p.t_s < first - TROT.loading_time_s for p in phases]] == 1.0)


def test_switches_never_cut_or_start_a_swing_half_way():
    scheduler = GaitScheduler(CRAWL)
    phases = run(scheduler, 14.0, switch={4.7: TROT, 7.3: CRAWL, 10.1: STAND})
    for leg in Leg:
        lifts = [p.t_s for p in phases if p.liftoff_event[leg]]
        downs = [p.t_s for p in phases if p.touchdown_event[leg]]
        assert len(lifts) == len(downs)
        for t_lo, t_td in zip(lifts, downs, strict=True):
            gait = next(p.gait for p in phases if p.t_s == t_lo)
            assert t_td - t_lo == pytest.approx(gait.swing_duration_s, abs=DT + 1e-9)
        for p in phases:
            if p.liftoff_event[leg]:  # a leg lifts off at its phase 0 of the running gait
                assert min(p.phase[leg], 1.0 - p.phase[leg]) < DT * p.gait.step_frequency_hz + 1e-9
    names = [p.gait.name for p in phases]
    assert names[0] == "crawl" and names[-1] == "stand" and "trot" in names
    assert not phases[-1].swing.any() and np.all(phases[-1].load_factor == 1.0)
    load = np.array([p.load_factor for p in phases])
    assert np.max(np.abs(np.diff(load, axis=0))) <= DT / TROT.loading_time_s + 1e-9


def test_requesting_the_running_gait_cancels_a_pending_switch():
    scheduler = GaitScheduler(TROT)
    run(scheduler, 1.0)
    scheduler.set_gait(CRAWL)
    assert scheduler.pending_gait is CRAWL
    scheduler.set_gait(TROT)
    assert scheduler.pending_gait is None
    phases = run(scheduler, 3.0, t_start=1.0)
    assert all(p.gait.name == "trot" for p in phases)


@pytest.mark.parametrize("gait", [TROT, CRAWL])
def test_a_new_step_height_applies_from_the_next_liftoff_without_touching_the_schedule(gait: GaitParameters):
    reference = run(GaitScheduler(gait), 6.0)
    scheduler = GaitScheduler(gait)
    phases = run(scheduler, 2.05)
    scheduler.set_step_height(0.2)
    assert scheduler.pending_gait is None and scheduler.gait.step_height_m == 0.2
    phases += run(scheduler, 6.0, t_start=2.05 + DT / 2)
    assert [p.t_s for p in phases if p.liftoff_event.any()] == pytest.approx(
        [p.t_s for p in reference if p.liftoff_event.any()])   # no switch, no preparation cycle
    assert {p.gait.step_height_m for p in phases if p.t_s > 2.05} == {0.2}
    with pytest.raises(MotionConfigError, match="step_height_m"):
        scheduler.set_step_height(0.0)
    assert scheduler.gait.step_height_m == 0.2


def test_a_step_height_before_the_first_update_and_with_a_pending_switch():
    scheduler = GaitScheduler(STAND)
    scheduler.set_step_height(0.05)
    run(scheduler, 1.0)
    assert scheduler.gait.step_height_m == 0.05
    scheduler.set_gait(TROT)
    scheduler.set_step_height(0.15)
    assert scheduler.gait.step_height_m == 0.15 and scheduler.pending_gait.step_height_m == 0.15
