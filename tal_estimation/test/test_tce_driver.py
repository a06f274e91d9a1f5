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


@pytest.mark.parametrize("average_torque", [False, True])
def test_ticks_fall_on_the_grid_once_base_and_terrain_are_in(average_torque: bool) -> None:
    driver = TceDriver(RobotModel.from_name("hyq"), period_s=0.004, average_torque=average_torque)
    base = standing()[0]
    assert driver.add_joints(0, read()) is None                  # no base, no terrain: not a tick
    driver.set_base(0, base)
    assert driver.add_joints(1 * MS, read()) is None             # no terrain yet
    driver.set_terrain(flat)
    calls: list[int] = []
    ticks = [driver.add_joints(k * MS, read(calls, k)) for k in range(2, 11)]
    assert [k for k, tick in zip(range(2, 11), ticks) if tick is not None] == [2, 4, 8]   # grid k * 4 ms
    # Only tick samples are read, or every sample for its torque (averaged over the interval).
    assert calls == (list(range(2, 11)) if average_torque else [2, 4, 8]) and driver.ticks == 3
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


def test_a_tick_waits_for_the_base_state_of_its_stamp_in_any_arrival_order() -> None:
    """base_period_s: the tick at 4 ms uses the base state of 4 ms whether it arrives before or after the joint
    state, so a lockstep run does not depend on DDS delivery order."""
    base, q, tau = standing()
    bases = {k: BaseState(base.position + [0.0, 0.0, -0.0005 * k], base.quat_xyzw, np.zeros(3), np.zeros(3))
             for k in range(0, 13, 4)}
    results = []
    for base_first in (True, False):
        driver = TceDriver(RobotModel.from_name("hyq"), period_s=0.004, base_period_s=0.004)
        driver.set_terrain(flat)
        ticks = []
        for k in range(13):
            events = [("joints", k)] + ([("base", k)] if k in bases else [])
            for kind, stamp in (events[::-1] if base_first else events):
                new = ([driver.add_joints(stamp * MS, read())] if kind == "joints"
                       else driver.set_base(stamp * MS, bases[stamp]))
                ticks += [tick for tick in new if tick is not None]
        assert driver.late_base_ticks == 0
        results.append([(t.stamp_ns, t.samples[Leg.LF].penetration_m) for t in ticks])
    assert [stamp for stamp, _ in results[0]] == [0, 4 * MS, 8 * MS, 12 * MS]
    assert results[0] == results[1]
    assert results[0][1][1] == pytest.approx(results[0][0][1] + 0.002)  # 4 ms: the base 2 mm lower


def test_the_next_tick_waits_behind_a_waiting_one_and_each_takes_the_base_state_of_its_own_stamp() -> None:
    """The sample of 4 ms comes before the base state of 0 ms (another topic): the tick of 4 ms queues behind the
    tick of 0 ms, and when the base states come each tick takes its own, as when they come in time, so a lockstep
    run does not depend on the order; a third waiting tick runs the oldest with what is there."""
    base, q, tau = standing()
    bases = {k: BaseState(base.position + [0.0, 0.0, -0.0005 * k], base.quat_xyzw, np.zeros(3), np.zeros(3))
             for k in (0, 4)}
    results = []
    for late_base in (False, True):
        driver = TceDriver(RobotModel.from_name("hyq"), period_s=0.004, base_period_s=0.004, max_defer_s=0.004)
        driver.set_terrain(flat)
        assert driver.add_joints(0, read()) is None
        ticks = []
        if late_base:   # the base state of 0 ms comes after the next tick's sample
            assert driver.add_joints(4 * MS, read()) is None      # 4 ms is not past the 0 ms tick's wait
            ticks += driver.set_base(0, bases[0])
        else:
            ticks += driver.set_base(0, bases[0])
            ticks.append(driver.add_joints(4 * MS, read()))
        ticks += driver.set_base(4 * MS, bases[4])
        ticks = [t for t in ticks if t is not None]
        assert [t.stamp_ns for t in ticks] == [0, 4 * MS] and driver.late_base_ticks == 0
        results.append([t.samples[Leg.LF].penetration_m for t in ticks])
    assert results[0] == results[1]
    assert results[0][1] == pytest.approx(results[0][0] + 0.002)   # each tick on its own base state
    driver = TceDriver(RobotModel.from_name("hyq"), period_s=0.004, base_period_s=0.004, max_defer_s=0.1)
    driver.set_terrain(flat)
    driver.set_base(0, bases[0])
    assert driver.add_joints(0, read()) is not None
    assert driver.add_joints(4 * MS, read()) is None and driver.add_joints(8 * MS, read()) is None
    late = driver.add_joints(12 * MS, read())                     # a third would wait: the oldest runs now
    assert late is not None and late.stamp_ns == 4 * MS and driver.late_base_ticks == 1


