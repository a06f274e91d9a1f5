"""The TCE's per-tick driver (tal_estimation.tce_driver), without ROS: the tick grid, the base state it
uses (and skips when stale), the robot state it assembles, feet outside the map and rejected input."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from tal_core.errors import InputError
from tal_core.legs import Leg
from tal_core.robot_model import RobotModel
from tal_core.state import BaseState
from tal_estimation.tce import FiniteDifferenceAcceleration, TceSettings, TerrainComplianceEstimator
from tal_estimation.tce_driver import TceDriver

MS = 1_000_000  # [ns]
G = 9.81


@cache
def model() -> RobotModel:
    return RobotModel.from_name("hyq")


@cache
def standing() -> tuple[BaseState, np.ndarray, np.ndarray]:
    """A level base at the nominal height, nominal joints and the torques holding the weight on four feet."""
    m = model()
    q = np.asarray(m.description.nominal_joint_positions_rad, float).copy()
    base = BaseState(np.array([0.0, 0.0, m.nominal_base_height_m]), np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(3),
                     np.zeros(3))
    m.update(m.make_q(base.position, base.quat_xyzw, q), np.zeros(m.nv))
    h = m.nonlinear_effects()
    grf = np.array([0.0, 0.0, m.total_mass_kg * G / 4.0])
    tau = np.concatenate([h[m.leg_joint_v_indices(leg)] + m.leg_torques_for_foot_force(leg, grf) for leg in range(4)])
    return base, q, tau


def read(calls: list[int] | None = None, k: int = 0):
    """A joint-state reader of the standing robot that records which samples were read."""
    def inner():
        if calls is not None:
            calls.append(k)
        _, q, tau = standing()
        return q, np.zeros(12), tau
    return inner


def flat(x: float, y: float) -> float:
    return 0.0


def test_ticks_fall_on_the_grid_once_base_and_terrain_are_in() -> None:
    driver = TceDriver(RobotModel.from_name("hyq"), period_s=0.004)
    base = standing()[0]
    assert driver.add_joints(0, read()) is None                  # no base, no terrain: not a tick
    driver.set_base(0, base)
    assert driver.add_joints(1 * MS, read()) is None             # no terrain yet
    driver.set_terrain(flat)
    calls: list[int] = []
    ticks = [driver.add_joints(k * MS, read(calls, k)) for k in range(2, 11)]
    assert [k for k, tick in zip(range(2, 11), ticks) if tick is not None] == [2, 4, 8]   # grid k * 4 ms
    assert calls == [2, 4, 8] and driver.ticks == 3              # only tick samples are read
    assert all(ticks[0].in_contact) and ticks[0].t_s == 2 * MS * 1e-9
    np.testing.assert_array_equal([e.samples for e in ticks[6].estimates], [3, 3, 3, 3])   # the tick at 8 ms


def test_a_stale_base_state_skips_the_tick() -> None:
    """The base state of 0 ms is too old at 16 ms (3 periods of 4 ms): the tick is skipped (counted) and the
    grid moves on; a fresh base state makes the next grid sample a tick again."""
    driver = TceDriver(RobotModel.from_name("hyq"), period_s=0.004, stale_state_periods=3)
    driver.set_terrain(flat)
    driver.set_base(0, standing()[0])
    assert driver.add_joints(12 * MS, read()) is not None        # 3 periods old: still usable
    assert driver.add_joints(16 * MS, read()) is None and driver.stale_ticks == 1
    driver.set_base(17 * MS, standing()[0])
    assert driver.add_joints(19 * MS, read()) is None            # 16 ms took the grid point: next is 20 ms
    assert driver.add_joints(20 * MS, read()) is not None and driver.ticks == 2
    driver.stale_state_periods = 1000
    driver.set_base(20 * MS, standing()[0])
    assert driver.add_joints(400 * MS, read()) is not None


def test_the_tick_assembles_the_robot_state_from_the_base_state() -> None:
    """A moving, turning base: the driver's samples are the TCE's own on q, v from the base state (angular
    velocity in the world frame) with vdot from the previous tick."""
    base, q, tau = standing()
    m = model()
    bases = [BaseState(base.position + [0.0, 0.0, -0.001 * k], np.array([0.0, 0.01 * k, 0.0, 1.0]) /
                       np.linalg.norm([0.0, 0.01 * k, 0.0, 1.0]), np.array([0.1, 0.0, -0.25]),
                       np.array([0.0, 0.2 * k, 0.05])) for k in range(3)]
    driver = TceDriver(RobotModel.from_name("hyq"), period_s=0.004)
    driver.set_terrain(flat)
    tce = TerrainComplianceEstimator(RobotModel.from_name("hyq"))
    fd = FiniteDifferenceAcceleration(max_gap_s=0.006)
    for k, b in enumerate(bases):
        qd = np.full(12, 0.1 * k)
        tick = driver.step(0.004 * k, b, q, qd, tau)
        v = m.make_v(b.linear_velocity, b.angular_velocity, qd, b.quat_xyzw)
        expected = tce.contact_states(m.make_q(b.position, b.quat_xyzw, q), v, tau, flat, vdot=fd.update(0.004 * k, v))
        estimates = tce.update(expected)
        for got, want in zip(tick.samples, expected):
            np.testing.assert_array_equal(got.force_n, want.force_n)
            assert got.penetration_m == want.penetration_m and got.penetration_rate_m_s == want.penetration_rate_m_s
        assert [e.samples for e in tick.estimates] == [e.samples for e in estimates]
    assert tick.samples[Leg.LF].penetration_rate_m_s != 0.0   # the base velocity did reach the feet


def test_feet_outside_the_map_give_no_sample() -> None:
    """Unknown heights in front of the robot: the front feet's stance samples are fed as not in contact
    (counted), the hind feet's enter their windows."""
    base, q, tau = standing()
    driver = TceDriver(RobotModel.from_name("hyq"))
    driver.set_terrain(lambda x, y: np.nan if x > 0.0 else 0.0)
    tick = driver.step(0.0, base, q, np.zeros(12), tau)
    assert driver.samples_outside_map == 2
    assert tick.in_contact.tolist() == [False, False, True, True]
    assert [e.samples for e in tick.estimates] == [0, 0, 1, 1]
    assert tick.samples[Leg.LF].penetration_m == 0.0 and tick.samples[Leg.LH].penetration_m != 0.0
    driver.set_terrain(flat)
    driver.step(0.004, base, q, np.zeros(12), tau)
    assert driver.samples_outside_map == 2 and [e.samples for e in driver.tce.estimates] == [1, 1, 2, 2]


