"""The command profile: segments in force, and the stamps a stamped player publishes."""

from __future__ import annotations

import pytest

from tal_control.cmd_vel_profile import command_at, parse_profile, stamps_due
from tal_core.errors import InputError

MS = 1_000_000


def test_command_in_force_is_the_last_segment_started() -> None:
    segments = parse_profile([0.0, 0.0, 0.0, 0.0, 1.0, 0.3, 0.0, 0.1])
    assert command_at(segments, 0.999).vx_m_s == 0.0
    assert command_at(segments, 1.0).vx_m_s == 0.3 and command_at(segments, 5.0).yaw_rate_rad_s == 0.1


def test_stamps_are_the_absolute_grid_plus_the_segment_starts() -> None:
    segments = parse_profile([0.0, 0.0, 0.0, 0.0, 1.013, 0.3, 0.0, 0.0])
    assert stamps_due(segments, 20 * MS, -1, 60 * MS) == [0, 20 * MS, 40 * MS, 60 * MS]
    # Joined late: the same grid, not one relative to the first clock.
    assert stamps_due(segments, 20 * MS, 7 * MS, 45 * MS) == [20 * MS, 40 * MS]
    assert stamps_due(segments, 20 * MS, 1000 * MS, 1040 * MS) == [1013 * MS, 1020 * MS, 1040 * MS]
    assert stamps_due(segments, 20 * MS, 40 * MS, 40 * MS) == []


def test_a_zero_period_is_refused() -> None:
    with pytest.raises(InputError, match="period"):
        stamps_due(parse_profile([0.0, 0.0, 0.0, 0.0]), 0, 0, 10)
