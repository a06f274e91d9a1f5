"""The wbc's tick policy without ROS: when a tick is due, which inputs it uses, restarts, safe mode, the
watchdog and the wait for a command source."""

from __future__ import annotations

import numpy as np
import pytest

from tal_control.tick_policy import CLOCK_RESET_NS, Mode, TickPolicyConfig, WbcTickPolicy
from tal_control.velocity_command import VelocityCommandInput
from tal_core.errors import InputError

MS = 1_000_000
PERIOD = 4 * MS


class FakeClock:
    """Steady time [s] the test sets."""

    def __init__(self, now_s: float = 100.0) -> None:
        self.now_s = now_s

    def __call__(self) -> float:
        return self.now_s


def policy(**config) -> WbcTickPolicy:
    clock = config.pop("clock", FakeClock())
    found = config.pop("found", lambda: True)
    return WbcTickPolicy(TickPolicyConfig(period_ns=PERIOD, **config), VelocityCommandInput(1.0, 1.0),
                         clock=clock, command_source_found=found)


def step(p: WbcTickPolicy, stamp_ns: int, base_ns: int | None = None):
    """Base state (stamped ``base_ns``, default the same stamp) then joint state at ``stamp_ns``; returns the
    joint state's arrival."""
    p.base_state(stamp_ns if base_ns is None else base_ns, f"base@{stamp_ns if base_ns is None else base_ns}")
    return p.joint_state(stamp_ns, f"joints@{stamp_ns}")


# -- the grid -------------------------------------------------------------------------------------------------
def test_ticks_fall_on_the_grid_and_use_the_samples_of_their_stamp() -> None:
    p = policy()
    first = step(p, 0)
    assert first.tick is not None and first.tick.stamp_ns == 0 and first.feed_watchdog
    assert (first.tick.joints, first.tick.base, first.tick.base_age_ns) == ("joints@0", "base@0", 0)
    assert first.tick.safe_reason is None and p.next_tick_ns == PERIOD
    between = [step(p, k * MS) for k in (1, 2, 3)]  # 1 kHz samples between control ticks
    assert all(a.tick is None and a.feed_watchdog for a in between)
    # A stamp just short of the tick (rounding of the physics step) still is the tick.
    almost = step(p, PERIOD - 50_000)
    assert almost.tick is not None and almost.tick.stamp_ns == PERIOD - 50_000
    assert p.next_tick_ns == 2 * PERIOD


def test_repeated_and_out_of_order_joint_states_are_dropped() -> None:
    p = policy()
    step(p, 0)
    step(p, 8 * MS)
    assert p.joint_state(4 * MS, "older").tick is None
    again = p.joint_state(8 * MS, "same")
    assert again.tick is None and not again.feed_watchdog and not again.restarted


# -- which base state ----------------------------------------------------------------------------------------
def test_ground_truth_tick_waits_for_the_base_state_of_its_stamp_whatever_the_arrival_order() -> None:
    p = policy()
    step(p, 0)
    p.base_state(3 * MS, "base@3")
    waiting = p.joint_state(4 * MS, "joints@4")
    assert waiting.tick is None and p.counters.deferred_ticks == 1
    done = p.base_state(4 * MS, "base@4")
    assert done.tick is not None and done.tick.stamp_ns == 4 * MS and done.tick.base == "base@4"
    assert done.feed_watchdog  # a tick computed on a base state's arrival feeds the watchdog too
    # The other order: base state first, then the joint state.
    p.base_state(8 * MS, "base@8")
    assert p.joint_state(8 * MS, "joints@8").tick.base == "base@8"


def test_on_the_estimate_a_tick_waits_for_the_estimators_latest_tick_at_or_before_it() -> None:
    p = policy(base_period_ns=3 * MS)
    assert p.expected_base_stamp(4 * MS) == 3 * MS and p.expected_base_stamp(6 * MS) == 6 * MS
    assert p.expected_base_stamp(6 * MS - 50_000) == 6 * MS  # within the tick tolerance
    tick = step(p, 0).tick
    assert tick is not None
    tick = step(p, 4 * MS, base_ns=3 * MS).tick   # the 3 ms estimate is the one for the 4 ms tick
    assert tick is not None and tick.base_age_ns == MS
    assert step(p, 8 * MS, base_ns=3 * MS).tick is None  # the 6 ms estimate is on its way
    tick = p.base_state(6 * MS, "base@6").tick
    assert tick is not None and tick.stamp_ns == 8 * MS and tick.base == "base@6"


