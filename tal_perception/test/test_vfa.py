"""VFA: the safe foothold closest to the nominal, on world maps built from tal_core courses/arrays."""

from __future__ import annotations

import numpy as np
import pytest
from tal_lab.vital.terrain_samples import terrain_samples

from tal_core.heightmap import HeightMapGrid, extract_heightmap
from tal_core.legs import LEGS, Leg
from tal_core.terrain import Course, DefaultGround, FlatPatch, GapPatch, Region
from tal_perception.errors import FecConfigError, PerceptionInputError
from tal_perception.fec_settings import GaitTiming
from tal_perception.vfa import FootholdSelector, VfaStatus, extract_patch, extract_patches, select_foothold

TROT_SWING = GaitTiming(step_frequency_hz=1.5, duty_factor=0.6, swing_time_left_s=0.4 / 1.5, step_height_m=0.1)
WALK_TWIST = np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0])
RIGID = {"stiffness_n_per_m": 2e6, "damping_ns_per_m": 400.0}
NOMINAL = np.array([0.40, 0.21, 0.0])  # LF nominal foothold [m], world


def course_map(*patches, size: int = 81) -> HeightMapGrid:
    course = Course("test", Region(-2, 2, -2, 2), DefaultGround(height_m=0.0, **RIGID), tuple(patches))
    return extract_heightmap(course, (NOMINAL[0], NOMINAL[1]), 0.0, size, size, 0.02)


def select(selector: FootholdSelector, grid, hip_height: float, leg: Leg = Leg.LF, **kwargs):
    kwargs.setdefault("twist", WALK_TWIST)
    kwargs.setdefault("gait", TROT_SWING)
    return select_foothold(selector, leg, kwargs.pop("nominal", NOMINAL), grid, hip_height_m=hip_height, **kwargs)


@pytest.mark.parametrize("leg", LEGS, ids=lambda leg: leg.name)
def test_flat_ground_keeps_the_nominal(selector: FootholdSelector, hip_height: float, leg: Leg) -> None:
    result = select(selector, course_map(), hip_height, leg)
    assert result.status is VfaStatus.SELECTED and result.any_safe and not result.adapted
    np.testing.assert_allclose(result.selected, NOMINAL, atol=1e-9)


def test_bar_edge_at_the_nominal_moves_the_foothold_off_the_edge(selector: FootholdSelector, hip_height: float) -> None:
    bar = FlatPatch(name="bar", region=Region(NOMINAL[0] + 0.01, NOMINAL[0] + 0.31, -2, 2), height_m=0.1, **RIGID)
    grid = course_map(bar)
    result = select(selector, grid, hip_height)
    assert result.any_safe and result.adapted
    edge_distance = abs(result.selected[0] - (NOMINAL[0] + 0.01))
    assert edge_distance >= 0.04  # off the edge by more than the roughness neighbourhood
    assert result.selected[2] == pytest.approx(grid.height_at(*result.selected[:2]))
    full = select(selector, grid, hip_height, lazy=False)
    np.testing.assert_allclose(full.selected, result.selected)
    assert full.safe_candidates > 0


def test_gap_at_the_nominal_is_avoided(selector: FootholdSelector, hip_height: float) -> None:
    gap = GapPatch(
        name="gap", region=Region(NOMINAL[0] - 0.05, NOMINAL[0] + 0.05, -2, 2), depth_m=0.3, start_height_m=0.0, **RIGID
    )
    result = select(selector, course_map(gap), hip_height)
    assert result.any_safe and result.adapted
    assert result.selected[2] == pytest.approx(0.0)  # on the ground, not in the gap
    assert min(abs(result.selected[0] - (NOMINAL[0] - 0.05)), abs(result.selected[0] - (NOMINAL[0] + 0.05))) >= 0.03


def test_unknown_cells_at_the_nominal_are_avoided(selector: FootholdSelector, hip_height: float) -> None:
    heights = np.array(course_map().heights)
    heights[38:43, 38:43] = np.nan  # 5 x 5 unknown cells around the nominal (map centre 40, 40)
    grid = HeightMapGrid(center_xy=tuple(NOMINAL[:2]), yaw=0.0, resolution_m=0.02, heights=heights)
    result = select(selector, grid, hip_height)
    assert result.any_safe and result.adapted
    assert np.isfinite(result.selected).all()
    row, col = result.offset_cells
    assert max(abs(row), abs(col)) >= 4  # two cells of unknown plus the one-cell margin


