"""The sim-time tick grid and the inbox that ties stamped inputs to a later tick."""

from __future__ import annotations

import pytest

from tal_core.ticks import (
    CLOCK_RESET_NS,
    HeldTicks,
    RecentByStamp,
    StampedInbox,
    TickAnswers,
    reaches_tick,
    tick_after,
)

MS = 1_000_000


def test_grid() -> None:
    assert reaches_tick(4 * MS - 50_000, 4 * MS) and not reaches_tick(3 * MS, 4 * MS)
    assert tick_after(4 * MS, 4 * MS) == 8 * MS and tick_after(5 * MS, 4 * MS) == 8 * MS


def test_inbox_hands_inputs_to_the_first_tick_one_lag_later_in_stamp_order() -> None:
    for order in ((0, 50, 100), (100, 0, 50)):
        inbox = StampedInbox(lag_ns=4 * MS)
        for stamp in order:
            inbox.add(stamp * MS, f"map@{stamp}")
        assert inbox.due(50 * MS) == [(0, "map@0")]  # 50 ms is its own tick: not yet
        assert inbox.due(54 * MS) == [(50 * MS, "map@50")]
        assert inbox.due(100 * MS) == [] and len(inbox) == 1
        assert inbox.due(104 * MS) == [(100 * MS, "map@100")] and len(inbox) == 0


def test_inbox_bounds_its_memory_and_forgets_inputs_from_before_a_restart() -> None:
    inbox = StampedInbox(lag_ns=0, keep=3)
    for stamp in range(5):
        inbox.add(stamp * MS, stamp)
    assert inbox.dropped == 2 and [item for _, item in inbox.due(10 * MS)] == [2, 3, 4]
    inbox.add(10 * MS + CLOCK_RESET_NS + 1, "before the restart")
    inbox.add(0, "after")
    assert inbox.due(0) == [(0, "after")] and len(inbox) == 0
    with pytest.raises(ValueError, match="lag_ns >= 0"):
        StampedInbox(lag_ns=-1)


def test_a_tolerance_for_jittered_stamps() -> None:
    """A sample 0.3 ms early takes its grid point with a 0.4 ms tolerance (not with the default), and the
    next grid point stays the one after it."""
    assert not reaches_tick(4 * MS - 300_000, 4 * MS)
    assert reaches_tick(4 * MS - 300_000, 4 * MS, tolerance_ns=400_000)
    assert tick_after(4 * MS - 300_000, 2 * MS, tolerance_ns=400_000) == 6 * MS


def test_an_inbox_with_the_producers_period_says_which_input_a_tick_awaits_and_counts_late_ones() -> None:
    """Heightmaps every 50 ms used one 4 ms tick after their stamp: the tick at 54 ms awaits the map of 50 ms
    (a newer one will do); a map that arrives after the tick that should have used it is late."""
    inbox = StampedInbox(lag_ns=4 * MS, period_ns=50 * MS)
    assert inbox.awaited(0) is None and inbox.due_stamp(0) is None  # nothing due before the first lag
    assert inbox.awaited(4 * MS) == 0
    inbox.add(0, "map@0")
    assert inbox.awaited(4 * MS) is None and inbox.awaited(53 * MS) is None and inbox.awaited(54 * MS) == 50 * MS
    assert inbox.has_due(4 * MS) and not inbox.has_due(0) and inbox.due(4 * MS) == [(0, "map@0")]
    assert inbox.due(58 * MS) == [] and inbox.late == 0
    inbox.add(50 * MS, "map@50")                    # after the 58 ms tick, which should have used it
    inbox.add(50 * MS, "map@50")                    # a repeat is not late again, and is dropped
    assert inbox.late == 1 and inbox.repeats == 1 and inbox.due(104 * MS) == [(50 * MS, "map@50")]
    inbox.add(50 * MS, "map@50 re-sent")            # already handed over: dropped too
    assert inbox.repeats == 2 and inbox.due(108 * MS) == []
    inbox.add(100 * MS, "map@100")                  # a newer map will do
    assert inbox.awaited(54 * MS) is None and inbox.awaited(104 * MS) is None and inbox.awaited(154 * MS) == 150 * MS
    assert StampedInbox(lag_ns=4 * MS).awaited(54 * MS) is None  # without a period nothing is awaited
    inbox.add(CLOCK_RESET_NS + 100 * MS, "later")
    inbox.add(0, "restarted")                       # a clock that jumps back forgets what arrived
    assert inbox.awaited(54 * MS) == 50 * MS and len(inbox) == 1
    with pytest.raises(ValueError, match="period_ns >= 0"):
        StampedInbox(lag_ns=0, period_ns=-1)