def test_a_deferred_tick_is_decided_by_the_next_joint_state_with_the_base_state_there() -> None:
    p = policy()
    step(p, 0)
    assert p.joint_state(4 * MS, "joints@4").tick is None      # no base state of 4 ms (yet)
    tick = p.joint_state(8 * MS, "joints@8").tick              # the driver moved on: decide now
    assert tick is not None and tick.stamp_ns == 8 * MS and tick.base == "base@0" and tick.safe_reason is None
    assert p.counters.deferred_ticks == 1 and p.next_tick_ns == 12 * MS


def test_on_the_wall_clock_a_deferred_tick_waits_max_defer_for_its_base_state() -> None:
    """Real time: the next joint samples come 1 ms apart, before the estimator's answer; with max_defer_ns
    the deferred tick keeps its own sample and waits for its base state instead of running on the old one."""
    p = policy(max_defer_ns=3 * MS)
    step(p, 0)
    assert p.joint_state(4 * MS, "joints@4").tick is None       # deferred
    assert not p.wants_joint_state(5 * MS)                      # within max_defer: not even deserialised
    assert p.joint_state(5 * MS, "joints@5").tick is None       # and ignored if handed over
    assert p.joint_state(7 * MS, "joints@7").tick is None
    tick = p.base_state(4 * MS, "base@4").tick                  # the answer comes: the tick of 4 ms runs
    assert tick is not None and tick.base == "base@4" and tick.joints == "joints@4" and tick.safe_reason is None
    assert p.counters.deferred_ticks == 1
    q = policy(max_defer_ns=3 * MS)
    step(q, 0)
    q.joint_state(4 * MS, "joints@4")
    late = q.joint_state(8 * MS, "joints@8").tick               # past max_defer: run on the base state there is
    assert late is not None and late.base == "base@0"


def test_older_base_states_are_dropped_and_newer_ones_replace_the_held_one() -> None:
    p = policy()
    p.base_state(8 * MS, "base@8")
    assert p.base_state(4 * MS, "base@4").tick is None
    tick = p.joint_state(8 * MS, "joints@8").tick
    assert tick is not None and tick.base == "base@8"


# -- safe mode -----------------------------------------------------------------------------------------------
def test_a_stale_base_state_makes_a_safe_mode_tick_and_the_next_fresh_tick_leaves_it() -> None:
    p = policy(stale_periods=3)
    step(p, 0)
    assert p.tick_done(fallback=False) is False and p.mode is Mode.NORMAL
    p.joint_state(20 * MS, "joints@20")                         # deferred: waits for its base state
    tick = p.joint_state(24 * MS, "joints@24").tick             # decided: base is 6 periods old
    assert tick is not None and tick.safe_reason == "base state is 24.0 ms old"
    assert p.enter_safe_mode() is True and p.mode is Mode.SAFE
    assert p.enter_safe_mode() is False                         # already in safe mode: say it once
    fresh = step(p, 28 * MS).tick
    assert fresh is not None and fresh.safe_reason is None
    assert p.tick_done(fallback=True) is True and p.mode is Mode.FALLBACK
    assert p.tick_done(fallback=False) is False and p.mode is Mode.NORMAL
    assert p.counters.ticks == 3


def test_exactly_stale_periods_old_is_still_fresh_and_the_threshold_is_live() -> None:
    p = policy(stale_periods=3)
    step(p, 0)
    assert p.joint_state(4 * MS, "j").tick is None
    tick = p.joint_state(12 * MS, "j").tick                     # 12 ms = 3 periods: not older than that
    assert tick is not None and tick.safe_reason is None
    p.set_stale_periods(1)
    assert p.stale_ns == PERIOD
    p.joint_state(16 * MS, "j")
    assert p.joint_state(20 * MS, "j").tick.safe_reason == "base state is 20.0 ms old"
    with pytest.raises(InputError, match="stale_periods"):
        p.set_stale_periods(0)


