"""tal_estimation.joint_velocity: causal joint velocities from positions on jittered stamps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tal_core.errors import InputError
from tal_estimation.joint_velocity import JointVelocityFilter


def jittered_stamps(n: int, period_s: float = 0.002, jitter_s: float = 3e-4, seed: int = 0) -> np.ndarray:
    return period_s * np.arange(n) + np.random.default_rng(seed).uniform(-jitter_s, jitter_s, n)


def test_a_ramp_gives_its_slope_on_jittered_stamps() -> None:
    slope = np.array([0.5, -1.0, 2.0])
    f = JointVelocityFilter(cutoff_hz=40.0)
    stamps = jittered_stamps(200)
    outputs = [f.update(t, slope * t) for t in stamps]
    np.testing.assert_array_equal(outputs[0], 0.0)  # the first sample has nothing to difference
    np.testing.assert_allclose(outputs[-1], slope, rtol=1e-9)


def test_a_step_in_velocity_is_low_passed_with_the_cut_off() -> None:
    """After one time constant 1 / (2 pi f_c) the output has covered 1 - 1/e of a velocity step."""
    cutoff = 10.0
    f = JointVelocityFilter(cutoff_hz=cutoff)
    dt = 1e-4
    f.update(0.0, np.zeros(1))
    tau = 1.0 / (2.0 * math.pi * cutoff)
    t = 0.0
    while t < tau - 1e-12:
        t += dt
        out = f.update(t, np.array([t]))  # velocity 1 from t = 0
    assert out[0] == pytest.approx(1.0 - math.exp(-1.0), abs=2e-3)


def test_a_sine_is_tracked_with_a_small_lag() -> None:
    amplitude, frequency = 0.05, 1.0
    stamps = jittered_stamps(1500)
    f = JointVelocityFilter(cutoff_hz=40.0)
    errors = []
    for t in stamps:
        v = f.update(t, np.array([amplitude * math.sin(2 * math.pi * frequency * t)]))[0]
        if t > 0.5:
            errors.append(v - amplitude * 2 * math.pi * frequency * math.cos(2 * math.pi * frequency * t))
    assert max(abs(e) for e in errors) < 0.02  # of an amplitude of 0.31 rad/s


def test_a_gap_or_a_stamp_that_does_not_advance_restarts() -> None:
    f = JointVelocityFilter(cutoff_hz=40.0, max_gap_s=0.05)
    for k in range(50):
        f.update(0.002 * k, np.array([0.002 * k]))
    np.testing.assert_array_equal(f.update(1.0, np.array([5.0])), 0.0)  # after a gap: not (5 - 0.1) / 0.9
    np.testing.assert_array_equal(f.update(1.0, np.array([6.0])), 0.0)  # same stamp again


def test_invalid_cut_off_is_rejected() -> None:
    with pytest.raises(InputError, match="cutoff_hz > 0"):
        JointVelocityFilter(cutoff_hz=0.0)
