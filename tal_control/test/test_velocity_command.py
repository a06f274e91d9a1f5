"""The velocity command input of the wbc: stamped commands by stamp, late ones counted, unstamped ones
applied unless stamped ones are in use."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tal_control.velocity_command import VelocityCommandInput
from tal_core.errors import InputError

MS = 1_000_000


def test_stamped_commands_apply_from_their_tick_whatever_the_arrival_order() -> None:
    cmd = VelocityCommandInput(1.0, 1.0)
    cmd.stamped(8 * MS, (0.2, 0.0, 0.0))
    cmd.stamped(4 * MS, (0.1, 0.0, 0.0))
    assert cmd.at_tick(0).tolist() == [0.0, 0.0, 0.0]
    assert cmd.at_tick(4 * MS).tolist() == [0.1, 0.0, 0.0]
    assert cmd.at_tick(8 * MS).tolist() == [0.2, 0.0, 0.0]
    assert cmd.late == 0


def test_a_stamped_command_after_its_tick_applies_at_once_and_counts_as_late_when_it_changes_it() -> None:
    cmd = VelocityCommandInput(1.0, 1.0)
    cmd.at_tick(12 * MS)
    assert not cmd.stamped(10 * MS, (0.0, 0.0, 0.0))        # late, but changes nothing
    assert cmd.stamped(12 * MS, (0.3, 0.0, 0.0))            # late for the tick at 12 ms
    assert cmd.command.tolist() == [0.3, 0.0, 0.0] and cmd.late == 1
    assert not cmd.stamped(11 * MS, (0.9, 0.0, 0.0))        # older than the one in force: ignored
    assert cmd.command.tolist() == [0.3, 0.0, 0.0] and cmd.late == 1


def test_unstamped_commands_apply_at_once_unless_stamped_ones_are_in_use() -> None:
    cmd = VelocityCommandInput(0.5, 0.2, stamped_priority_s=1.0)
    assert cmd.unstamped((2.0, -2.0, 1.0))
    assert cmd.command.tolist() == [0.5, -0.5, 0.2]        # clamped
    cmd.stamped(100 * MS, (0.1, 0.0, 0.0))
    assert not cmd.unstamped((0.3, 0.0, 0.0)) and cmd.unstamped_ignored == 1
    cmd.at_tick(100 * MS)
    cmd.at_tick(1100 * MS)                                  # the newest stamp is 1 s old: still in use
    assert not cmd.unstamped((0.3, 0.0, 0.0))
    cmd.at_tick(1104 * MS)                                  # the stamped source went quiet
    assert cmd.unstamped((0.3, 0.0, 0.0)) and cmd.command.tolist() == [0.3, 0.0, 0.0]


def test_reset_forgets_the_queue_and_keeps_the_command() -> None:
    cmd = VelocityCommandInput(1.0, 1.0)
    cmd.stamped(0, (0.1, 0.0, 0.0))
    cmd.at_tick(0)
    cmd.stamped(4 * MS, (0.2, 0.0, 0.0))
    cmd.reset()
    assert cmd.at_tick(4 * MS).tolist() == [0.1, 0.0, 0.0] and not cmd.stamped_in_use()


@pytest.mark.parametrize("values", [(math.nan, 0.0, 0.0), (0.0, 0.0), (0.0, math.inf, 0.0)])
def test_bad_commands_raise_and_change_nothing(values) -> None:
    cmd = VelocityCommandInput(1.0, 1.0)
    with pytest.raises(InputError, match="3 finite values"):
        cmd.unstamped(values)
    with pytest.raises(InputError, match="3 finite values"):
        cmd.stamped(0, values)
    assert np.array_equal(cmd.command, np.zeros(3)) and not cmd.stamped_in_use()


def test_new_limits_clamp_the_command_in_force_and_the_queued_ones_at_once() -> None:
    cmd = VelocityCommandInput(1.0, 1.0)
    cmd.unstamped((0.8, -0.6, 0.9))
    cmd.stamped(4 * MS, (0.7, 0.0, -0.9))
    cmd.set_limits(0.5, 0.25)
    assert cmd.command.tolist() == [0.5, -0.5, 0.25]
    assert cmd.at_tick(4 * MS).tolist() == [0.5, 0.0, -0.25]
    with pytest.raises(InputError, match="max_linear_m_s"):
        cmd.set_limits(-1.0, 0.25)
    assert cmd.max_linear_m_s == 0.5