# -- heightmaps ----------------------------------------------------------------------------------------------
def test_a_heightmap_comes_into_use_one_control_period_after_its_stamp() -> None:
    p = policy()
    step(p, 0)
    p.heightmap(4 * MS, "map@4")              # stamped with the next tick: not used by it
    p.heightmap(0, "map@0")                   # arrival order does not matter
    assert step(p, 4 * MS).tick.heightmap == "map@0"
    assert step(p, 8 * MS).tick.heightmap == "map@4"
    assert step(p, 12 * MS).tick.heightmap == "map@4"   # kept until a newer one is due
    p.heightmap(9 * MS, "map@9")
    p.heightmap(10 * MS, "map@10")
    assert step(p, 16 * MS).tick.heightmap == "map@10"  # the newest due one
    assert p.heightmap_in_use == "map@10"


# -- contacts ------------------------------------------------------------------------------------------------
def test_with_contacts_a_tick_waits_for_the_contacts_of_its_stamp_and_goes_on_without_stale_ones() -> None:
    p = policy(contacts=True)
    assert step(p, 0).tick is None and p.counters.deferred_ticks == 1
    flags = np.array([True, True, False, True])
    tick = p.contacts(0, flags).tick
    assert tick is not None and tick.contacts is flags
    step(p, 4 * MS)                                       # no contacts of 4 ms: deferred
    tick = step(p, 8 * MS).tick                           # decided, with contacts 8 ms old: still fresh
    assert tick.contacts is flags and p.counters.ticks_without_contacts == 0
    step(p, 12 * MS)
    tick = step(p, 16 * MS).tick                          # contacts 16 ms old > 3 periods: the plan
    assert tick is not None and tick.contacts is None and p.counters.ticks_without_contacts == 1


def test_contacts_on_the_estimators_grid_are_expected_at_its_latest_tick_not_the_wbcs_stamp() -> None:
    # The estimator's contact estimate comes every 3 ms (0, 3, 6, 9 ...): the wbc's tick at 4 ms uses the
    # one of 3 ms, and waits for it; on the joint state's own grid it would wait for contacts of 4 ms that
    # never come.
    p = policy(contacts=True, contact_period_ns=3 * MS, base_period_ns=3 * MS)
    p.contacts(0, "c@0")
    assert step(p, 0).tick.contacts == "c@0"
    assert step(p, 4 * MS, base_ns=3 * MS).tick is None               # contacts of 3 ms not there yet
    tick = p.contacts(3 * MS, "c@3").tick
    assert tick is not None and tick.stamp_ns == 4 * MS and tick.contacts == "c@3"
    p.contacts(6 * MS, "c@6")
    tick = step(p, 8 * MS, base_ns=6 * MS).tick                       # 6 ms is the latest at or before 8
    assert tick is not None and tick.contacts == "c@6" and p.counters.deferred_ticks == 1
    same_grid = policy(contacts=True, base_period_ns=3 * MS)
    same_grid.contacts(3 * MS, "c@3")
    step(same_grid, 0)
    assert step(same_grid, 4 * MS, base_ns=3 * MS).tick is None       # waits for contacts stamped 4 ms


def test_without_contacts_configured_ticks_carry_none() -> None:
    p = policy()
    p.contacts(0, "flags")
    assert step(p, 0).tick.contacts is None and p.counters.ticks_without_contacts == 0


# -- restarts and repeats ------------------------------------------------------------------------------------
def test_a_clock_jump_back_restarts_the_grid_and_forgets_inputs_of_the_old_run() -> None:
    p = policy()
    p.commands.stamped(2_100 * MS, (0.5, 0.0, 0.0))       # queued for a tick the old run will not reach
    p.heightmap(0, "map@0")
    for k in range(0, 2_001, 4):
        step(p, k * MS)
        p.answered(k * MS)
    p.heightmap(1_999 * MS, "map@1999")                   # pending at the restart: forgotten
    p.contacts(2_000 * MS, "contacts@2000")
    assert p.heightmap_in_use == "map@0" and p.next_tick_ns == 2_004 * MS
    back = p.joint_state(1_400 * MS, "joints@1400")
    assert back.restarted and back.tick is None           # the base state of the old run is forgotten
    assert p.next_tick_ns == 0 and p.counters.restarts == 1
    tick = p.base_state(1_400 * MS, "base@1400").tick     # jumps back too: replaces the held one
    assert tick is not None and tick.stamp_ns == 1_400 * MS and tick.base == "base@1400"
    assert tick.heightmap == "map@0"                      # the map in use stays
    assert tick.command.tolist() == [0.0, 0.0, 0.0]
    for k in range(1_404, 2_201, 4):                      # the new run passes the old stamps
        tick = step(p, k * MS).tick
        assert tick.heightmap == "map@0" and tick.command.tolist() == [0.0, 0.0, 0.0]


