"""Swing trajectories: boundary conditions, apex, derivative consistency, mid-swing retargeting."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tal_control.errors import MotionConfigError
from tal_control.motion.swing import SwingTrajectory
from tal_core.errors import InputError

LIFTOFF = np.array([0.37, 0.21, 0.02])
TOUCHDOWN = np.array([0.52, 0.18, 0.10])  # forward, a little inwards, onto a 8 cm step
DURATION = 0.4
APEX = 0.12


def samples(swing: SwingTrajectory, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    states = [swing.sample(t) for t in times]
    return (np.array([s.position for s in states]), np.array([s.velocity for s in states]),
            np.array([s.acceleration for s in states]))


def assert_derivatives_consistent(swing: SwingTrajectory, t0: float, t1: float) -> None:
    """Central differences of position and velocity match velocity and acceleration."""
    h = 1e-5
    times = np.linspace(t0 + 2 * h, t1 - 2 * h, 96)  # even count: skip the jerk step at mid-swing
    p_plus, v_plus, _ = samples(swing, times + h)
    p_minus, v_minus, _ = samples(swing, times - h)
    _, v, a = samples(swing, times)
    np.testing.assert_allclose((p_plus - p_minus) / (2 * h), v, atol=1e-6)
    np.testing.assert_allclose((v_plus - v_minus) / (2 * h), a, atol=1e-4)


def test_boundary_conditions():
    swing = SwingTrajectory(LIFTOFF, TOUCHDOWN, DURATION, APEX)
    start, end = swing.sample(0.0), swing.sample(DURATION)
    np.testing.assert_allclose(start.position, LIFTOFF, atol=1e-12)
    np.testing.assert_allclose(end.position, TOUCHDOWN, atol=1e-12)
    for state in (start, end):
        np.testing.assert_allclose(state.velocity, 0.0, atol=1e-12)
        np.testing.assert_allclose(state.acceleration, 0.0, atol=1e-12)
    # outside the swing the foot rests at the end points
    np.testing.assert_allclose(swing.sample(-0.1).position, LIFTOFF)
    np.testing.assert_allclose(swing.sample(1.0).position, TOUCHDOWN)
    np.testing.assert_allclose(swing.sample(1.0).velocity, 0.0, atol=1e-12)


def test_apex_height_is_reached_at_mid_swing():
    swing = SwingTrajectory(LIFTOFF, TOUCHDOWN, DURATION, APEX)
    times = np.linspace(0.0, DURATION, 801)
    positions, velocities, _ = samples(swing, times)
    expected_apex = max(LIFTOFF[2], TOUCHDOWN[2]) + APEX
    assert swing.apex_z == pytest.approx(expected_apex)
    assert positions[:, 2].max() == pytest.approx(expected_apex, abs=1e-12)
    assert times[np.argmax(positions[:, 2])] == pytest.approx(DURATION / 2)
    # z rises monotonically to the apex and falls to touchdown; x moves monotonically forward
    mid = len(times) // 2
    assert np.all(velocities[1:mid, 2] >= 0.0) and np.all(velocities[mid + 1:-1, 2] <= 0.0)
    assert np.all(np.diff(positions[:, 0]) >= 0.0)
    # horizontal motion is a quintic: half way in time is half way in space
    np.testing.assert_allclose(positions[mid, :2], 0.5 * (LIFTOFF[:2] + TOUCHDOWN[:2]), atol=1e-12)


def test_velocity_and_acceleration_are_consistent_with_position():
    swing = SwingTrajectory(LIFTOFF, TOUCHDOWN, DURATION, APEX)
    assert_derivatives_consistent(swing, 0.0, DURATION)


@pytest.mark.parametrize("t_retarget", [0.05, 0.13, 0.21, 0.33])
def test_retarget_is_continuous_and_ends_at_the_new_target(t_retarget: float):
    swing = SwingTrajectory(LIFTOFF, TOUCHDOWN, DURATION, APEX)
    before = swing.sample(t_retarget)
    new_target = TOUCHDOWN + np.array([0.06, -0.04, 0.05])
    swing.retarget(new_target, t_retarget)
    after = swing.sample(t_retarget)
    np.testing.assert_allclose(after.position, before.position, atol=1e-12)
    np.testing.assert_allclose(after.velocity, before.velocity, atol=1e-10)
    np.testing.assert_allclose(after.acceleration, before.acceleration, atol=1e-8)
    end = swing.sample(DURATION)
    np.testing.assert_allclose(end.position, new_target, atol=1e-12)
    np.testing.assert_allclose(end.velocity, 0.0, atol=1e-10)
    np.testing.assert_allclose(end.acceleration, 0.0, atol=1e-8)
    np.testing.assert_allclose(swing.touchdown_position, new_target)
    assert swing.retarget_count == 1
    # smooth on both sides of the retarget, no jump across it
    assert_derivatives_consistent(swing, t_retarget, DURATION)
    eps = 1e-7
    np.testing.assert_allclose(swing.sample(t_retarget - eps).position,
                               swing.sample(t_retarget + eps).position, atol=1e-6)
    # before mid-swing the apex follows the higher target; the foot never dips below the lift-off
    if DURATION / 2 - t_retarget >= 0.1 * DURATION:
        z = samples(swing, np.linspace(0.0, DURATION, 401))[0][:, 2]
        assert z.max() == pytest.approx(max(LIFTOFF[2], new_target[2]) + APEX, abs=1e-9)


def test_repeated_retargets_keep_the_history_and_stay_smooth():
    swing = SwingTrajectory(LIFTOFF, TOUCHDOWN, DURATION, APEX)
    early = swing.sample(0.02)
    target = TOUCHDOWN.copy()
    for k, t in enumerate(np.arange(0.04, 0.3, 0.004)):  # a small change every control tick
        target = target + np.array([0.0005, 0.0002, 0.0])
        before = swing.sample(t)
        swing.retarget(target, t)
        after = swing.sample(t)
        np.testing.assert_allclose(after.velocity, before.velocity, atol=1e-9, err_msg=f"retarget {k}")
    np.testing.assert_allclose(swing.sample(0.02).position, early.position)  # the past is unchanged
    np.testing.assert_allclose(swing.sample(DURATION).position, target, atol=1e-12)
    assert_derivatives_consistent(swing, 0.3, DURATION)


def test_invalid_inputs():
    with pytest.raises(MotionConfigError, match="duration_s must be > 0"):
        SwingTrajectory(LIFTOFF, TOUCHDOWN, 0.0, APEX)
    with pytest.raises(MotionConfigError, match="apex_height_m must be >= 0"):
        SwingTrajectory(LIFTOFF, TOUCHDOWN, DURATION, -0.1)
    with pytest.raises(InputError, match="touchdown_xyz must be 3 finite values"):
        SwingTrajectory(LIFTOFF, [0.0, math.nan, 0.0], DURATION, APEX)
    swing = SwingTrajectory(LIFTOFF, TOUCHDOWN, DURATION, APEX)
    with pytest.raises(InputError, match="retarget time must be in"):
        swing.retarget(TOUCHDOWN, DURATION)
    with pytest.raises(InputError, match="new_touchdown_xyz must be 3 finite values"):
        swing.retarget([1.0, 2.0], 0.1)
    with pytest.raises(InputError, match="time must be finite"):
        swing.sample(math.inf)
