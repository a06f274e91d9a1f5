"""The sim-time tick grid and the inbox that ties stamped inputs to a later tick."""

from __future__ import annotations

import pytest

from tal_core.ticks import CLOCK_RESET_NS, StampedInbox, reaches_tick, tick_after

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