def test_contacts_from_after_the_restart_stamp_are_forgotten() -> None:
    p = policy(contacts=True)
    for k in range(0, 1_001, 4):
        p.contacts(k * MS, f"contacts@{k}")
        step(p, k * MS)
    assert p.joint_state(400 * MS, "joints@400").restarted
    assert p.base_state(400 * MS, "base@400").tick is None  # waits for the new run's contacts
    assert p.counters.restarts == 1 and p.counters.deferred_ticks == 1
    tick = p.contacts(400 * MS, "contacts@400 again").tick
    assert tick is not None and tick.contacts == "contacts@400 again"


def test_a_small_jump_back_is_reordering_not_a_restart() -> None:
    p = policy()
    step(p, 1_000 * MS)
    small = p.joint_state(1_000 * MS - CLOCK_RESET_NS + MS, "late sample")
    assert not small.restarted and small.tick is None
    assert p.joint_state(1_000 * MS - CLOCK_RESET_NS - MS, "restarted").restarted


def test_the_state_last_answered_is_answered_again_until_the_driver_moves_on() -> None:
    p = policy()
    step(p, 0)
    p.answered(0)
    again = p.joint_state(0, "repeat")
    assert again.repeat_answer and again.tick is None and not again.feed_watchdog
    assert not p.joint_state(MS, "next").repeat_answer
    # After a restart nothing has been answered yet.
    for k in range(4, 1_001, 4):
        step(p, k * MS)
        p.answered(k * MS)
    assert p.joint_state(0, "restarted at 0").restarted
    assert not p.joint_state(0, "repeat of the new first").repeat_answer


# -- velocity command at the tick ----------------------------------------------------------------------------
def test_a_stamped_command_applies_from_its_tick() -> None:
    p = policy()
    p.commands.stamped(4 * MS, (0.3, 0.0, 0.0))
    assert step(p, 0).tick.command.tolist() == [0.0, 0.0, 0.0]
    assert step(p, 4 * MS).tick.command.tolist() == [0.3, 0.0, 0.0]


# -- the watchdog --------------------------------------------------------------------------------------------
def test_the_watchdog_trips_after_the_timeout_of_silence_from_the_last_handled_joint_state() -> None:
    clock = FakeClock(100.0)
    p = policy(watchdog_timeout_s=0.25, clock=clock)
    clock.now_s = 200.0
    assert p.watchdog() is None                    # no joint state yet: nothing to guard
    step(p, 0)
    step(p, MS)
    p.feed_watchdog()                              # the node handled the 1 ms joint state at 200 s
    clock.now_s = 200.125
    assert p.watchdog() is None and p.counters.watchdog_trips == 0
    clock.now_s = 200.25                           # exactly the timeout
    trip = p.watchdog()
    assert trip is not None and trip.stamp_ns == MS and trip.silence_s == 0.25
    clock.now_s = 200.5
    assert p.watchdog().silence_s == 0.5 and p.counters.watchdog_trips == 2
    p.feed_watchdog()
    assert p.watchdog() is None


def test_the_watchdog_is_off_at_timeout_zero() -> None:
    clock = FakeClock()
    p = policy(clock=clock)
    step(p, 0)
    p.feed_watchdog()
    clock.now_s += 1e6
    assert p.watchdog() is None