def test_all_unsafe_passes_the_nominal_through(selector: FootholdSelector, hip_height: float) -> None:
    unknown = HeightMapGrid(center_xy=(0.0, 0.0), yaw=0.0, resolution_m=0.02, heights=np.full((41, 41), np.nan))
    for grid, kwargs in ((unknown, {}), (course_map(), {"hip_height": 1.6})):
        result = select(selector, grid, kwargs.get("hip_height", hip_height), lazy=False)
        assert not result.any_safe and result.status is VfaStatus.NO_SAFE_CANDIDATE
        assert result.safe_candidates == 0
        np.testing.assert_array_equal(result.selected, NOMINAL)


def test_missing_or_stale_map_passes_the_nominal_through(selector: FootholdSelector, hip_height: float) -> None:
    missing = select(selector, None, hip_height)
    stale = select(selector, course_map(), hip_height, map_age_s=2.0)
    assert (missing.status, stale.status) == (VfaStatus.NO_MAP, VfaStatus.STALE_MAP)
    for result in (missing, stale):
        assert not result.any_safe
        np.testing.assert_array_equal(result.selected, NOMINAL)


def test_map_outside_the_patch_and_rotated_heading(selector: FootholdSelector, hip_height: float) -> None:
    grid = course_map(size=41)
    patch = extract_patch(grid, (NOMINAL[0] + 0.5, NOMINAL[1]), 0.0, 33, 0.02)
    assert np.isnan(patch[-5:, :]).all() and not np.isnan(patch[:5, :]).any()
    result = select(selector, course_map(), hip_height, yaw=np.pi / 2)
    np.testing.assert_allclose(result.selected, NOMINAL, atol=1e-9)


def test_lazy_search_equals_full_evaluation(selector: FootholdSelector, hip_height: float) -> None:
    rng = np.random.default_rng(11)
    for i, sample in enumerate(terrain_samples(seed=7, count=30)):
        base = float(sample.parameters["base_height_m"])
        grid = HeightMapGrid(center_xy=(0.0, 0.0), yaw=sample.yaw, resolution_m=0.02, heights=sample.heights)
        twist = [rng.uniform(0, 0.5), rng.uniform(-0.1, 0.1), 0, 0, 0, rng.uniform(-0.3, 0.3)]
        gait = GaitTiming(1.5, 0.6, rng.uniform(0.0, 0.4 / 1.5), 0.1)
        kwargs = {"nominal": np.array([0.0, 0.0, base]), "leg": LEGS[i % 4], "twist": twist, "gait": gait}
        hip = hip_height + base + rng.uniform(-0.05, 0.05)
        lazy = select(selector, grid, hip, **kwargs)
        full = select(selector, grid, hip, lazy=False, **kwargs)
        assert lazy.status == full.status, sample.kind
        np.testing.assert_allclose(lazy.selected, full.selected, err_msg=sample.kind)


def test_bad_inputs_raise_precise_errors(selector: FootholdSelector, hip_height: float) -> None:
    grid = course_map()
    with pytest.raises(PerceptionInputError, match=r"VFA: nominal_world must be 3 finite values"):
        select(selector, grid, hip_height, nominal=[0.0, np.nan, 0.0])
    with pytest.raises(PerceptionInputError, match=r"FecInput.twist has non-finite value\(s\) at index \[0\]"):
        select(selector, grid, hip_height, twist=[np.nan, 0, 0, 0, 0, 0])
    with pytest.raises(PerceptionInputError, match=r"VFA: the heightmap is stamped 0.5000 s in the future"):
        select(selector, grid, hip_height, map_age_s=-0.5)
    with pytest.raises(FecConfigError, match=r"max_map_age_s must be a finite value > 0 \[s\], got 0"):
        FootholdSelector(selector.evaluator, max_map_age_s=0)


def test_aligned_patch_equals_the_general_extraction() -> None:
    rng = np.random.default_rng(4)
    grid = HeightMapGrid(center_xy=(0.3, -0.2), yaw=0.4, resolution_m=0.02, heights=rng.uniform(size=(50, 60)))
    for center in ((0.31, -0.19), (0.8, 0.1), (-0.5, -0.9), (5.0, 5.0)):
        fast = extract_patch(grid, center, 0.4, 33, 0.02)
        general = extract_patch(grid, center, 0.4 + 1e-6, 33, 0.02)  # not aligned: the per-cell look-up
        np.testing.assert_array_equal(fast, general)