def test_a_waiting_tick_runs_late_when_the_robot_moves_on() -> None:
    """The base state of 4 ms never comes: the next joint sample past max_defer_s computes the tick on the
    latest base state there is (counted); an estimate grid of 3 ms: the tick at 8 ms waits for the estimate
    of 6 ms."""
    base = standing()[0]
    driver = TceDriver(RobotModel.from_name("hyq"), period_s=0.004, base_period_s=0.004, max_defer_s=0.002)
    driver.set_terrain(flat)
    driver.set_base(0, base)
    assert driver.add_joints(0, read()) is not None
    assert driver.add_joints(4 * MS, read()) is None
    assert driver.wants_joints(5 * MS) and driver.add_joints(5 * MS, read()) is None   # a torque sample
    assert driver.add_joints(6 * MS, read()) is None  # 2 ms: still waiting
    assert driver.wants_joints(7 * MS)
    late = driver.add_joints(7 * MS, read())
    assert late is not None and late.stamp_ns == 4 * MS and driver.late_base_ticks == 1
    estimate = TceDriver(RobotModel.from_name("hyq"), period_s=0.004, base_period_s=0.003)
    estimate.set_terrain(flat)
    estimate.set_base(3 * MS, base)
    assert estimate.add_joints(8 * MS, read()) is None  # waits for the estimate of 6 ms
    assert [t.stamp_ns for t in estimate.set_base(6 * MS, base)] == [8 * MS]
    with pytest.raises(InputError, match="base_period_s must be > 0"):
        TceDriver(RobotModel.from_name("hyq"), base_period_s=0.0)


def test_a_waiting_tick_is_answered_when_the_next_one_is_due() -> None:
    """max_defer_s of a whole period (the lockstep tour's): the tick of 4 ms still waits for its estimate when
    the sample of 8 ms makes the next tick due. The 8 ms tick waits behind it, and each is answered when its own
    estimate comes, oldest first (replacing the waiting one unanswered left the estimator waiting for it and the
    TCE for the estimator, a lockstep stall; answering it with the base state there was made runs differ). A
    tick whose estimate does not come is answered on the first sample past max_defer_s."""
    base = standing()[0]
    driver = TceDriver(RobotModel.from_name("hyq"), period_s=0.004, base_period_s=0.003, max_defer_s=0.004)
    driver.set_terrain(flat)
    driver.set_base(0, base)
    assert [t.stamp_ns for t in driver.add_joints_all(0, read())] == [0]
    assert driver.add_joints_all(4 * MS, read()) == []              # waits for the estimate of 3 ms
    assert driver.add_joints_all(8 * MS, read()) == []              # waits behind it (the estimate of 6 ms)
    assert [t.stamp_ns for t in driver.set_base(3 * MS, base)] == [4 * MS]
    assert [t.stamp_ns for t in driver.set_base(6 * MS, base)] == [8 * MS]
    assert driver.late_base_ticks == 0
    driver.set_base(9 * MS, base)
    assert driver.add_joints_all(12 * MS, read()) == []               # waits for the estimate of 12 ms
    late = driver.add_joints_all(17 * MS, read())                     # overdue: answered on the 9 ms estimate
    assert [t.stamp_ns for t in late] == [12 * MS] and driver.late_base_ticks == 1