# -- the wait for a command source ---------------------------------------------------------------------------
def test_the_first_tick_waits_for_a_command_source_and_retries_on_the_repeated_first_state() -> None:
    clock, found = FakeClock(10.0), {"value": False}
    p = policy(command_source_wait_s=60.0, clock=clock, found=lambda: found["value"])
    first = step(p, 0)
    assert first.tick is None and p.waiting_for_command_source and p.counters.command_source_waits == 1
    assert p.joint_state(0, "repeat").tick is None and p.counters.command_source_waits == 2
    found["value"] = True
    retry = p.joint_state(0, "repeat")
    assert retry.tick is not None and retry.tick.stamp_ns == 0 and not retry.command_source_missing
    assert not retry.feed_watchdog and not p.waiting_for_command_source


def test_the_wait_for_a_command_source_ends_at_its_deadline() -> None:
    clock = FakeClock(10.0)
    p = policy(command_source_wait_s=5.0, clock=clock, found=lambda: False)
    assert step(p, 0).tick is None
    clock.now_s = 15.5
    late = p.joint_state(0, "repeat")
    assert late.tick is not None and late.command_source_missing
    assert not step(p, 4 * MS).command_source_missing  # said once


# -- configuration -------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("changes", "message"), [
    ({"period_ns": 0}, "period_ns"), ({"stale_periods": 0}, "stale_periods"),
    ({"base_period_ns": -1}, "base_period_ns"), ({"watchdog_timeout_s": float("nan")}, "watchdog_timeout_s"),
    ({"command_source_wait_s": -1.0}, "command_source_wait_s"),
])
def test_invalid_configurations_are_refused_by_name(changes: dict, message: str) -> None:
    with pytest.raises(InputError, match=message):
        TickPolicyConfig(**{"period_ns": PERIOD, **changes})


# -- lagged inputs (impedance, footholds, body pose) -----------------------------------------------------------
def test_lagged_inputs_reach_the_first_tick_one_period_after_their_stamp_in_stamp_order() -> None:
    """A foothold answer stamped with tick 4 ms arrives before or after the joint state of 8 ms: either way it
    is used from the tick at 8 ms, never at 4 ms, and several are handed over in stamp order."""
    for early in (True, False):
        p = policy()
        assert step(p, 0).tick.inputs == ()
        assert p.lagged("footholds", 4 * MS, "f@4").tick is None  # not waited: no decision
        tick4 = step(p, 4 * MS).tick
        assert tick4 is not None and tick4.inputs == ()  # stamped with this tick: the next one uses it
        p.lagged("body_pose", 0, "pose@0")
        if early:
            p.lagged("footholds", 8 * MS, "f@8")
        tick8 = step(p, 8 * MS).tick
        assert tick8.inputs == (("body_pose", "pose@0"), ("footholds", "f@4"))
        if not early:
            p.lagged("footholds", 8 * MS, "f@8")
        assert step(p, 12 * MS).tick.inputs == (("footholds", "f@8"),)


def test_a_tick_waits_for_the_previous_ticks_waited_input() -> None:
    """waited_inputs: the tick at 8 ms is computed only once the impedance answering 4 ms is in; a producer
    that skipped 4 ms and answered 8 ms releases it too; past max_defer the tick runs without it (counted)."""
    p = policy(waited_inputs=("impedance",))
    assert step(p, 0).tick is not None  # the first tick waits for nothing
    p.lagged("impedance", 0, "k@0")
    assert step(p, 4 * MS).tick.inputs == (("impedance", "k@0"),)
    assert step(p, 8 * MS).tick is None and p.counters.deferred_ticks == 1  # no answer to 4 ms yet
    late = p.lagged("impedance", 4 * MS, "k@4")
    assert late.tick is not None and late.tick.stamp_ns == 8 * MS and late.tick.inputs == (("impedance", "k@4"),)
    assert step(p, 12 * MS).tick is None
    skipped = p.lagged("impedance", 12 * MS, "k@12")  # 8 ms skipped: the answer to 12 ms will do
    assert skipped.tick is not None and skipped.tick.inputs == ()  # ... but it is not used before 16 ms
    bounded = policy(waited_inputs=("impedance",), max_defer_ns=2 * MS)
    step(bounded, 0)
    assert step(bounded, 4 * MS).tick is None and step(bounded, 6 * MS).tick is None
    assert step(bounded, 7 * MS).tick is not None and bounded.counters.ticks_without_waited == 1


