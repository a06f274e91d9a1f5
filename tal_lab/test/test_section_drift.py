"""section_drift: the z drift an estimate accumulates per course section, in m and m per m travelled."""

from __future__ import annotations

import math

import numpy as np
import pytest
from tal_lab.section_drift import SectionDrift, format_section_table

from tal_core.terrain import load_course


def patches_by_x(x: float, y: float) -> str:
    return "soft" if 1.0 <= x < 2.0 else "default"


def test_sections_follow_the_patches_crossed_and_add_up_to_the_final_drift() -> None:
    """Walk 3 m along x at 0.2 m/s; the error grows in z only on the soft patch (x in [1, 2)): 0.05 m per m."""
    drift = SectionDrift(patches_by_x)
    t = np.arange(0.0, 15.0 + 1e-9, 0.01)
    x = 0.2 * t
    z_error = 0.05 * np.clip(x - 1.0, 0.0, 1.0)
    for ti, xi, ei in zip(t, x, z_error):
        drift.add(ti, np.array([xi, 0.0, 0.6]), np.array([0.0, 0.0, ei]))
    sections = drift.summary()
    assert [s["name"] for s in sections] == ["default", "soft", "default"]   # a patch crossed twice: two sections
    assert [s["distance_m"] for s in sections] == pytest.approx([1.0, 1.0, 1.0], abs=0.003)
    assert [s["drift_m"][2] for s in sections] == pytest.approx([0.0, 0.05, 0.0], abs=2e-4)
    assert sections[1]["z_drift_per_m"] == pytest.approx(0.05, abs=5e-4)
    assert sum(s["drift_m"][2] for s in sections) == pytest.approx(z_error[-1], abs=1e-12)
    table = format_section_table(sections)
    assert table[0].startswith("| section |") and len(table) == 2 + 3
    assert "| soft |" in table[3] and "+0.050" in table[3]


def test_a_section_without_travel_has_no_rate() -> None:
    drift = SectionDrift(patches_by_x)
    for t in range(3):
        drift.add(float(t), np.array([0.5, 0.0, 0.6]), np.array([0.0, 0.0, 0.01 * t]))
    (section,) = drift.summary()
    assert section["distance_m"] == 0.0 and section["z_drift_per_m"] is None
    assert section["drift_m"][2] == pytest.approx(0.02)
    assert "n/a" in format_section_table([section])[2]


def test_graph_tour_sections_in_order() -> None:
    course = load_course("graph_tour")
    drift = SectionDrift(course.patch_at)
    for x in np.arange(0.0, 7.0, 0.01):
        drift.add(x, np.array([x, 0.0, 0.6]), np.zeros(3))
    assert [s["name"] for s in drift.summary()] == ["default", "soft_t1", "moderate_t2", "default", "stairs_up",
                                                    "landing"]
    assert all(not math.isnan(s["distance_m"]) for s in drift.summary())
