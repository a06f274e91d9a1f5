"""The state estimator's streaming tick (tal_estimation.streaming), without ROS: the grid, the IMU window,
pairing by stamp in any arrival order, the pending tick, restarts, rejections and duplicates. Estimates are
compared bit for bit with a StateEstimator fed by hand."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from tal_core.errors import InputError
from tal_core.robot_model import RobotModel
from tal_estimation.leg_odometry import LegImpedance
from tal_estimation.live_settings import with_field
from tal_estimation.state_estimator import StateEstimate, StateEstimator
from tal_estimation.streaming import CLOCK_RESET_NS, EstimatorOutput, StreamingEstimator

MS = 1_000_000  # [ns]
G = 9.81


@cache
def model() -> RobotModel:
    return RobotModel.from_name("hyq")


@cache
def standing() -> tuple[np.ndarray, np.ndarray]:
    """Nominal joint positions and the torques holding the weight on four feet."""
    m = model()
    q = np.asarray(m.description.nominal_joint_positions_rad, float).copy()
    m.update(m.make_q(np.array([0.0, 0.0, m.nominal_base_height_m]), np.array([0.0, 0.0, 0.0, 1.0]), q),
             np.zeros(m.nv))
    h = m.nonlinear_effects()
    grf = np.array([0.0, 0.0, m.total_mass_kg * G / 4.0])
    tau = np.concatenate([h[m.leg_joint_v_indices(leg)] + m.leg_torques_for_foot_force(leg, grf) for leg in range(4)])
    return q, tau


def imu(k: int) -> tuple[np.ndarray, np.ndarray]:
    """A distinct IMU sample per millisecond k, so a wrong window shows in the estimate."""
    return (np.array([0.02 * np.sin(k), 0.03 * np.cos(k), G + 0.05 * np.sin(0.7 * k)]),
            np.array([1e-3 * np.cos(k), 2e-3 * np.sin(k), 1e-3 * np.sin(0.3 * k)]))


def joints(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    q, tau = standing()
    return q + 1e-3 * np.sin(k + np.arange(12)), np.full(12, 1e-3 * np.cos(k)), tau


def add_imu(stream: StreamingEstimator, k: int) -> list[EstimatorOutput]:
    return stream.add_imu(k * MS, *imu(k))


def add_joints(stream: StreamingEstimator, k: int) -> list[EstimatorOutput]:
    return stream.add_joints(k * MS, lambda: joints(k))


def paired(stream: StreamingEstimator, ks) -> list[EstimatorOutput]:
    out: list[EstimatorOutput] = []
    for k in ks:
        out += add_imu(stream, k) + add_joints(stream, k)
    return out


def estimates(outputs: list[EstimatorOutput]) -> dict[int, StateEstimate]:
    return {o.stamp_ns: o.estimate for o in outputs if o.kind == "estimate"}


def by_hand(start_ms: int, ticks: list[tuple[int, list[int]]]) -> dict[int, StateEstimate]:
    """A StateEstimator initialised standing at start_ms, updated at each (tick ms, IMU sample ms list)
    with the mean of those IMU samples and the joint state of the tick."""
    estimator = StateEstimator(model())
    estimator.initialise_standing(start_ms * MS * 1e-9, joints(start_ms)[0], (0.0, 0.0))
    out = {}
    for tick, window in ticks:
        f = np.mean([imu(k)[0] for k in window], axis=0)
        w = np.mean([imu(k)[1] for k in window], axis=0)
        out[tick * MS] = estimator.update(tick * MS * 1e-9, f, w, *joints(tick))
    return out


def assert_same(actual: dict[int, StateEstimate], expected: dict[int, StateEstimate]) -> None:
    assert list(actual) == list(expected)
    for stamp in expected:
        for field in ("position", "quat_xyzw", "linear_velocity", "gyro_bias", "position_covariance"):
            np.testing.assert_array_equal(getattr(actual[stamp], field), getattr(expected[stamp], field),
                                          err_msg=f"{field} at {stamp / MS} ms")


def test_ticks_fall_on_the_grid_with_the_mean_of_the_imu_window() -> None:
    """Started at 1 ms, the 3 ms grid is k * 3 ms (not relative to the start): ticks at 3, 6, 9 ms, each on
    the mean of the IMU samples since the previous tick (the sample of the start initialises only)."""
    stream = StreamingEstimator(model())
    out = paired(stream, range(1, 11))
    assert [(o.kind, o.stamp_ns // MS) for o in out] == [("initial", 1), ("estimate", 3), ("estimate", 6),
                                                        ("estimate", 9)]
    assert_same(estimates(out), by_hand(1, [(3, [2, 3]), (6, [4, 5, 6]), (9, [7, 8, 9])]))
    assert stream.ticks == 3 and not stream.rejections


def test_a_wrong_window_would_show() -> None:
    """Control for the test above: including the initial sample in the first window changes the estimate."""
    stream = StreamingEstimator(model())
    with pytest.raises(AssertionError):
        assert_same(estimates(paired(stream, range(1, 4))), by_hand(1, [(3, [1, 2, 3])]))


def test_joint_and_imu_samples_pair_by_stamp_in_any_order() -> None:
    """The joint sample of a tick waits (pending) for the IMU sample of its stamp and vice versa: joints
    first, IMU first or the IMU a sample late all give the paired stream's estimates."""
    reference = estimates(paired(StreamingEstimator(model()), range(0, 13)))
    joints_first = StreamingEstimator(model())
    out: list[EstimatorOutput] = []
    for k in range(0, 13):
        out += add_joints(joints_first, k)
        if k == 3:
            assert estimates(out) == {}  # pending: the IMU sample of 3 ms has not come
        out += add_imu(joints_first, k)
    assert_same(estimates(out), reference)

    imu_late = StreamingEstimator(model())
    out = add_joints(imu_late, 0)
    for k in range(1, 13):
        out += add_joints(imu_late, k) + add_imu(imu_late, k - 1)
    out += add_imu(imu_late, 12)
    assert_same(estimates(out), reference)


