"""The fault relay's logic: exact, seeded fault fractions and NaN corruption of positions (the node is
tested in tests/test_faults.py)."""

from __future__ import annotations

import math

import pytest
from nav_msgs.msg import Odometry
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

from tal_core.ros.fault_injection import FaultRelay, FaultSchedule, corrupt_with_nan


def picks(schedule: FaultSchedule, n: int) -> list[int]:
    return [k for k in range(n) if schedule.next()]


def test_schedule_picks_exactly_the_fraction_in_every_period_at_seeded_positions() -> None:
    schedule = FaultSchedule(0.1, seed=3)
    assert (schedule.count, schedule.period) == (1, 10)
    picked = picks(schedule, 1000)
    assert len(picked) == 100 and schedule.picked == 100 and schedule.seen == 1000
    assert [k // 10 for k in picked] == list(range(100))  # one in each block of ten
    assert len({k % 10 for k in picked}) > 5               # at random places within the blocks
    assert picks(FaultSchedule(0.1, seed=3), 1000) == picked
    assert picks(FaultSchedule(0.1, seed=4), 1000) != picked


@pytest.mark.parametrize("fraction", [0.0, 0.25, 0.333, 1.0])
def test_schedule_is_within_one_period_count_of_the_fraction(fraction: float) -> None:
    schedule = FaultSchedule(fraction, seed=0)
    for n in (7, 100, 1234):
        while schedule.seen < n:
            schedule.next()
        assert abs(schedule.picked - schedule.fraction * n) <= schedule.count
    assert schedule.fraction == pytest.approx(fraction, abs=1e-3)


@pytest.mark.parametrize("fraction", [-0.1, 1.5, math.nan])
def test_schedule_refuses_a_fraction_outside_0_1(fraction: float) -> None:
    with pytest.raises(ValueError, match="fault fraction must be in"):
        FaultSchedule(fraction)


def test_corrupt_with_nan_replaces_joint_and_odometry_positions_only() -> None:
    joints = corrupt_with_nan(JointState(name=["a", "b"], position=[1.0, 2.0], velocity=[3.0, 4.0]))
    assert all(math.isnan(v) for v in joints.position) and list(joints.velocity) == [3.0, 4.0]
    odom = Odometry()
    odom.pose.pose.orientation.w = 1.0
    corrupt_with_nan(odom)
    assert math.isnan(odom.pose.pose.position.z) and odom.pose.pose.orientation.w == 1.0
    with pytest.raises(TypeError, match="Float64"):
        corrupt_with_nan(Float64())


def test_relay_drops_then_corrupts_and_counts_by_stamp() -> None:
    relay = FaultRelay(drop_fraction=0.1, nan_fraction=0.2, seed=7)
    out = []
    for k in range(100):
        msg = JointState(name=["a"], position=[float(k)])
        msg.header.stamp.nanosec = k
        out.append(relay.process(msg))
    counts = relay.counts
    assert counts.received == 100 and counts.dropped == 10 and counts.passed == 90
    assert counts.dropped_stamps_ns == [k for k in range(100) if out[k] is None]
    corrupted = [k for k in range(100) if out[k] is not None and math.isnan(out[k].position[0])]
    assert corrupted == counts.corrupted_stamps_ns and counts.corrupted == len(corrupted)
    # Exactly 20 messages were picked for NaN; those that were also dropped were not sent.
    assert relay.nans.picked == 20 and counts.corrupted <= 20



def test_relay_passes_messages_stamped_before_the_start_without_using_the_schedule() -> None:
    relay = FaultRelay(drop_fraction=0.5, seed=2, start_ns=50)
    reference = FaultSchedule(0.5, seed=2)
    out = []
    for k in range(100):
        msg = JointState(name=["a"], position=[float(k)])
        msg.header.stamp.nanosec = k
        out.append(relay.process(msg))
    assert all(m is not None for m in out[:50])
    assert [k for k in range(50, 100) if out[k] is None] == [50 + k for k in picks(reference, 50)]
    assert relay.counts.as_dict() == {"received": 100, "eligible": 50, "passed": 75, "dropped": 25, "corrupted": 0}
