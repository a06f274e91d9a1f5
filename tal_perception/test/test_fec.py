"""Foothold Evaluation Criteria on synthetic patches (patch frame: x forward, centre = nominal)."""

from __future__ import annotations

import numpy as np
import pytest

from tal_control.motion.swing import SwingTrajectory
from tal_core.legs import LEGS, Leg
from tal_perception.errors import FecConfigError, PerceptionInputError
from tal_perception.fec import FootholdEvaluator
from tal_perception.fec_grid import erode, terrain_roughness
from tal_perception.fec_settings import FecInput, FecSettings, GaitTiming

CENTRE = 16
TROT_SWING = GaitTiming(step_frequency_hz=1.5, duty_factor=0.6, swing_time_left_s=0.4 / 1.5, step_height_m=0.1)
WALK_TWIST = np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0])


def fec_input(heights: np.ndarray, hip_height: float, leg: Leg = Leg.LF, **kwargs) -> FecInput:
    return FecInput(leg, heights, hip_height, kwargs.pop("twist", WALK_TWIST), kwargs.pop("gait", TROT_SWING), **kwargs)


@pytest.mark.parametrize("leg", LEGS, ids=lambda leg: leg.name)
def test_flat_ground_nominal_is_safe(evaluator: FootholdEvaluator, hip_height: float, leg: Leg) -> None:
    result = evaluator.evaluate(fec_input(np.zeros((33, 33)), hip_height, leg))
    assert result.terrain_roughness.all() and result.leg_collision.all() and result.foot_trajectory_collision.all()
    assert result.safe[CENTRE, CENTRE]
    assert 200 < result.safe_count < 33 * 33  # the workspace bounds the safe region
    np.testing.assert_array_equal(
        result.raw,
        result.terrain_roughness
        & result.kinematic_feasibility
        & result.leg_collision
        & result.foot_trajectory_collision,
    )


def test_bar_edge_makes_the_edge_rough_and_blocks_the_swing(evaluator: FootholdEvaluator, hip_height: float) -> None:
    heights = np.zeros((33, 33))
    heights[CENTRE + 1 :, :] = 0.1  # a 10 cm step up starting one cell ahead of the nominal
    result = evaluator.evaluate(fec_input(heights, hip_height))
    assert not result.terrain_roughness[CENTRE - 1 : CENTRE + 3, :].any()  # within 2 cells of the edge
    assert result.terrain_roughness[CENTRE - 3, :].all() and result.terrain_roughness[CENTRE + 4, :].all()
    assert not result.safe[CENTRE, CENTRE]


def test_rising_swing_over_a_tall_bar_collides(evaluator: FootholdEvaluator, hip_height: float) -> None:
    heights = np.zeros((33, 33))
    heights[CENTRE - 6 : CENTRE - 3, :] = 0.25  # 25 cm wall between lift-off and the nominal
    result = evaluator.evaluate(fec_input(heights, hip_height))
    assert not result.foot_trajectory_collision[CENTRE:, CENTRE].any()  # apex 10 cm: cannot clear 25 cm


def test_unknown_cells_are_unsafe_and_eroded(evaluator: FootholdEvaluator, hip_height: float) -> None:
    heights = np.zeros((33, 33))
    heights[CENTRE, CENTRE] = np.nan
    result = evaluator.evaluate(fec_input(heights, hip_height))
    assert not result.raw[CENTRE, CENTRE] and not result.terrain_roughness[CENTRE, CENTRE]
    assert not result.safe[CENTRE - 1 : CENTRE + 2, CENTRE].any()  # neighbours within the 2 cm margin
    assert not result.safe[CENTRE, CENTRE - 1 : CENTRE + 2].any()


def test_hip_height_out_of_reach_leaves_nothing_safe(evaluator: FootholdEvaluator) -> None:
    result = evaluator.evaluate(fec_input(np.zeros((33, 33)), hip_height=1.5))
    assert result.safe_count == 0 and not result.kinematic_feasibility.any()


def test_safe_count_peaks_near_the_nominal_hip_height(evaluator: FootholdEvaluator, hip_height: float) -> None:
    counts = [evaluator.evaluate(fec_input(np.zeros((33, 33)), h)).safe_count for h in (0.35, hip_height, 0.75)]
    assert counts[1] > counts[0] and counts[1] > counts[2]