def test_a_pending_tick_runs_with_what_arrived() -> None:
    """The IMU sample of 3 ms is lost: the 3 ms tick runs when a later IMU sample shows it will not come,
    on the samples it has (1, 2 ms); if no IMU comes at all, the next grid sample (6 ms) releases it."""
    stream = StreamingEstimator(model())
    out = paired(stream, range(0, 3)) + add_joints(stream, 3)
    assert estimates(out) == {}
    out += add_imu(stream, 4)
    assert_same(estimates(out), by_hand(0, [(3, [1, 2])]))

    silent = StreamingEstimator(model())
    out = paired(silent, range(0, 3)) + add_joints(silent, 3) + add_joints(silent, 4) + add_joints(silent, 5)
    assert estimates(out) == {}
    out += add_joints(silent, 6)
    assert_same(estimates(out), by_hand(0, [(3, [1, 2])]))
    out += add_imu(silent, 6)   # the 6 ms sample is pending in turn
    assert_same(estimates(out), by_hand(0, [(3, [1, 2]), (6, [6])]))


def test_out_of_order_and_bad_imu_samples_are_rejected_and_counted() -> None:
    stream = StreamingEstimator(model())
    out = paired(stream, range(0, 5))
    out += add_imu(stream, 3)                                   # backwards by 2 ms: out of order
    out += stream.add_imu(5 * MS, np.array([np.nan, 0.0, G]), np.zeros(3))
    out += stream.add_imu(5 * MS, np.array([0.0, 0.0, 500.0]), np.zeros(3))
    out += add_imu(stream, 5) + add_joints(stream, 5) + paired(stream, [6])
    assert dict(stream.rejections) == {"imu_out_of_order": 1, "imu_nan": 1, "imu_saturated": 1}
    # None of the rejected samples entered the window of the 6 ms tick.
    assert_same(estimates(out), by_hand(0, [(3, [1, 2, 3]), (6, [4, 5, 6])]))