def test_the_first_tick_waits_for_a_first_answer_of_each_waited_input() -> None:
    """A producer discovered late: the first tick (the driver re-sends its initial state) waits for its first
    answer, up to command_source_wait_s of wall time; without a producer it starts at the deadline."""
    clock = FakeClock()
    p = policy(waited_inputs=("impedance",), command_source_wait_s=5.0, clock=clock)
    assert step(p, 0).tick is None
    assert p.wants_joint_state(0) and step(p, 0).tick is None  # a re-sent initial state: still waiting
    first = p.lagged("impedance", 0, "k@0")
    assert first.tick is not None and first.tick.stamp_ns == 0 and first.tick.inputs == ()
    assert step(p, 4 * MS).tick.inputs == (("impedance", "k@0"),)
    alone = policy(waited_inputs=("impedance",), command_source_wait_s=5.0, clock=clock)
    assert step(alone, 0).tick is None
    clock.now_s += 6.0
    assert step(alone, 0).tick is not None  # the deadline passed: start without it ...
    assert alone.unanswered_inputs == ("impedance",)
    assert step(alone, 4 * MS).tick is not None  # ... and no longer wait for it


def test_a_producer_answering_every_p_of_sim_time_is_waited_for_on_its_own_grid() -> None:
    """The VPA answers the first gait state at least 50 ms after its last answer: after its answer to 0 ms,
    the ticks up to 52 ms wait for nothing; the tick at 56 ms waits for its answer to 52 ms."""
    p = policy(waited_inputs=("body_pose",), waited_periods_ns=(("body_pose", 50 * MS),), gait_driven=("body_pose",))
    assert step(p, 0).tick is not None  # gait-driven: the first tick waits for nothing (no command source wait)
    assert step(p, 4 * MS).tick is None  # the answer to the gait state of 0 ms is not in
    assert p.lagged("body_pose", 0, "pose@0").tick.stamp_ns == 4 * MS
    for k in range(8, 53, 4):
        assert step(p, k * MS).tick is not None, k
    assert step(p, 56 * MS).tick is None
    late = p.lagged("body_pose", 52 * MS, "pose@52")
    assert late.tick is not None and late.tick.inputs == (("body_pose", "pose@52"),)


def test_the_first_tick_waits_for_gait_driven_producers_to_be_discovered() -> None:
    clock, ready = FakeClock(), [False]
    p = WbcTickPolicy(TickPolicyConfig(period_ns=PERIOD, command_source_wait_s=5.0, waited_inputs=("footholds",),
                                       gait_driven=("footholds",)),
                      VelocityCommandInput(1.0, 1.0), clock=clock, producers_ready=lambda: ready[0])
    assert step(p, 0).tick is None
    ready[0] = True
    assert step(p, 0).tick is not None  # the re-sent initial state: now the vfa listens
    assert step(p, 4 * MS).tick is None  # ... and its answer to 0 ms is awaited
    never = WbcTickPolicy(TickPolicyConfig(period_ns=PERIOD, command_source_wait_s=5.0, waited_inputs=("footholds",),
                                           gait_driven=("footholds",)),
                          VelocityCommandInput(1.0, 1.0), clock=clock, producers_ready=lambda: False)
    assert step(never, 0).tick is None
    clock.now_s += 6.0
    assert step(never, 0).tick is not None and never.unanswered_inputs == ("footholds",)
    assert step(never, 4 * MS).tick is not None


def test_startup_inputs_hold_only_the_first_tick() -> None:
    """On the wall clock nothing is waited for after the start, but the robot starts once its producers run:
    the first tick waits for the TCE's first answer and the vfa's discovery; the next ticks run without
    the TCE's answers; a producer that never comes is given up at the deadline and said."""
    clock, ready = FakeClock(), [False]
    p = WbcTickPolicy(TickPolicyConfig(period_ns=PERIOD, command_source_wait_s=5.0, gait_driven=("footholds",),
                                       startup_inputs=("impedance", "footholds")),
                      VelocityCommandInput(1.0, 1.0), clock=clock, producers_ready=lambda: ready[0])
    assert step(p, 0).tick is None
    assert p.first_tick_waits_for() == ("the first impedance answer",
                                        "the footholds / body pose producers' gait_state subscriptions")
    assert p.lagged("impedance", 0, "k@0").tick is None  # the vfa is not there yet
    ready[0] = True
    assert step(p, 0).tick is not None
    for k in range(1, 5):  # no answers to later ticks: nobody waits for them
        assert step(p, 4 * k * MS).tick is not None, k
    late = WbcTickPolicy(TickPolicyConfig(period_ns=PERIOD, command_source_wait_s=5.0,
                                          startup_inputs=("impedance",)),
                         VelocityCommandInput(1.0, 1.0), clock=clock)
    assert step(late, 0).tick is None
    clock.now_s += 6.0
    assert step(late, 0).tick is not None and late.unanswered_inputs == ("impedance",)
    assert step(late, 4 * MS).tick is not None
    without_wait = policy(startup_inputs=("impedance",))  # command_source_wait_s 0: no wait at all
    assert step(without_wait, 0).tick is not None


