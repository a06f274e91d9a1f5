"""The bridge's timing without ROS: output schedule, lockstep gate, real-time pacing."""

from __future__ import annotations

import pytest

from tal_sim_bridge.errors import BridgeConfigError
from tal_sim_bridge.stepping import LockstepGate, OutputSchedule, RealtimePacer


def test_schedule_from_the_node_default_rates() -> None:
    schedule = OutputSchedule.from_rates(1000.0, 1000.0, 250.0, 20.0)
    assert (schedule.sensor_every, schedule.contact_every, schedule.heightmap_every) == (1, 4, 50)
    due = [schedule.due(step) for step in range(100)]
    assert sum(d.sensors for d in due) == 100
    assert [i for i, d in enumerate(due) if d.contacts][:3] == [0, 4, 8]
    assert [i for i, d in enumerate(due) if d.heightmap] == [0, 50]
    assert schedule.due(7, force_all=True) == schedule.due(0)
    assert all(d.clock for d in due)  # the clock at every physics step unless its rate is given
    clocked = OutputSchedule.from_rates(1000.0, 1000.0, 250.0, 20.0, clock_rate_hz=250.0)
    assert [step for step in range(12) if clocked.due(step).clock] == [0, 4, 8]


def test_ground_truth_at_the_control_rate_falls_on_every_control_tick() -> None:
    default = OutputSchedule.from_rates(1000.0, 1000.0, 250.0, 20.0)
    assert all(default.due(step).ground_truth for step in range(10))  # with the sensors unless its rate is given
    mocap = OutputSchedule.from_rates(1000.0, 1000.0, 250.0, 20.0, ground_truth_rate_hz=250.0)
    assert [step for step in range(13) if mocap.due(step).ground_truth] == [0, 4, 8, 12]
    assert mocap.due(3, force_all=True).ground_truth
    mocap.check_control_steps(4)
    mocap.check_control_steps(8)
    slow = OutputSchedule.from_rates(1000.0, 1000.0, 250.0, 20.0, ground_truth_rate_hz=100.0)
    with pytest.raises(BridgeConfigError, match="ground truth every 10 physics steps does not fall on every control"):
        slow.check_control_steps(4)


def test_schedule_rejects_a_zero_period() -> None:
    with pytest.raises(BridgeConfigError, match="contact_every must be >= 1"):
        OutputSchedule(1, 0, 50)
    with pytest.raises(BridgeConfigError, match="physics_rate_hz must be > 0"):
        OutputSchedule.from_rates(0.0, 1.0, 1.0, 1.0)


def test_lockstep_gate_releases_on_the_awaited_tick_only() -> None:
    gate = LockstepGate(timeout_s=2.0, startup_timeout_s=30.0)
    assert not gate.releases(0)  # not waiting
    gate.wait_for(4_000_000, now_s=10.0)
    assert not gate.releases(3_999_999)  # a command for an earlier tick
    assert gate.releases(4_000_000) and gate.releases(8_000_000)
    gate.release()
    assert gate.awaiting_tick_ns is None and gate.timed_out(100.0, commands_accepted=5) is None


def test_lockstep_gate_times_out_with_the_startup_timeout_before_the_first_command() -> None:
    gate = LockstepGate(timeout_s=2.0, startup_timeout_s=30.0)
    gate.wait_for(0, now_s=0.0)
    assert gate.timed_out(29.0, commands_accepted=0) is None
    assert gate.timed_out(30.5, commands_accepted=0) == 30.0
    gate.wait_for(4_000_000, now_s=40.0)
    assert gate.timed_out(41.0, commands_accepted=1) is None
    assert gate.timed_out(42.5, commands_accepted=1) == 2.0
    assert gate.timeouts == 2


def test_realtime_pacer_follows_the_wall_clock_and_drops_a_backlog() -> None:
    pacer = RealtimePacer(physics_rate_hz=1000.0, max_catch_up_steps=20, start_s=100.0)
    assert pacer.steps_due(100.0005, step_count=0) == 0
    assert pacer.steps_due(100.0104, step_count=0) == 10
    assert pacer.steps_due(100.0104, step_count=10) == 0
    # 0.5 s stalled: 490 steps behind, 20 taken, the rest dropped (sim time falls behind the wall clock)
    assert pacer.steps_due(100.5004, step_count=10) == 20
    assert pacer.overruns == 1
    assert pacer.start_s == pytest.approx(100.47)
    assert pacer.steps_due(100.5004, step_count=30) == 0
    with pytest.raises(BridgeConfigError, match="max_catch_up_steps >= 1"):
        RealtimePacer(1000.0, 0, 0.0)