def test_a_tick_without_valid_imu_holds_the_previous_mean() -> None:
    stream = StreamingEstimator(model())
    out = paired(stream, range(0, 4))
    for k in (4, 5, 6):
        out += stream.add_imu(k * MS, np.array([np.nan, 0.0, G]), np.zeros(3)) + add_joints(stream, k)
    out += add_imu(stream, 7)   # shows the 6 ms sample will not come
    assert stream.held_imu_ticks == 1 and stream.rejections["imu_nan"] == 3
    estimator = StateEstimator(model())
    estimator.initialise_standing(0.0, joints(0)[0], (0.0, 0.0))
    mean = [np.mean([imu(k)[i] for k in (1, 2, 3)], axis=0) for i in (0, 1)]
    expected = {tick * MS: estimator.update(tick * MS * 1e-9, *mean, *joints(tick)) for tick in (3, 6)}
    assert_same(estimates(out), expected)


def test_unreadable_joint_states_are_rejected_and_only_tick_samples_are_read() -> None:
    stream = StreamingEstimator(model())
    reads: list[int] = []

    def read(k: int):
        def inner():
            reads.append(k)
            if k == 3:
                raise InputError("joint_states lacks joints")
            return joints(k)
        return inner

    out: list[EstimatorOutput] = []
    for k in range(0, 7):
        out += add_imu(stream, k) + stream.add_joints(k * MS, read(k))
    assert reads == [0, 3, 4, 6]            # 1, 2, 5 are not grid samples; 4 took the rejected 3 ms point
    assert stream.rejections == {"joints": 1}
    assert [o.stamp_ns // MS for o in out if o.kind == "estimate"] == [4, 6]
    assert_same(estimates(out), by_hand(0, [(4, [1, 2, 3, 4]), (6, [5, 6])]))


def test_repeated_samples_are_counted_and_the_last_tick_is_answered_again() -> None:
    stream = StreamingEstimator(model())
    paired(stream, range(0, 4))
    assert add_imu(stream, 3) == []
    repeat = add_joints(stream, 3)
    assert [(o.kind, o.stamp_ns) for o in repeat] == [("repeat", 3 * MS)]
    assert stream.duplicates == 2 and stream.ticks == 1 and not stream.rejections


def test_a_clock_jumping_back_restarts_the_estimator() -> None:
    """Back by more than CLOCK_RESET_NS: a new estimator starts at the new stamps (initial, then the grid);
    back by less is reordering and is rejected."""
    stream = StreamingEstimator(model())
    paired(stream, range(2000, 2010))
    first = stream.estimator
    assert CLOCK_RESET_NS < 2000 * MS
    assert add_imu(stream, 0) == [] and stream.restarts == 1 and stream.estimator is not first  # IMU first
    out = add_joints(stream, 0) + paired(stream, range(1, 7))
    assert stream.restarts == 1
    assert [(o.kind, o.stamp_ns // MS) for o in out] == [("initial", 0), ("estimate", 3), ("estimate", 6)]
    assert_same(estimates(out), by_hand(0, [(3, [1, 2, 3]), (6, [4, 5, 6])]))

    reordered = StreamingEstimator(model())
    paired(reordered, range(2000, 2010))
    assert add_imu(reordered, 2000 - CLOCK_RESET_NS // MS + 20) == []
    assert reordered.restarts == 0 and reordered.rejections == {"imu_out_of_order": 1}


def test_waiting_for_the_initial_pose() -> None:
    """With wait_for_initial_pose the first tick stays pending until a pose comes and starts there (the
    latest grid sample by then); a restart forgets the pose and waits again."""
    stream = StreamingEstimator(model(), wait_for_initial_pose=True)
    out = paired(stream, range(2000, 2006))
    assert out == [] and not stream.estimator.initialised
    position = np.array([1.0, 2.0, 0.6])
    out = stream.set_initial_pose(position, np.eye(3))
    assert [(o.kind, o.stamp_ns // MS) for o in out] == [("initial", 2004)]   # grid 2001, 2004, 2007 ms
    assert stream.estimator.kf is not None
    np.testing.assert_array_equal(stream.estimator.kf.x[:3, 0], position)
    assert stream.set_initial_pose(np.zeros(3), np.eye(3)) == []                # the first pose stays
    assert [o.stamp_ns // MS for o in paired(stream, range(2006, 2011)) if o.kind == "estimate"] == [2007, 2010]
    assert paired(stream, range(0, 4)) == []
    assert stream.restarts == 1 and not stream.has_initial_pose and not stream.estimator.initialised


def test_settings_change_at_run_time_and_survive_a_restart() -> None:
    """A contact threshold of 30 % of the weight: the standing legs (25 % each) leave contact from the next
    tick; a 5 m/s^2 accelerometer range rejects the IMU at rest; the period and mode are fixed."""
    stream = StreamingEstimator(model())
    assert all(estimates(paired(stream, range(2000, 2002)))[2001 * MS].legs.in_contact)
    stream.reconfigure(with_field(stream.settings, "leg_odometry.contact_threshold_weight_fraction", 0.3))
    assert not any(estimates(paired(stream, range(2002, 2005)))[2004 * MS].legs.in_contact)
    stream.reconfigure(with_field(stream.settings, "accel_range_m_s2", 5.0))
    paired(stream, [2005])
    assert stream.rejections == {"imu_saturated": 1}
    paired(stream, range(0, 2))
    assert stream.restarts == 1 and stream.settings.accel_range_m_s2 == 5.0
    assert stream.estimator.legs.threshold_n == pytest.approx(0.3 * model().total_mass_kg * G)
    with pytest.raises(InputError, match="period"):
        stream.reconfigure(with_field(stream.settings, "period_s", 0.004))
    with pytest.raises(InputError, match="mode"):
        stream.reconfigure(with_field(stream.settings, "leg_odometry.mode", "terrain_aware"))
    with pytest.raises(ValueError, match="k_p"):
        with_field(stream.settings, "attitude.k_p", -1.0)


def soft_ground(k_ms: int) -> LegImpedance:
    """A confident soft-ground fit, a different one for each TCE tick (stamp k_ms), so which one a tick used
    shows in its estimate."""
    k = np.full(4, 3000.0 + 400.0 * k_ms)
    return LegImpedance(k, np.full(4, 300.0), np.tile([0.0, 0.0, 1.0], (4, 1)), np.ones(4, bool), np.ones(4),
                        np.zeros(4, bool))


def terrain_aware(**kwargs) -> StreamingEstimator:
    settings = with_field(StreamingEstimator(model()).settings, "leg_odometry.mode", "terrain_aware")
    return StreamingEstimator(model(), settings, **kwargs)


def test_a_streamed_impedance_is_used_one_tce_period_later_and_waited_for() -> None:
    """With impedance_period_s (the TCE's 4 ms) the tick at J uses the TCE's answer to its tick at the newest
    4 ms grid point at least 4 ms before J, whether that answer arrives long before the tick (a fast TCE) or
    after the tick's joint and IMU samples (a slow one): the estimates are identical, and a tick waits for it."""
    tce_ticks = range(0, 24, 4)

    def run(early: bool) -> tuple[list[EstimatorOutput], StreamingEstimator]:
        stream = terrain_aware(impedance_period_s=0.004)
        out: list[EstimatorOutput] = []
        for k in range(0, 25):
            if early and k in tce_ticks:
                out += stream.add_impedance(k * MS, soft_ground(k))
            out += add_imu(stream, k) + add_joints(stream, k)
            # The slow TCE answers its tick u after the sample u + 6: every tick has to wait for its answer.
            if not early and k >= 6 and (k - 6) in tce_ticks:
                if k == 6:
                    assert 6 * MS not in estimates(out)  # the 6 ms tick waits for the answer to the 0 ms tick
                out += stream.add_impedance((k - 6) * MS, soft_ground(k - 6))
        if not early:
            out += stream.add_impedance(20 * MS, soft_ground(20))  # the answer the 24 ms tick waits for
        return out, stream

    fast, fast_stream = run(early=True)
    slow, slow_stream = run(early=False)
    assert sorted(estimates(fast)) == [k * MS for k in range(3, 25, 3)]
    assert_same(estimates(slow), estimates(fast))
    assert fast_stream.late_impedance_ticks == slow_stream.late_impedance_ticks == 0

    # Control: the latest impedance as it arrives (no period) gives other estimates for the fast TCE.
    latest = terrain_aware()
    out: list[EstimatorOutput] = []
    for k in range(0, 25):
        if k in tce_ticks:
            out += latest.add_impedance(k * MS, soft_ground(k))
        out += add_imu(latest, k) + add_joints(latest, k)
    with pytest.raises(AssertionError):
        assert_same(estimates(out), estimates(fast))


def test_a_tick_whose_impedance_never_comes_runs_late_and_is_counted() -> None:
    """The TCE stops answering: a waiting tick runs with the impedance it has once the next grid sample
    arrives (counted in late_impedance_ticks); a re-sent answer is dropped as a repeat."""
    stream = terrain_aware(impedance_period_s=0.004)
    out = stream.add_impedance(0, soft_ground(0)) + stream.add_impedance(0, soft_ground(0))
    out += paired(stream, range(0, 10))
    assert sorted(estimates(out)) == [3 * MS, 6 * MS]  # 9 ms waits for the answer to the 4 ms tick
    assert stream.late_impedance_ticks == 0 and stream.impedance_repeats == 1
    out += paired(stream, range(10, 13))
    assert 9 * MS in estimates(out) and stream.late_impedance_ticks == 1
    assert stream.impedance is not None and stream.impedance.stiffness_n_per_m[0] == soft_ground(0).stiffness_n_per_m[0]


def test_ticks_queue_behind_a_waiting_one_up_to_the_defer_limit() -> None:
    """A TCE that answers its tick u only after the sample u + 10 (up to 6 ms after the estimator's tick that
    needs it): with impedance_max_defer_s 8 ms a waiting tick is not released by the next grid sample (3 ms
    later), the ticks after it queue, and the estimates are those of a fast TCE; with no defer the same
    schedule runs ticks late (the control)."""
    tce_ticks = range(0, 28, 4)

    def run(defer_s: float | None) -> tuple[dict[int, StateEstimate], StreamingEstimator]:
        stream = terrain_aware(impedance_period_s=0.004, impedance_max_defer_s=defer_s or 0.0)
        out: list[EstimatorOutput] = []
        for k in range(0, 37):
            if defer_s is None and k in tce_ticks:
                out += stream.add_impedance(k * MS, soft_ground(k))
            out += add_imu(stream, k) + add_joints(stream, k)
            if defer_s is not None and (k - 10) in tce_ticks:
                out += stream.add_impedance((k - 10) * MS, soft_ground(k - 10))
        return {s: e for s, e in estimates(out).items() if s <= 27 * MS}, stream

    fast, _ = run(None)
    queued, stream = run(0.008)
    assert sorted(fast) == [k * MS for k in range(3, 28, 3)]
    assert_same(queued, fast)
    assert stream.late_impedance_ticks == 0
    impatient, stream = run(0.0)
    assert stream.late_impedance_ticks > 0
    with pytest.raises(AssertionError):
        assert_same(impatient, fast)
    with pytest.raises(ValueError, match="impedance_max_defer_s"):
        terrain_aware(impedance_period_s=0.004, impedance_max_defer_s=-1.0)
