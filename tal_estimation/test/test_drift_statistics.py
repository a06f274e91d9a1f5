"""Drift statistics and the stamp matcher that pairs estimates with ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from tal_estimation.drift_statistics import DriftStatistics, StampMatcher


def test_matcher_pairs_common_stamps_in_any_arrival_order() -> None:
    estimates = {stamp: f"e{stamp}" for stamp in range(0, 48, 3)}  # 333 Hz grid (ms)
    truths = {stamp: f"t{stamp}" for stamp in range(0, 48, 4)}  # 250 Hz grid
    pairs_by_order = []
    for truth_first in (True, False):
        matcher, pairs = StampMatcher(), []
        for stamp in range(48):
            arrivals = [("t", truths.get(stamp)), ("e", estimates.get(stamp))]
            for kind, item in (arrivals if truth_first else arrivals[::-1]):
                if item is None:
                    continue
                pair = (matcher.add_reference(stamp, item) if kind == "t" else matcher.add_estimate(stamp, item))
                if pair is not None:
                    pairs.append(pair)
        pairs_by_order.append(pairs)
    assert pairs_by_order[0] == pairs_by_order[1] == [("e0", "t0"), ("e12", "t12"), ("e24", "t24"), ("e36", "t36")]


def test_matcher_holds_a_bounded_number_of_unmatched_items() -> None:
    matcher = StampMatcher(keep=4)
    for stamp in range(100):
        assert matcher.add_estimate(stamp, stamp) is None
    assert matcher.add_reference(3, "old") is None  # forgotten: only the four newest are held
    assert matcher.add_reference(99, "new") == (99, "new")
    with pytest.raises(ValueError, match="keep must be >= 1"):
        StampMatcher(keep=0)


def test_drift_statistics_align_the_start() -> None:
    stats = DriftStatistics(align_start=True)
    stats.add(0.0, np.array([1.0, 0.0, 0.0]), np.zeros(3))
    stats.add(1.0, np.array([1.5, 0.0, -0.2]), np.array([0.1, 0.0, 0.0]))
    summary = stats.summary()
    assert summary["final_drift_m"] == [0.5, 0.0, -0.2]
    assert summary["samples"] == 2 and summary["compared_s"] == 1.0
