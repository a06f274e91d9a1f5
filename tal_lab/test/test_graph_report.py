"""graph_report: rates and missed ticks from stamps, stiffness attributed to the patch under the foot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from tal_lab.graph_report import read_bag, stiffness_table, topic_rates

from tal_core.ros.bag_io import BagWriter
from tal_core.ros.node_utils import stamp_from_ns
from tal_msgs.msg import ContactState, TerrainImpedance

MS = 1_000_000


def test_rates_count_the_missed_ticks_of_each_gap() -> None:
    ticks = [k * 4 * MS for k in range(1001)]          # 250 Hz for 4 s
    del ticks[500:503]                                  # one gap of 4 periods: 3 ticks missed
    del ticks[100]                                      # one gap of 2 periods: 1 missed
    rates = {r.topic: r for r in topic_rates({"gait_state": ticks}, real_time_factor=0.5)}
    gait = rates["gait_state"]
    assert gait.missed_ticks == 4
    assert gait.messages == 997
    assert gait.sim_rate_hz == pytest.approx(996 / 4.0)
    assert gait.wall_rate_hz == pytest.approx(0.5 * 996 / 4.0)
    assert rates["joint_states"].messages == 0 and rates["joint_states"].sim_rate_hz is None
    assert rates["footholds"].target_hz is None


def _write_walk(path: Path) -> None:
    """Every foot walks along x at 0.1 m/s from x = 1.0 (stance_course: rigid up to 2, T1 3500 N/m on
    [2, 4]); the estimate reported is the true stiffness under the foot, except LF's which is doubled."""
    with BagWriter(path) as bag:
        for k in range(0, 25_000, 20):                  # 25 s at 50 Hz
            t_ns = k * MS
            x = 1.0 + 0.1e-3 * k
            contacts, impedance = ContactState(), TerrainImpedance()
            contacts.header.stamp = impedance.header.stamp = stamp_from_ns(t_ns)
            for i in range(4):
                contacts.in_contact[i] = True
                contacts.foot_position[i].x = x
                true_k = 3500.0 if 2.0 <= x < 4.0 else 2.0e6
                impedance.stiffness_normal[i] = true_k * (2.0 if i == 0 else 1.0)
                impedance.valid[i] = True
                impedance.confidence[i] = 0.05 if i == 1 else 0.9   # RF below the wbc's threshold
            bag.write("/ground_truth/contacts", contacts, t_ns)
            bag.write("/terrain_impedance", impedance, t_ns)


def test_an_estimate_counts_for_a_patch_only_once_the_lookback_lies_on_it(tmp_path: Path) -> None:
    _write_walk(tmp_path / "bag")
    series = read_bag(tmp_path / "bag", "stance_course", lookback_s=2.5)
    assert set(series.stiffness) == {"default", "soft_t1"}
    t1 = np.array([s[0] for s in series.stiffness["soft_t1"]])
    # The foot enters T1 at t = 10 s: its estimates count from 12.5 s (lookback) on; it is still on T1 at the end.
    assert t1.min() == pytest.approx(12.5, abs=0.01)
    assert t1.max() == pytest.approx(24.98, abs=0.01)  # the last sample of the 25 s
    rows = {r["patch"]: r for r in stiffness_table(series, "stance_course")}
    assert rows["soft_t1"]["true_n_per_m"] == 3500.0
    assert rows["soft_t1"]["median_n_per_m"] == 3500.0     # 3 of 4 legs exact, LF doubled
    assert rows["soft_t1"]["p90_n_per_m"] == 7000.0
    assert rows["soft_t1"]["confident_share"] == pytest.approx(0.75, abs=0.01)   # RF's are not adopted
    assert rows["soft_t1"]["confident_median_n_per_m"] == 3500.0                 # LH, RH exact, LF doubled
    assert rows["default"]["true_n_per_m"] == 2.0e6
    assert rows["soft_t1"]["samples"] == len(t1) == pytest.approx(4 * (25.0 - 12.5) / 0.020, abs=8)