def test_with_the_heightmap_period_a_tick_waits_for_the_map_due_at_it() -> None:
    """Maps every 50 ms: the tick at 4 ms waits for the map of 0 ms, the one at 56 ms for the map of 50 ms (it
    arrives after the joint state: DDS gives no order between topics); a map that comes after the tick that
    should have used it is late (counted). Without the period the tick would have used the older map."""
    p = policy(heightmap_period_ns=50 * MS)
    assert step(p, 0).tick is not None                   # nothing due before the first control period
    assert step(p, 4 * MS).tick is None and p.deferred_for == ("heightmap",)
    assert p.first_tick_waits_for() == ()                 # the first tick is done: nothing to report
    arrival = p.heightmap(0, "map@0")
    assert arrival.tick is not None and arrival.tick.stamp_ns == 4 * MS and arrival.tick.heightmap == "map@0"
    for k in range(8, 53, 4):
        assert step(p, k * MS).tick.heightmap == "map@0", k
    assert step(p, 56 * MS).tick is None
    assert p.heightmap(50 * MS, "map@50").tick.heightmap == "map@50"
    p.heightmap(100 * MS, "map@100")
    assert step(p, 104 * MS).tick.heightmap == "map@100" and p.late_heightmaps == 0
    unwaited = policy()                                    # without the period: used as it arrives
    step(unwaited, 0)
    assert step(unwaited, 54 * MS).tick.heightmap is None
    unwaited.heightmap(50 * MS, "map@50")                  # after the tick that should have used it
    assert unwaited.late_heightmaps == 1
    bounded = policy(heightmap_period_ns=50 * MS, max_defer_ns=2 * MS)
    step(bounded, 0)
    assert step(bounded, 4 * MS).tick is None and step(bounded, 7 * MS).tick is not None
    assert bounded.counters.ticks_without_heightmap == 1
    with pytest.raises(InputError, match="heightmap_period_ns"):
        TickPolicyConfig(period_ns=PERIOD, heightmap_period_ns=-1)


def test_a_repeated_answer_is_dropped_and_says_the_tick_waits_for_answers() -> None:
    """A producer answers a re-sent gait state again: the repeat (the newest stamp again) is used once."""
    p = policy(waited_inputs=("footholds",))
    step(p, 0)
    assert step(p, 4 * MS).tick is None and p.waiting_for_answers
    first = p.lagged("footholds", 0, "f@0")
    assert first.tick is not None and first.tick.inputs == (("footholds", "f@0"),) and not p.waiting_for_answers
    assert p.lagged("footholds", 0, "f@0 again").tick is None and p.counters.repeated_answers == 1
    p.lagged("footholds", 4 * MS, "f@4")
    assert step(p, 8 * MS).tick.inputs == (("footholds", "f@4"),)


def test_the_first_tick_says_what_it_waits_for() -> None:
    clock = FakeClock()
    p = policy(waited_inputs=("impedance",), command_source_wait_s=5.0, clock=clock, found=lambda: False)
    assert p.first_tick_waits_for() == ("a joint state", "a base state", "a cmd_vel_stamped publisher",
                                        "the first impedance answer")
    step(p, 0)
    assert p.first_tick_waits_for() == ("a cmd_vel_stamped publisher", "the first impedance answer")
    clock.now_s += 6.0
    assert step(p, 0).tick is not None and p.first_tick_waits_for() == ()