def test_unusable_joint_states_are_rejected_and_counted() -> None:
    rejected: list[Exception] = []
    driver = TceDriver(RobotModel.from_name("hyq"), on_reject=rejected.append)
    driver.set_terrain(flat)
    driver.set_base(0, standing()[0])
    _, q, tau = standing()

    def missing_joint():
        raise InputError("joint_states lacks joints")

    assert driver.add_joints(0, missing_joint) is None
    assert driver.add_joints(4 * MS, lambda: (q, np.zeros(12), np.full(12, np.nan))) is None
    assert driver.rejected == 2 and driver.ticks == 0
    assert "lacks joints" in str(rejected[0]) and "torques" in str(rejected[1])
    with pytest.raises(InputError, match="terrain"):
        TceDriver(RobotModel.from_name("hyq")).step(0.0, standing()[0], q, np.zeros(12), tau)


def test_thresholds_change_at_run_time_the_window_does_not() -> None:
    """A contact threshold above the quarter weight (213 N) at run time: the standing feet stop feeding
    their windows from the next tick; the window length is fixed."""
    base, q, tau = standing()
    driver = TceDriver(RobotModel.from_name("hyq"))
    driver.set_terrain(flat)
    assert all(driver.step(0.0, base, q, np.zeros(12), tau).in_contact)
    driver.reconfigure(TceSettings(contact_force_threshold_n=300.0))
    tick = driver.step(0.004, base, q, np.zeros(12), tau)
    assert not any(tick.in_contact) and [e.samples for e in tick.estimates] == [1, 1, 1, 1]
    with pytest.raises(InputError, match="window"):
        driver.reconfigure(TceSettings(window=100, min_samples=10))