@pytest.mark.parametrize("yaw", [0.0, np.pi / 2, -2.0])
def test_given_liftoff_is_rotated_into_the_patch_frame(
    selector: FootholdSelector, hip_height: float, yaw: float
) -> None:
    bar = FlatPatch(name="bar", region=Region(NOMINAL[0] - 0.12, NOMINAL[0] + 0.01, -2, 2), height_m=0.12, **RIGID)
    grid = course_map(bar)
    step = WALK_TWIST[0] / TROT_SWING.step_frequency_hz  # the default lift-off: one step behind, on the ground
    behind = NOMINAL - step * np.array([np.cos(yaw), np.sin(yaw), 0.0])
    behind[2] = grid.height_at(behind[0], behind[1])
    default = select(selector, grid, hip_height, yaw=yaw, lazy=False)
    given = select(selector, grid, hip_height, yaw=yaw, lazy=False, liftoff_world=behind)
    np.testing.assert_allclose(given.selected, default.selected)
    assert given.safe_candidates == default.safe_candidates
    flat = course_map()
    raised = np.array([behind[0], behind[1], 0.05])  # 5 cm above the flat ground: the leg folds more (KF)
    flat_default = select(selector, flat, hip_height, yaw=yaw, lazy=False).safe_candidates
    flat_raised = select(selector, flat, hip_height, yaw=yaw, lazy=False, liftoff_world=raised).safe_candidates
    assert 0 < flat_raised < flat_default


@pytest.mark.parametrize("yaw", [0.0, 2.5])
def test_given_hip_at_touchdown_is_rotated_into_the_patch_frame(
    selector: FootholdSelector, hip_height: float, yaw: float
) -> None:
    grid = course_map()
    half_stance = 0.5 * TROT_SWING.stance_duration_s * WALK_TWIST[0]  # the default: Raibert, v_hip = v here
    heading = np.array([np.cos(yaw), np.sin(yaw)])
    default = select(selector, grid, hip_height, yaw=yaw, lazy=False)
    given = select(
        selector, grid, hip_height, yaw=yaw, lazy=False, hip_touchdown_world=NOMINAL[:2] - half_stance * heading
    )
    assert given.safe_candidates == default.safe_candidates
    ahead = select(selector, grid, hip_height, yaw=yaw, lazy=False, hip_touchdown_world=NOMINAL[:2] + 0.1 * heading)
    assert ahead.safe_candidates != default.safe_candidates


@pytest.mark.parametrize("yaw_offset", [0.0, 0.37])
def test_extract_patches_equals_extract_patch_for_each_centre(yaw_offset: float) -> None:
    """The batched extraction (the CNN selector's) gives extract_patch's heights bit for bit, for patches
    inside the map, across its border and outside it, aligned with the map (slices) or not (nearest cell)."""
    rng = np.random.default_rng(3)
    heights = rng.normal(size=(61, 53)).astype(np.float32)
    heights[rng.random(heights.shape) < 0.05] = np.nan
    grid = HeightMapGrid(center_xy=(0.31, -0.2), yaw=0.4, resolution_m=0.02, heights=heights)
    centres = np.array([[0.31, -0.2], [0.5, 0.1], [0.31 + 0.55, -0.2], [3.0, 3.0], [0.123456, -0.3456789]])
    yaw = grid.yaw + yaw_offset
    expected = np.stack([extract_patch(grid, c, yaw, 33, 0.02) for c in centres])
    np.testing.assert_array_equal(extract_patches(grid, centres, yaw, 33, 0.02), expected)
    out = np.full((len(centres), 33, 33), 7.0, np.float32)
    assert extract_patches(grid, centres, yaw, 33, 0.02, out=out) is out
    np.testing.assert_array_equal(out, expected.astype(np.float32))
    # the definition: the nearest grid cell at every patch cell centre, NaN off the grid
    forward, left = np.meshgrid((np.arange(33) - 16) * 0.02, (np.arange(33) - 16) * 0.02, indexing="ij")
    for (x0, y0), patch in zip(centres, expected):
        rows, cols = grid.cell_index(x0 + np.cos(yaw) * forward - np.sin(yaw) * left,
                                     y0 + np.sin(yaw) * forward + np.cos(yaw) * left)  # fmt: skip
        np.testing.assert_array_equal(patch, np.where(rows >= 0, grid.heights[rows, cols], np.nan))
