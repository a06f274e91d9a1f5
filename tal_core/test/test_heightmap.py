"""Tests of tal_core.heightmap: grid convention (tal_msgs/HeightMap), sampling, inverse, bilinear look-up."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tal_core.errors import InputError
from tal_core.heightmap import GridNormals, HeightMapGrid, extract_heightmap
from tal_core.terrain import load_course

TAN_15 = math.tan(math.radians(15.0))


@pytest.fixture(scope="module")
def slope_map() -> HeightMapGrid:
    """Default 33 x 33 map at 2 cm, centred on the 15 deg ramp (x 1..3, z = tan15 (x - 1)), yaw 0.3 rad."""
    return extract_heightmap(load_course("slope_15deg"), center_xy=(2.0, 0.4), yaw=0.3)


def test_defaults_and_dtype(slope_map: HeightMapGrid) -> None:
    assert (slope_map.rows, slope_map.cols, slope_map.resolution_m) == (33, 33, 0.02)
    assert slope_map.heights.dtype == np.float32 and not slope_map.heights.flags.writeable


def test_slope_heightmap_matches_the_plane(slope_map: HeightMapGrid) -> None:
    xy = slope_map.cell_world_xy()
    np.testing.assert_allclose(slope_map.heights, TAN_15 * (xy[..., 0] - 1.0), atol=1e-6)


def test_cell_convention_yaw_zero() -> None:
    grid = extract_heightmap(load_course("flat_rigid"), (1.0, 0.5), 0.0, rows=5, cols=3, resolution_m=0.1)
    xy = grid.cell_world_xy()
    assert xy.shape == (5, 3, 2)
    np.testing.assert_allclose(xy[2, 1], [1.0, 0.5])  # centre cell
    np.testing.assert_allclose(xy[4, 1], [1.2, 0.5])  # last row: forward (+x)
    np.testing.assert_allclose(xy[2, 2], [1.0, 0.6])  # last column: left (+y)


def test_rotation_convention_yaw_half_pi() -> None:
    """With yaw = pi/2 the robot faces world +y: rows run along +y and columns (left) along -x."""
    grid = extract_heightmap(
        load_course("flat_rigid"), (1.0, 0.5), math.pi / 2, rows=5, cols=3, resolution_m=0.1
    )
    xy = grid.cell_world_xy()
    np.testing.assert_allclose(xy[4, 1], [1.0, 0.7], atol=1e-12)  # forward = world +y
    np.testing.assert_allclose(xy[2, 2], [0.9, 0.5], atol=1e-12)  # left = world -x
    np.testing.assert_allclose(xy[0, 0], [1.1, 0.3], atol=1e-12)  # hind right corner


def test_slope_seen_facing_left() -> None:
    """Facing +y on a ramp rising along world x, heights change along columns only (falling to the left)."""
    grid = extract_heightmap(
        load_course("slope_15deg"), (2.0, 0.0), math.pi / 2, rows=9, cols=7, resolution_m=0.05
    )
    np.testing.assert_allclose(np.diff(grid.heights, axis=0), 0.0, atol=1e-6)
    np.testing.assert_allclose(np.diff(grid.heights, axis=1), -0.05 * TAN_15, atol=1e-6)


def test_outside_the_course_is_nan() -> None:
    grid = extract_heightmap(load_course("flat_rigid"), (-2.0, 0.0), 0.0, rows=5, cols=5, resolution_m=0.1)
    assert np.all(np.isnan(grid.heights[:2])) and np.all(grid.heights[2:] == 0.0)  # row 2 lies on the edge


def test_cell_index_is_the_inverse(slope_map: HeightMapGrid) -> None:
    xy = slope_map.cell_world_xy()
    rows, cols = slope_map.cell_index(xy[..., 0], xy[..., 1])
    expected_rows, expected_cols = np.meshgrid(np.arange(33), np.arange(33), indexing="ij")
    np.testing.assert_array_equal(rows, expected_rows)
    np.testing.assert_array_equal(cols, expected_cols)
    fractional_rows, _ = slope_map.fractional_index(xy[3, 4, 0], xy[3, 4, 1])
    assert fractional_rows == pytest.approx(3.0)
    assert slope_map.cell_index(10.0, 10.0) == (-1, -1)


def test_height_at_is_bilinear(slope_map: HeightMapGrid) -> None:
    rng = np.random.default_rng(3)
    half_span = 0.5 * 32 * 0.02
    forward, left = rng.uniform(-half_span, half_span, (2, 200))
    cos_yaw, sin_yaw = math.cos(0.3), math.sin(0.3)
    x = 2.0 + cos_yaw * forward - sin_yaw * left
    y = 0.4 + sin_yaw * forward + cos_yaw * left
    # A bilinear interpolation of a plane is the plane itself.
    np.testing.assert_allclose(slope_map.height_at(x, y), TAN_15 * (x - 1.0), atol=1e-6)
    assert math.isnan(slope_map.height_at(5.0, 5.0))


def test_height_at_between_four_cells() -> None:
    grid = HeightMapGrid(center_xy=(0.0, 0.0), yaw=0.0, resolution_m=1.0, heights=[[0.0, 1.0], [2.0, 3.0]])
    assert grid.height_at(0.0, 0.0) == pytest.approx(1.5)  # centre between the four cells
    assert grid.height_at(-0.5, 0.5) == pytest.approx(1.0)  # on cell (0, 1)
    assert grid.height_at(0.7, 0.7) == pytest.approx(3.0)  # edge cells extend half a cell outwards
    assert math.isnan(grid.height_at(1.2, 0.0))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"resolution_m": 0.0}, "resolution_m must be a finite value > 0"),
        ({"rows": 0}, "rows must be an integer >= 1"),
        ({"cols": 2.5}, "cols must be an integer >= 1"),
        ({"yaw": float("nan")}, "yaw must be finite"),
        ({"center_xy": (0.0, float("inf"))}, "center_xy must be 2 finite values"),
    ],
)
def test_bad_arguments(kwargs: dict, message: str) -> None:
    arguments = {"center_xy": (0.0, 0.0), "yaw": 0.0, **kwargs}
    with pytest.raises(InputError, match=message):
        extract_heightmap(load_course("flat_rigid"), **arguments)


def test_bad_heights_shape() -> None:
    with pytest.raises(InputError, match=r"non-empty \(rows, cols\) array, got shape \(3,\)"):
        HeightMapGrid(center_xy=(0.0, 0.0), yaw=0.0, resolution_m=0.1, heights=np.zeros(3))


def test_scalar_queries_are_bit_identical_to_array_queries() -> None:
    """The scalar path (controllers query a few points per tick) gives exactly the array path's values,
    NaN next to unknown cells and outside the grid included."""
    rng = np.random.default_rng(5)
    heights = rng.random((41, 33)).astype(np.float32)
    heights[3, 4] = np.nan
    for yaw in (0.0, 0.3, -2.0):
        grid = HeightMapGrid(center_xy=(0.3, -0.2), yaw=yaw, resolution_m=0.02, heights=heights)
        xy = rng.uniform(-0.6, 0.6, (2000, 2))
        batch = grid.height_at(xy[:, 0], xy[:, 1])
        one_by_one = np.array([grid.height_at(float(x), float(y)) for x, y in xy])
        assert np.isnan(batch).any() and np.isfinite(batch).any()
        np.testing.assert_array_equal(one_by_one, batch)


def test_normals_at_match_the_scalar_normal_and_are_up_where_unknown() -> None:
    rng = np.random.default_rng(3)
    heights = rng.normal(0.0, 0.05, (21, 25)).astype(np.float32)
    heights[3, 4] = np.nan
    grid = HeightMapGrid(center_xy=(1.0, -0.5), yaw=0.4, resolution_m=0.02, heights=heights)
    centres = grid.cell_world_xy().reshape(-1, 2)[::7]
    xy = centres + rng.normal(0.0, 0.004, centres.shape)
    xy = np.vstack([xy, [[50.0, 50.0]], grid.cell_world_xy()[3, 4][None]])   # outside; next to the NaN cell
    many = GridNormals(grid).many(xy[:, 0], xy[:, 1])

    def scalar_normal(x: float, y: float) -> np.ndarray:   # central differences by scalar look-ups
        h = grid.resolution_m
        n = np.array([-(grid.height_at(x + h, y) - grid.height_at(x - h, y)) / (2 * h),
                      -(grid.height_at(x, y + h) - grid.height_at(x, y - h)) / (2 * h), 1.0])
        return n / np.linalg.norm(n) if np.all(np.isfinite(n)) else np.array([0.0, 0.0, 1.0])

    one = np.array([scalar_normal(float(x), float(y)) for x, y in xy])
    np.testing.assert_array_equal(np.array([GridNormals(grid)(x, y) for x, y in xy]), many)
    np.testing.assert_allclose(many, one, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(many, axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(many[-2], [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(many[-1], [0.0, 0.0, 1.0])
    assert not np.allclose(many[:, :2], 0.0)   # the random relief tilts most normals
    with pytest.raises(InputError, match="as many x as y"):
        grid.normals_at([0.0, 1.0], [0.0])
