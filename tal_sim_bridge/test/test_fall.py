"""Fall detection without ROS (tal_sim_bridge.fall): confirmation, onset, links, the height bound, and the
detector fed by BridgeCore on a real simulation (a collapse is a fall, standing is not)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tal_core.robot_description import load_robot_description
from tal_core.robot_model import RobotModel
from tal_core.terrain import load_course
from tal_sim_bridge.bridge_core import BridgeCore
from tal_sim_bridge.errors import BridgeConfigError
from tal_sim_bridge.fall import DEFAULT_MIN_HEIGHT_RATIO, NO_FALL_SUMMARY, FallDetector
from tal_sim_bridge.physics import Simulation

DT = 0.004  # [s] the contact rate's period
UP = (1.0, 0.0, 0.55)  # base origin [m] of a robot standing on flat ground at z = 0


def feed(detector: FallDetector, samples) -> list:
    """samples: (t, base position, terrain height, links); returns what each update returned."""
    return [detector.update(t, p, h, links) for t, p, h, links in samples]


def test_a_graze_shorter_than_the_confirmation_time_is_not_a_fall() -> None:
    detector = FallDetector(min_base_height_m=0.35, confirm_s=0.2)
    samples = [(k * DT, UP, 0.0, ["lf_upperleg"] if 10 <= k < 50 else []) for k in range(200)]  # 0.16 s graze
    assert feed(detector, samples) == [None] * 200
    assert detector.fall is None
    assert detector.summary() == NO_FALL_SUMMARY


def test_held_body_contact_is_a_fall_dated_and_placed_at_its_onset() -> None:
    detector = FallDetector(min_base_height_m=0.35, confirm_s=0.2)
    samples = []
    for k in range(200):
        t = k * DT
        links = [] if k < 100 else (["lf_upperleg"] if k < 120 else ["lf_upperleg", "trunk"])
        samples.append((t, (1.0 + t, 0.1, 0.55 - 0.1 * max(0.0, t - 0.4)), 0.0, links))
    results = feed(detector, samples)
    confirmed = [k for k, r in enumerate(results) if r is not None]
    assert confirmed == [150]  # onset at sample 100 (0.4 s), held 0.2 s: confirmed at 0.6 s, returned once
    fall = detector.fall
    assert fall is results[150]
    assert fall.time_s == pytest.approx(0.4) and fall.confirmed_s == pytest.approx(0.6)
    assert fall.position_m == pytest.approx((1.4, 0.1, 0.55))
    assert fall.links == ("lf_upperleg", "trunk")  # every link on the ground while it held
    assert fall.reason == "body-ground contact"
    summary = detector.summary()
    assert summary["fell"] is True and summary["fall_time_s"] == pytest.approx(0.4)
    assert summary["fall_position_m"] == [1.4, 0.1, 0.55] and summary["fall_links"] == ["lf_upperleg", "trunk"]
    assert "t = 0.400 s" in fall.describe() and "trunk" in fall.describe()


def test_a_break_in_the_condition_restarts_the_confirmation() -> None:
    detector = FallDetector(min_base_height_m=0.35, confirm_s=0.1)
    links = lambda k: [] if k == 20 else ["trunk"]  # noqa: E731  one clear sample at 0.08 s
    results = feed(detector, [(k * DT, UP, 0.0, links(k)) for k in range(100)])
    assert [k for k, r in enumerate(results) if r is not None] == [46]  # 21 + 25 samples (0.1 s)
    assert detector.fall.time_s == pytest.approx(21 * DT)


def test_a_low_base_over_the_terrain_under_it_is_a_fall() -> None:
    detector = FallDetector(min_base_height_m=0.35, confirm_s=0.0)
    # 0.5 m above a 0.4 m step: z = 0.9 is fine; z = 0.7 is 0.3 m above it.
    assert detector.update(0.0, (6.0, 0.0, 0.9), 0.4, []) is None
    fall = detector.update(0.004, (6.0, 0.0, 0.7), 0.4, [])
    assert fall is not None and fall.links == () and fall.base_height_m == pytest.approx(0.3)
    assert fall.reason == "base 0.300 m above the terrain, below the bound 0.350 m"
    assert detector.update(0.008, (6.0, 0.0, 0.0), 0.4, ["trunk"]) is None  # the first fall is the run's


def test_leaving_the_course_is_a_fall_and_a_zero_bound_switches_the_height_criterion_off() -> None:
    off = FallDetector(min_base_height_m=0.0, confirm_s=0.0)
    assert off.update(0.0, (1.0, 0.0, 0.05), 0.0, []) is None  # lying low counts only with a bound
    fall = off.update(0.004, (99.0, 0.0, 0.55), math.nan, [])
    assert fall is not None and fall.reason == "no terrain under the base (off the course)"
    assert math.isnan(fall.base_height_m)


def test_the_bound_is_a_fraction_of_the_nominal_height_and_settings_are_checked() -> None:
    assert FallDetector.for_robot(0.5).min_base_height_m == pytest.approx(DEFAULT_MIN_HEIGHT_RATIO * 0.5)
    assert FallDetector.for_robot(0.5, 0.5, 0.3).confirm_s == 0.3
    with pytest.raises(BridgeConfigError, match="min_base_height_m must be finite and >= 0"):
        FallDetector(-0.1)
    with pytest.raises(BridgeConfigError, match="confirm_s must be finite and >= 0"):
        FallDetector(0.3, confirm_s=math.nan)
    with pytest.raises(BridgeConfigError, match="nominal base height must be > 0"):
        FallDetector.for_robot(0.0)
    with pytest.raises(BridgeConfigError, match=r"min_height_ratio must be in \[0, 1\]"):
        FallDetector.for_robot(0.5, 1.5)


# --- on the simulation, through BridgeCore ----------------------------------------------------------------
@pytest.fixture(scope="module")
def description():
    return load_robot_description("hyq")


def test_the_nominal_base_height_comes_from_the_robot_description(description) -> None:
    sim = Simulation(description, load_course("flat_rigid"))
    try:
        assert sim.nominal_base_height_m == pytest.approx(RobotModel(description).nominal_base_height_m, abs=1e-6)
        assert sim.base_pose()[0][2] == pytest.approx(sim.nominal_base_height_m, abs=1e-6)  # reset on flat ground
    finally:
        sim.close()


def run_core(description, course: str, steps: int, *, stand: bool, drop_height_m: float = 0.0) -> BridgeCore:
    """Step a BridgeCore, feeding its statistics (and fall detector) every 4 steps as the node does."""
    from tal_control.stand_hold import StandHold

    sim = Simulation(description, load_course(course))
    if drop_height_m:
        sim.reset(drop_height_m=drop_height_m)
    core = BridgeCore(sim)
    hold = StandHold(RobotModel(description), 1500.0, 40.0) if stand else None
    try:
        for k in range(steps):
            if hold is not None and k % 4 == 0:
                f = hold.command(sim.joint_state()[0])
                core.commands.submit(k * 1_000_000, description.joint_names, f["effort"], f["position"],
                                     f["velocity"], f["kp"], f["kd"])
            state = core.step()
            if k % 4 == 3:
                core.record_statistics(state, sim.foot_contacts())
        return core
    finally:
        sim.close()


@pytest.mark.slow
def test_a_robot_collapsing_without_torque_falls_and_the_summary_says_when(description) -> None:
    core = run_core(description, "flat_t4", 1500, stand=False, drop_height_m=0.05)
    fall = core.fall
    assert fall is not None
    print(f"\ncollapse: {fall.describe()}")
    assert 0.1 < fall.time_s < 1.2 and fall.confirmed_s == pytest.approx(fall.time_s + 0.2, abs=0.005)
    assert fall.position_m[2] < 0.6 * core.sim.nominal_base_height_m + 0.01
    summary = core.summary(1.0)
    assert summary["fell"] is True and summary["fall_time_s"] == pytest.approx(fall.time_s)
    assert summary["robot"] == "hyq"


@pytest.mark.slow
def test_a_standing_robot_does_not_fall(description) -> None:
    core = run_core(description, "flat_t1", 1500, stand=True)
    assert core.fall is None
    assert core.summary(1.0)["fell"] is False
    assert np.isfinite(core.summary(1.0)["base_height_m"])
