"""HeightmapAligner: the z offset between a world heightmap and a drifting state estimate."""

from __future__ import annotations

import numpy as np
import pytest

from tal_control.map_alignment import HeightmapAligner
from tal_core.errors import InputError

RADIUS = 0.02


def ramp_map(x: float, y: float) -> float:
    """A 10 % slope along x, NaN (unmapped) beyond x = 5 m."""
    return 0.1 * x if x < 5.0 else float("nan")


def feet(drift_z: float, x0: float = 0.0) -> np.ndarray:
    """Four feet standing on the ramp, seen by an estimate whose z is off by ``drift_z``."""
    xy = np.array([[x0 + 0.4, 0.3], [x0 + 0.4, -0.3], [x0 - 0.4, 0.3], [x0 - 0.4, -0.3]])
    z = np.array([ramp_map(x, y) for x, y in xy]) + RADIUS + drift_z
    return np.column_stack([xy, z])


def test_the_offset_follows_a_slow_estimator_drift_so_the_aligned_map_matches_the_feet():
    aligner = HeightmapAligner(time_constant_s=0.5, max_rate_m_s=0.05)
    loaded = np.ones(4)
    for k in range(2500):  # 10 s at 250 Hz, drift -0.01 m/s (HyQ's estimate on foam sank at this order)
        t = k * 0.004
        aligner.update(t, feet(-0.01 * t), loaded, RADIUS, ramp_map)
    assert aligner.offset_m == pytest.approx(-0.1, abs=0.006)  # lag = rate x tau = 5 mm
    aligned = aligner.aligned(ramp_map)
    foot = feet(-0.1)[0]
    assert aligned(foot[0], foot[1]) == pytest.approx(foot[2] - RADIUS, abs=0.006)


def test_swing_and_loading_feet_and_unmapped_feet_do_not_move_the_offset():
    aligner = HeightmapAligner(time_constant_s=0.1)
    positions = feet(0.0)
    positions[0, 2] += 0.15  # a foot in swing, 15 cm up
    positions[1, 2] += 0.05  # a foot still loading
    aligner.update(0.0, positions, np.array([0.0, 0.5, 1.0, 1.0]), RADIUS, ramp_map)
    assert aligner.offset_m == pytest.approx(0.0, abs=1e-12)
    unmapped = feet(0.3, x0=10.0)
    assert aligner.update(0.5, unmapped, np.ones(4), RADIUS, ramp_map) == pytest.approx(0.0, abs=1e-12)


def test_the_offset_rate_is_bounded_and_time_going_backwards_resets_it():
    aligner = HeightmapAligner(time_constant_s=0.01, max_rate_m_s=0.05)
    aligner.update(0.0, feet(0.0), np.ones(4), RADIUS, ramp_map)
    aligner.update(1.0, feet(0.5), np.ones(4), RADIUS, ramp_map)  # an unmapped 0.5 m step under all feet
    assert aligner.offset_m == pytest.approx(0.05)
    aligner.update(0.5, feet(0.2), np.ones(4), RADIUS, ramp_map)
    assert aligner.offset_m == pytest.approx(0.2)  # restarted from the new residual
    assert aligner.updates == 1


@pytest.mark.parametrize("kwargs", [{"time_constant_s": 0.0}, {"max_rate_m_s": float("nan")},
                                    {"load_threshold": 0.0}, {"load_threshold": 1.5}])
def test_invalid_settings_are_refused(kwargs):
    with pytest.raises(InputError):
        HeightmapAligner(**kwargs)
