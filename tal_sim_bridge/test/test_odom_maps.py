"""Heightmaps in the state estimate's frame (tal_sim_bridge.odom_maps): the placement keeps every cell where it is
relative to the robot, and the map of a tick waits for the estimate of that tick whatever the arrival order."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tal_core.errors import InputError
from tal_core.heightmap import extract_heightmap
from tal_core.terrain import load_course
from tal_sim_bridge.odom_maps import EstimateFrameMaps, PlanarPose, grid_in_estimate_frame

MS = 1_000_000


@pytest.fixture(scope="module")
def stairs_map():
    course = load_course("graph_tour")
    truth = PlanarPose(5.6, 0.02, 0.72, 0.03)
    grid = extract_heightmap(course, (truth.x, truth.y), truth.yaw, rows=41, cols=31, resolution_m=0.02)
    return course, truth, grid


def test_a_cell_keeps_its_place_relative_to_the_robot_and_its_height_moves_by_the_height_error(stairs_map) -> None:
    course, truth, grid = stairs_map
    estimate = PlanarPose(5.5, -0.01, 0.69, 0.05)   # 0.1 m behind, 3 cm low, 0.02 rad of yaw off
    placed = grid_in_estimate_frame(grid, truth, estimate)
    # A point 0.2 m ahead and 0.1 m left of the base (on the second step): in the world at the true pose, in the
    # map at the estimate's.
    ahead, left = 0.2, 0.1

    def at(pose: PlanarPose) -> tuple[float, float]:
        c, s = math.cos(pose.yaw), math.sin(pose.yaw)
        return pose.x + c * ahead - s * left, pose.y + s * ahead + c * left

    wx, wy = at(truth)
    ex, ey = at(estimate)
    true_height = float(course.height(np.array([wx]), np.array([wy]))[0])
    assert placed.height_at(ex, ey) == pytest.approx(true_height + (estimate.z - truth.z), abs=1e-6)
    # Read at the estimate's coordinates, the world-frame map is off by a step (this is what the frame fixes).
    assert abs(grid.height_at(ex, ey) - true_height) > 0.05
    assert placed.yaw == pytest.approx(grid.yaw + 0.02)


def test_the_same_pose_changes_nothing(stairs_map) -> None:
    _, truth, grid = stairs_map
    placed = grid_in_estimate_frame(grid, truth, truth)
    assert placed.center_xy == pytest.approx(grid.center_xy)
    assert placed.yaw == pytest.approx(grid.yaw)
    np.testing.assert_array_equal(placed.heights, grid.heights)


def test_a_map_waits_for_the_estimate_of_its_tick_in_either_arrival_order(stairs_map) -> None:
    _, truth, grid = stairs_map
    first, second = EstimateFrameMaps(3 * MS), EstimateFrameMaps(3 * MS)
    estimate = PlanarPose(5.5, 0.0, 0.7, 0.03)
    other = PlanarPose(5.4, 0.0, 0.7, 0.03)
    # The map of t = 50 ms takes the estimate of 48 ms (the estimator's newest tick at or before it).
    assert first.expected_stamp(50 * MS) == 48 * MS
    assert first.add_estimate(45 * MS, other) == []
    assert first.add_map(50 * MS, grid, truth) == []          # 48 ms not there yet: it waits
    assert first.waiting == 1
    (a,) = first.add_estimate(48 * MS, estimate)
    second.add_estimate(48 * MS, estimate)                     # the other order: the estimate comes first
    second.add_estimate(45 * MS, other)
    (b,) = second.add_map(50 * MS, grid, truth)
    for placed in (a, b):
        assert placed.estimate_stamp_ns == 48 * MS
        assert placed.grid.center_xy == pytest.approx((grid.center_xy[0] - 0.1, grid.center_xy[1] - 0.02))
    np.testing.assert_array_equal(a.grid.heights, b.grid.heights)
    assert first.late_estimate_maps == second.late_estimate_maps == 0


def test_a_skipped_estimate_or_a_flush_places_the_map_with_the_newest_earlier_one_and_counts_it(stairs_map) -> None:
    _, truth, grid = stairs_map
    maps = EstimateFrameMaps(3 * MS)
    assert maps.add_map(0, grid, truth) == []                  # waits for the estimate of 0 ...
    assert maps.flush()[0].estimate_stamp_ns is None           # ... flushed before any: the world frame
    assert maps.world_frame_maps == 1
    maps.add_estimate(45 * MS, PlanarPose(5.5, 0.0, 0.7, 0.03))
    assert maps.add_map(50 * MS, grid, truth) == []
    (placed,) = maps.add_estimate(51 * MS, PlanarPose(5.6, 0.0, 0.7, 0.03))   # 48 ms never came
    assert placed.estimate_stamp_ns == 45 * MS
    assert maps.add_map(100 * MS, grid, truth) == []
    (flushed,) = maps.flush()
    assert flushed.estimate_stamp_ns == 51 * MS
    assert maps.late_estimate_maps == 2 and maps.waiting == 0
    assert maps.summary()["placed_maps"] == 3


def test_bad_inputs_are_refused() -> None:
    with pytest.raises(InputError, match="estimate_period_ns"):
        EstimateFrameMaps(0)
    with pytest.raises(InputError, match="position"):
        PlanarPose.from_position_quat([0.0, math.nan, 0.5], [0.0, 0.0, 0.0, 1.0])
    with pytest.raises(InputError, match="position"):
        PlanarPose.from_position_quat([0.0, 0.5], [0.0, 0.0, 0.0, 1.0])
