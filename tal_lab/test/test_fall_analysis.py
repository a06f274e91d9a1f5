"""fall_analysis: the centroidal wrench of the WBC's forces and the first tick the QP missed the desired one."""

from __future__ import annotations

import numpy as np
import pytest
from tal_lab.fall_analysis import first_wrench_miss, wrench_miss_episodes

from tal_control.wbc.swbc import joint_acceleration_bounds
from tal_control.wbc.tasks import centroidal_wrench_map
from tal_core.errors import InputError

NAMES = tuple(f"{leg}_{joint}" for leg in ("lf", "rf", "lh", "rh") for joint in ("haa", "hfe", "kfe"))
LIMITS = (np.full(12, -1.0), np.full(12, 1.0))  # [rad]
HORIZON_S = 0.04


def constant_torque_limits(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.full(12, -150.0), np.full(12, 150.0)


def centroidal_wrench(forces: np.ndarray, points: np.ndarray, com) -> np.ndarray:
    return centroidal_wrench_map(points, com) @ np.asarray(forces, dtype=float).ravel()


def test_centroidal_wrench_sums_forces_and_their_moments() -> None:
    points = np.array([[0.4, 0.2, 0.0], [0.4, -0.2, 0.0], [-0.4, 0.2, 0.0], [-0.4, -0.2, 0.0]])
    weight = np.tile([0.0, 0.0, 200.0], (4, 1))
    np.testing.assert_allclose(centroidal_wrench(weight, points, [0.0, 0.0, 0.5]), [0, 0, 800, 0, 0, 0], atol=1e-9)
    one = np.zeros((4, 3))
    one[0, 2] = 100.0  # LF alone: it pitches the trunk nose up (-y moment) and rolls it right (+x moment)
    np.testing.assert_allclose(centroidal_wrench(one, points, np.zeros(3)), [0, 0, 100, 20, -40, 0], atol=1e-9)
    with pytest.raises(InputError, match=r"must be \(4, 3\)"):
        centroidal_wrench(np.zeros((4, 3)), points[:3], np.zeros(3))


def test_joint_acceleration_bounds_close_when_a_joint_runs_at_its_stop() -> None:
    q, qd = np.array([0.0, 0.95]), np.array([0.0, 2.0])
    qdd_min, qdd_max = joint_acceleration_bounds(q, qd, np.array([-1.0, -1.0]), np.array([1.0, 1.0]), HORIZON_S)
    assert qdd_max[0] == pytest.approx(1250.0) and qdd_min[0] == pytest.approx(-1250.0)
    assert qdd_max[1] < 0.0  # 2 rad/s towards a stop 0.05 rad away: it must already brake


def synthetic(n: int = 10, miss_at: int = 6) -> dict[str, np.ndarray]:
    t = 1.0 + 0.1 * np.arange(n)
    des = np.tile([0.0, 0.0, 880.0, 0.0, 0.0, 0.0], (n, 1))
    wbc = des.copy()
    wbc[miss_at:, 1] = 400.0  # 400 N sideways from the miss on
    wbc[1, 2] = 2000.0  # a larger miss before after_s: ignored
    stance = np.tile([False, True, True, False], (n, 1))
    tau, q, qd = np.zeros((n, 12)), np.zeros((n, 12)), np.zeros((n, 12))
    tau[miss_at, 6] = 150.0  # LH HAA at its limit
    q[miss_at, 1], qd[miss_at, 1] = 0.95, 2.0  # LF HFE running into its stop
    slacks = np.zeros((n, 4, 3))
    slacks[miss_at, 0, 2] = 12.0
    return {
        "t": t,
        "wrench_des": des,
        "wrench_wbc": wbc,
        "stance": stance,
        "tau": tau,
        "q": q,
        "qd": qd,
        "slacks": slacks,
    }


def analyse(arrays: dict[str, np.ndarray], **kwargs):
    return first_wrench_miss(
        **arrays,
        torque_limits=constant_torque_limits,
        joint_names=NAMES,
        position_limits=LIMITS,
        horizon_s=HORIZON_S,
        **kwargs,
    )


def test_first_miss_names_the_limits_that_held_the_qp() -> None:
    miss = analyse(synthetic(), after_s=1.5)
    assert miss is not None and miss.t_s == pytest.approx(1.6)
    assert miss.force_error_n == pytest.approx(400.0) and miss.stance == ("RF", "LH")
    assert miss.saturated == ("lh_haa",) and miss.at_joint_limit == ("lf_hfe",)
    assert miss.largest_slack_leg == "LF" and miss.largest_slack == pytest.approx(12.0)
    assert "lh_haa" in miss.describe() and "400 N" in miss.describe()


def test_no_miss_below_the_threshold_or_before_the_start() -> None:
    assert analyse(synthetic(), after_s=1.5, threshold_n=500.0) is None
    early = analyse(synthetic(miss_at=9), after_s=1.0)
    assert early is not None and early.t_s == pytest.approx(1.1)  # the 2000 N spike counts from t = 1.0 s


def test_wrong_shapes_are_rejected() -> None:
    arrays = synthetic()
    arrays["tau"] = arrays["tau"][:, :11]
    with pytest.raises(InputError, match="tau must have shape"):
        analyse(arrays)


def test_last_episode_is_the_onset_of_the_misses_that_last_to_the_end() -> None:
    arrays = synthetic(n=20, miss_at=12)  # misses from t = 2.2 s to the end
    arrays["wrench_wbc"][3, 1] = 400.0  # a transient at t = 1.3 s the trot recovered from
    assert analyse(arrays, after_s=1.0).t_s == pytest.approx(1.1)  # the 2000 N spike at t = 1.1 s
    onset = analyse(arrays, after_s=1.0, last_episode=True)
    assert onset is not None and onset.t_s == pytest.approx(2.2)
    arrays["wrench_wbc"][12:, 1] = 0.0  # nothing at the end: the run did not end in a miss
    assert analyse(arrays, after_s=1.0, last_episode=True) is None


def test_miss_episodes_group_close_misses_and_say_which_ones_the_run_recovered_from() -> None:
    t = 1.0 + 0.1 * np.arange(40)  # 1.0-4.9 s
    des = np.tile([0.0, 0.0, 880.0, 0.0, 0.0, 0.0], (40, 1))
    wbc = des.copy()
    wbc[1, 2] = 2000.0  # before after_s: ignored
    wbc[[6, 8], 1] = [400.0, 350.0]  # 1.6 and 1.8 s: 0.2 s apart, one episode
    wbc[20, 0] = 500.0  # 3.0 s: a second one, recovered
    wbc[36:, 1] = -310.0  # 4.6 s to the end: the fall
    wbc[30, 3:] = 5000.0  # a moment error alone is no miss
    episodes = wrench_miss_episodes(t, des, wbc, after_s=1.5)
    assert [(e.start_s, e.end_s) for e in episodes] == [pytest.approx((1.6, 1.8)), pytest.approx((3.0, 3.0)),
                                                        pytest.approx((4.6, 4.9))]
    assert [e.peak_force_error_n for e in episodes] == pytest.approx([400.0, 500.0, 310.0])
    assert [e.recovered for e in episodes] == [True, True, False]
    assert wrench_miss_episodes(t, des, des, after_s=1.5) == []
    # a threshold above every error: no episode; one below the smallest: the same three
    assert wrench_miss_episodes(t, des, wbc, after_s=1.5, threshold_n=600.0) == []
    assert len(wrench_miss_episodes(t, des, wbc, after_s=1.5, threshold_n=300.0)) == 3


def test_miss_episodes_reject_bad_arrays() -> None:
    t = np.arange(5.0)
    with pytest.raises(InputError, match=r"wrench_wbc must have shape \(5, 6\)"):
        wrench_miss_episodes(t, np.zeros((5, 6)), np.zeros((4, 6)))
    with pytest.raises(InputError, match="strictly increasing"):
        wrench_miss_episodes(t[::-1], np.zeros((5, 6)), np.zeros((5, 6)))
