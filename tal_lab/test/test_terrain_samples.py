"""Seeded random terrain patches."""

from __future__ import annotations

import numpy as np
import pytest
from tal_lab.vital.terrain_samples import TERRAIN_KINDS, random_terrain, terrain_samples

from tal_perception.errors import FecConfigError


def test_samples_are_reproducible_and_cover_every_kind() -> None:
    first, second = list(terrain_samples(3, 10)), list(terrain_samples(3, 10))
    assert [s.kind for s in first] == list(TERRAIN_KINDS) * 2
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a.heights, b.heights)
        assert a.heights.shape == (33, 33) and np.isfinite(a.heights).all()
    assert np.ptp(first[0].heights) == 0.0  # flat
    assert all(np.ptp(s.heights) > 0.0 for s in first[1:4])  # bars, gaps, stairs cross the patch


def test_bad_arguments() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(FecConfigError, match=r"terrain kind 'lava' is not one of flat, bars, gaps, stairs, rocks"):
        random_terrain(rng, "lava")
    with pytest.raises(FecConfigError, match=r"kinds must be a non-empty subset"):
        list(terrain_samples(0, 1, kinds=()))
    with pytest.raises(FecConfigError, match=r"cells must be an integer >= 1, got 0"):
        random_terrain(rng, "flat", cells=0)