def test_yaw_rate_moves_the_workspace(evaluator: FootholdEvaluator, hip_height: float) -> None:
    straight = evaluator.evaluate(fec_input(np.zeros((33, 33)), hip_height)).safe
    turning = evaluator.evaluate(fec_input(np.zeros((33, 33)), hip_height, twist=[0.3, 0, 0, 0, 0, 1.0])).safe
    assert (straight != turning).any()


def test_swing_model_matches_tal_control(evaluator: FootholdEvaluator, hip_height: float) -> None:
    heights = np.zeros((33, 33))
    heights[20, 10] = 0.05
    prep = evaluator.prepare(fec_input(heights, hip_height, liftoff_xyz=[-0.25, 0.02, 0.01]))
    cell = np.array([20 * 33 + 10])
    x, y, z = evaluator._swing_centres(prep, cell, prep.swing_times)
    r = evaluator.foot_radius_m
    swing = SwingTrajectory([-0.25, 0.02, 0.01 + r], [0.08, -0.12, 0.05 + r], TROT_SWING.swing_duration_s, 0.1)
    expected = np.array([swing.sample(t).position for t in prep.swing_times])
    np.testing.assert_allclose(np.column_stack([x[:, 0], y[:, 0], z[:, 0]]), expected, atol=1e-12)


def _step_down_patch() -> np.ndarray:
    """The lift-off (one 0.2 m step behind the centre at 0.3 m/s and 1.5 Hz) on a tread 0.1 m above the
    rest of the patch, whose edge is 0.12 m behind the nominal."""
    heights = np.zeros((33, 33))
    heights[:10] = 0.1
    return heights


def _maps(result) -> list[np.ndarray]:
    return [result.terrain_roughness, result.kinematic_feasibility, result.leg_collision,
            result.foot_trajectory_collision, result.raw, result.safe]


def test_hip_rise_lets_the_leg_lift_off_above_the_lower_tread(evaluator: FootholdEvaluator) -> None:
    """Stepping down with the hip at a height for the lower tread (0.54 m above it): held there for the whole
    swing (the thesis), the leg lifting off the upper tread behind the hip is folded past its joint limits
    and no lower-tread candidate is feasible; with the hip 0.1 m higher at lift-off, moving down during the
    swing, 486 are."""
    heights = _step_down_patch()
    lower = np.zeros((33, 33), dtype=bool)
    lower[12:] = True
    level = evaluator.evaluate(fec_input(heights, 0.54))
    following = evaluator.evaluate(fec_input(heights, 0.54, hip_rise_at_liftoff_m=0.1))
    assert level.kinematic_feasibility[lower].sum() == 0 and level.safe_count == 0
    assert following.kinematic_feasibility[lower].sum() == 486 and following.safe_count > 50


