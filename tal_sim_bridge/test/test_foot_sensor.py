"""The feet's contact sensors (tal_sim_bridge.foot_sensor): a reading comes a sample late with its noise, the
flag turns on at the threshold and off below the release level, and the same seed gives the same readings."""

from __future__ import annotations

import numpy as np
import pytest

from tal_sim_bridge.errors import BridgeConfigError
from tal_sim_bridge.foot_sensor import FootForceSensor, FootSensorSettings


def loads(*normal_forces: float) -> list[np.ndarray]:
    return [np.array([0.0, 0.0, f]) for f in normal_forces]


def test_a_reading_comes_one_sample_late_and_the_flag_has_hysteresis() -> None:
    sensor = FootForceSensor(FootSensorSettings(delay_samples=1, noise_std_n=0.0, threshold_n=50.0,
                                                hysteresis_fraction=0.3))
    readings, flags = sensor.measure(loads(0, 0, 200, 400))
    np.testing.assert_array_equal(readings, [0, 0, 200, 400])   # the first sample: nothing older to report
    readings, flags = sensor.measure(loads(60, 0, 40, 400))
    np.testing.assert_array_equal(readings, [0, 0, 200, 400])   # a sample late
    assert flags.tolist() == [False, False, True, True]
    readings, flags = sensor.measure(loads(60, 49, 30, 0))
    np.testing.assert_array_equal(readings, [60, 0, 40, 400])
    assert flags.tolist() == [True, False, True, True]          # 40 N is above the release level (35 N)
    readings, flags = sensor.measure(loads(0, 0, 0, 0))
    assert flags.tolist() == [True, False, False, False]        # 49 N: not yet on; 30 N: off; 0: off


def test_noise_is_seeded_and_light_touches_are_missed() -> None:
    settings = FootSensorSettings(delay_samples=0, noise_std_n=5.0, threshold_n=50.0, seed=3)
    a, b = FootForceSensor(settings), FootForceSensor(settings)
    runs = [[sensor.measure(loads(30, 30, 300, 300)) for _ in range(200)] for sensor in (a, b)]
    readings = np.array([r for r, _ in runs[0]])
    np.testing.assert_array_equal(readings, np.array([r for r, _ in runs[1]]))
    assert readings[:, 2].std() == pytest.approx(5.0, rel=0.2)
    assert not any(flags[0] for _, flags in runs[0])            # 30 N under 50 N with 5 N of noise
    assert all(flags[2] for _, flags in runs[0])


def test_invalid_settings_are_refused_by_name() -> None:
    with pytest.raises(BridgeConfigError, match="delay_samples"):
        FootSensorSettings(delay_samples=-1)
    with pytest.raises(BridgeConfigError, match="noise_std_n"):
        FootSensorSettings(noise_std_n=float("nan"))
    with pytest.raises(BridgeConfigError, match="hysteresis_fraction"):
        FootSensorSettings(hysteresis_fraction=1.0)