def test_with_the_heightmap_period_a_tick_waits_for_the_map_of_its_grid_point() -> None:
    """Maps every 8 ms, streamed: the tick at 8 ms uses the map of 8 ms whether it arrives before or after the
    joint state (the maps differ by 1 mm here, as robot-centred maps differ under a foot); a map that comes after
    its tick is late (counted), and a tick whose map never comes runs late on the next sample past max_defer_s."""
    base = standing()[0]
    results = []
    for map_first in (True, False):
        driver = TceDriver(RobotModel.from_name("hyq"), period_s=0.004, base_period_s=0.004, heightmap_period_s=0.008)
        ticks = []
        for k in range(13):
            events = [("joints", k)] + ([("base", k)] if k % 4 == 0 else []) + ([("map", k)] if k % 8 == 0 else [])
            for kind, stamp in (events[::-1] if map_first else events):
                if kind == "joints":
                    new = [driver.add_joints(stamp * MS, read())]
                elif kind == "base":
                    new = driver.set_base(stamp * MS, base)
                else:
                    new = driver.add_heightmap(stamp * MS, lambda x, y, h=-0.001 * stamp / 8: h)
                ticks += [tick for tick in new if tick is not None]
        assert driver.late_heightmaps == 0 and driver.late_heightmap_ticks == 0
        results.append([(t.stamp_ns, t.samples[Leg.LF].penetration_m) for t in ticks])
    assert [stamp for stamp, _ in results[0]] == [0, 4 * MS, 8 * MS, 12 * MS]
    assert results[0] == results[1]
    assert results[0][2][1] == pytest.approx(results[0][1][1] - 0.001)  # 8 ms: on the map of 8 ms
    lost = TceDriver(RobotModel.from_name("hyq"), period_s=0.004, base_period_s=0.004, max_defer_s=0.002,
                     heightmap_period_s=0.008)
    lost.set_base(0, base)
    lost.add_heightmap(0, flat)
    assert lost.add_joints(0, read()) is not None
    lost.set_base(8 * MS, base)
    assert lost.add_joints(8 * MS, read()) is None  # waits for the map of 8 ms
    assert lost.add_joints(11 * MS, read()) is not None and lost.late_heightmap_ticks == 1
    lost.add_heightmap(8 * MS, flat)
    assert lost.late_heightmaps == 1
    with pytest.raises(InputError, match="heightmap_period_s"):
        TceDriver(RobotModel.from_name("hyq"), heightmap_period_s=-1.0)


def test_a_tick_after_a_long_gap_does_not_feed_the_fit() -> None:
    """Accelerations are finite-differenced across one lost tick; after a longer gap they are unknown (the force
    would be its static part only, and a swing leg could read as loaded): the tick leaves the windows alone."""
    base, q, tau = standing()
    driver = TceDriver(RobotModel.from_name("hyq"), period_s=0.004)
    driver.set_terrain(flat)
    for t in (0.0, 0.004, 0.012):           # the first tick, the next, one tick lost: all feed the fit
        driver.step(t, base, q, np.zeros(12), tau)
    assert [e.samples for e in driver.tce.estimates] == [3, 3, 3, 3] and driver.ticks_without_acceleration == 0
    before = [e.samples for e in driver.step(0.030, base, q, np.zeros(12), tau).estimates]   # 4.5 periods later
    assert before == [3, 3, 3, 3] and driver.ticks_without_acceleration == 1
    tick = driver.step(0.034, base, q, np.zeros(12), tau)                                   # consecutive again
    assert [e.samples for e in tick.estimates] == [4, 4, 4, 4] and driver.ticks == 5


def test_a_tick_takes_the_mean_torque_of_its_interval() -> None:
    """The command changes within the 4 ms before the tick at 8 ms (on the wall clock it arrives whenever the
    controller is done): the torques of 5 and 6 ms are 20 N m below the holding torque, those of 7 and 8 ms
    20 N m above. The legs' accelerations are finite-differenced over the interval, so the tick takes the
    interval's mean torque: the feet's forces are those of the holding torque, not of the last sample's."""
    base, q, tau = standing()
    step = np.full(12, 20.0)

    def forces(torques: dict[int, np.ndarray], average_torque: bool) -> np.ndarray:
        driver = TceDriver(RobotModel.from_name("hyq"), period_s=0.004, average_torque=average_torque)
        driver.set_terrain(flat)
        driver.set_base(0, base)
        tick = None
        for k in range(9):
            sample = torques.get(k, tau)
            tick = driver.add_joints(k * MS, lambda sample=sample: (q, np.zeros(12), sample)) or tick
        assert tick is not None and tick.stamp_ns == 8 * MS
        return np.array([s.force_n for s in tick.samples])

    switching = {5: tau - step, 6: tau - step, 7: tau + step, 8: tau + step}
    held = forces({}, True)
    np.testing.assert_allclose(forces(switching, True), held, rtol=1e-12, atol=1e-9)
    last_only = forces(switching, False)
    np.testing.assert_allclose(last_only, forces({8: tau + step}, False), rtol=1e-12, atol=1e-9)
    assert np.max(np.abs(last_only - held)) > 10.0   # the last sample alone: tens of newtons off
    # A command held over the interval: exactly the last sample's torque (lockstep runs stay bit for bit).
    same = {k: tau + step for k in range(5, 9)}
    assert np.array_equal(forces(same, True), forces(same, False))