def test_hip_rise_zero_or_no_swing_left_changes_nothing(evaluator: FootholdEvaluator) -> None:
    """A zero rise is the thesis' model bit for bit; with no swing left every sample is at touchdown, where
    the hip is at hip_height_m whatever the rise."""
    heights = _step_down_patch()
    default = evaluator.evaluate(fec_input(heights, 0.6))
    zero = evaluator.evaluate(fec_input(heights, 0.6, hip_rise_at_liftoff_m=0.0))
    for a, b in zip(_maps(default), _maps(zero)):
        np.testing.assert_array_equal(a, b)
    landed = GaitTiming(1.5, 0.6, 0.0, 0.1)
    at_touchdown = evaluator.evaluate(fec_input(heights, 0.6, gait=landed))
    risen = evaluator.evaluate(fec_input(heights, 0.6, gait=landed, hip_rise_at_liftoff_m=0.1))
    for a, b in zip(_maps(at_touchdown), _maps(risen)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(PerceptionInputError, match=r"FecInput.hip_rise_at_liftoff_m must be a finite number \[m\], got nan"):
        fec_input(heights, 0.6, hip_rise_at_liftoff_m=float("nan"))


def test_roughness_thresholds_on_planes_and_small_steps() -> None:
    """The figures FecSettings' docstring and the README give for the default thresholds."""
    x = np.arange(33)[:, None] * 0.02 * np.ones((1, 33))
    gentle, steep = np.tan(np.radians(26.0)) * x, np.tan(np.radians(28.0)) * x
    assert terrain_roughness(gentle, 0.02, 0.04, 0.3, 0.35)[2:-2, 2:-2].all()
    assert not terrain_roughness(steep, 0.02, 0.04, 0.3, 0.35)[2:-2, 2:-2].any()
    step = np.zeros((33, 33))
    step[17:, :] = 0.02
    rough_rows = np.flatnonzero(~terrain_roughness(step, 0.02, 0.04, 0.3, 0.35)[:, 16])
    assert rough_rows.tolist() == [16, 17]  # the two cells next to the edge


def test_erosion_ignores_cells_outside_the_patch() -> None:
    safe = np.ones((5, 5), dtype=bool)
    assert erode(safe, 0.02, 0.02).all()
    safe[2, 2] = False
    eroded = erode(safe, 0.02, 0.02)
    assert eroded.sum() == 25 - 5  # the cell and its 4 neighbours within 2 cm


def test_bad_inputs_raise_precise_errors(evaluator: FootholdEvaluator, hip_height: float) -> None:
    with pytest.raises(
        PerceptionInputError, match=r"FecInput.heights must be a \(rows, cols\) array .* got shape \(33,\)"
    ):
        fec_input(np.zeros(33), hip_height)
    with pytest.raises(PerceptionInputError, match=r"FecInput.twist has non-finite value\(s\) at index \[5\]"):
        fec_input(np.zeros((33, 33)), hip_height, twist=[0, 0, 0, 0, 0, np.nan])
    with pytest.raises(PerceptionInputError, match=r"FecInput.twist must have shape \(6,\), got \(3,\)"):
        fec_input(np.zeros((33, 33)), hip_height, twist=[0, 0, 0])
    with pytest.raises(PerceptionInputError, match=r"FecInput.hip_height_m must be a finite number \[m\], got nan"):
        fec_input(np.zeros((33, 33)), float("nan"))
    with pytest.raises(
        PerceptionInputError, match=r"FEC: heights must have the settings' patch shape \(33, 33\), got \(21, 21\)"
    ):
        evaluator.evaluate(fec_input(np.zeros((21, 21)), hip_height))
    with pytest.raises(
        PerceptionInputError, match=r"GaitTiming.duty_factor must be in \(0, 1\) for a swinging leg, got 1.0"
    ):
        GaitTiming(1.5, 1.0, 0.1, 0.1)
    with pytest.raises(PerceptionInputError, match=r"GaitTiming.swing_time_left_s must be in \[0, 0.2667\] s"):
        GaitTiming(1.5, 0.6, 0.5, 0.1)
    with pytest.raises(FecConfigError, match=r"FecSettings.max_mean_slope must be >= 0, got -1"):
        FecSettings(max_mean_slope=-1)
    with pytest.raises(FecConfigError, match=r"FecSettings.patch_cells must be odd"):
        FecSettings(patch_cells=32)
    with pytest.raises(FecConfigError, match=r"FecSettings.swing_samples must be an integer >= 1, got 0"):
        FecSettings(swing_samples=0)
    with pytest.raises(FecConfigError, match=r"FecSettings.resolution_m must be a finite number, got inf"):
        FecSettings(resolution_m=float("inf"))


def test_gathered_grid_operations_match_the_reference_ones(evaluator: FootholdEvaluator) -> None:
    from tal_lab.vital.terrain_samples import terrain_samples

    from tal_perception.fec_grid import PatchGrids, disc_max

    s = evaluator.settings
    grids = PatchGrids(33, 33, 0.02, s.roughness_radius_m, s.leg_radius_m, evaluator.foot_radius_m, 0.04)
    rng = np.random.default_rng(1)
    for sample in terrain_samples(seed=2, count=10):
        heights = np.array(sample.heights, dtype=float)
        heights[rng.uniform(size=heights.shape) < 0.03] = np.nan
        np.testing.assert_array_equal(
            grids.roughness_ok(heights, 0.3, 0.35).reshape(33, 33), terrain_roughness(heights, 0.02, 0.04, 0.3, 0.35)
        )
        np.testing.assert_array_equal(grids.highest(heights, grids.leg), disc_max(heights, 0.02, s.leg_radius_m))
        safe = rng.uniform(size=(33, 33)) < 0.9
        np.testing.assert_array_equal(grids.erode(safe), erode(safe, 0.02, 0.04))