def test_an_input_that_never_came_while_a_newer_one_did_is_counted_as_missed() -> None:
    """The vpa's held update at 52 ms was due the 0 ms map, which DDS dropped (published before its
    subscription matched); the 50 ms map released it and it ran without a map (a CI run's tours differed by
    8 mm): counted once in missed."""
    inbox = StampedInbox(lag_ns=4 * MS, period_ns=50 * MS)
    held = HeldTicks([inbox])
    assert held.offer(52 * MS, "gait@52") == [] and inbox.awaited(52 * MS) == 0
    inbox.add(50 * MS, "map@50")
    assert held.arrived() == [(52 * MS, "gait@52")]
    assert inbox.due(52 * MS) == [] and inbox.missed == 1
    assert inbox.due(53 * MS) == [] and inbox.missed == 1          # counted once per missing input
    assert inbox.due(56 * MS) == [(50 * MS, "map@50")] and inbox.missed == 1
    control = StampedInbox(lag_ns=4 * MS, period_ns=50 * MS)      # the map came (late or not): not missed
    control.add(0, "map@0")
    control.add(50 * MS, "map@50")
    assert control.due(52 * MS) == [(0, "map@0")] and control.missed == 0


def test_held_ticks_wait_for_their_inputs_and_run_in_order() -> None:
    maps = StampedInbox(lag_ns=4 * MS, period_ns=50 * MS)
    maps.add(0, "map@0")
    held = HeldTicks([maps], max_defer_ns=0)
    assert held.offer(50 * MS, "gait@50") == [(50 * MS, "gait@50")]  # its map (0 ms) is here: at once
    assert held.offer(54 * MS, "gait@54") == [] and len(held) == 1     # awaits the map of 50 ms
    assert held.arrived() == [] and held.held_ticks == 1
    maps.add(50 * MS, "map@50")
    assert held.arrived() == [(54 * MS, "gait@54")] and len(held) == 0
    # A tick past max_defer releases an older held one without its input, counted; the new one still waits.
    assert held.offer(104 * MS, "gait@104") == []
    assert held.offer(108 * MS, "gait@108") == [(104 * MS, "gait@104")] and held.released_late == 1
    maps.add(100 * MS, "map@100")
    assert held.arrived() == [(108 * MS, "gait@108")]
    patient = HeldTicks([StampedInbox(lag_ns=4 * MS, period_ns=50 * MS)], max_defer_ns=10 * MS)
    assert patient.offer(4 * MS, "a") == [] and patient.offer(8 * MS, "b") == []
    assert patient.offer(16 * MS, "c") == [(4 * MS, "a")] and patient.released_late == 1
    with pytest.raises(ValueError, match="max_defer_ns"):
        HeldTicks([], max_defer_ns=-1)


def test_tick_answers_say_which_tick_is_a_repeat_and_what_to_send_again() -> None:
    answers = TickAnswers()
    assert answers.seen(0) == (False, None)
    assert answers.seen(0) == (True, None)               # repeated before it was answered: nothing to send
    answers.answered(0, "answer@0")
    assert answers.seen(0) == (True, "answer@0") and answers.resent == 1
    assert answers.seen(4 * MS) == (False, None) and answers.answered_ns == 0
    assert answers.seen(4 * MS) == (True, None)          # the answer on record is to another tick


def test_recent_by_stamp_keeps_the_newest_few_and_answers_exact_newest_and_at_or_before() -> None:
    recent = RecentByStamp(keep=3)
    assert recent.newest() is None and recent.at_or_before(10) is None
    for stamp in (3, 9, 6):                      # out of order
        recent.add(stamp, f"s{stamp}")
    recent.add(6, "again")                       # a repeat keeps the first
    assert recent.get(6) == "s6" and recent.newest() == (9, "s9")
    assert recent.at_or_before(8) == (6, "s6") and recent.at_or_before(2) is None
    recent.add(12, "s12")                        # the oldest to arrive (3) goes
    assert 3 not in recent and len(recent) == 3 and recent.newest() == (12, "s12")
    with pytest.raises(ValueError, match="keep"):
        RecentByStamp(keep=0)
