"""Robot-centric heightmaps sampled from a terrain course.

The grid convention is the one of ``tal_msgs/HeightMap``: rows x cols square cells aligned with the
robot's horizontal frame (base yaw only). Cell (r, c) has its centre at horizontal-frame offsets

    dx = (r - (rows - 1) / 2) * resolution   (forward)
    dy = (c - (cols - 1) / 2) * resolution   (left)

which are rotated by yaw and added to the centre to give world x, y. Heights are world z [m]; NaN means
unknown (outside the course).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tal_core.errors import InputError
from tal_core.terrain import Course

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class HeightMapGrid:
    """A robot-centric grid of world-frame heights.

    center_xy [m] world frame; yaw [rad] heading of the row axis in the world frame; resolution_m [m]
    cell edge; heights (rows, cols) float32 [m] world z, read-only, NaN = unknown.
    """

    center_xy: tuple[float, float]
    yaw: float
    resolution_m: float
    heights: NDArray[np.float32]

    def __post_init__(self) -> None:
        heights = np.array(self.heights, dtype=np.float32)  # own copy, so freezing it is safe
        if heights.ndim != 2 or heights.shape[0] < 1 or heights.shape[1] < 1:
            raise InputError(
                f"heightmap heights must be a non-empty (rows, cols) array, got shape {heights.shape}"
            )
        _check_pose(self.center_xy, self.yaw, self.resolution_m)
        heights.setflags(write=False)
        object.__setattr__(self, "heights", heights)
        object.__setattr__(self, "center_xy", (float(self.center_xy[0]), float(self.center_xy[1])))
        rows, cols = heights.shape
        # The scalar look-up's constants (a controller queries ~20 points a tick, one at a time).
        object.__setattr__(self, "_point_constants", (
            self.center_xy[0], self.center_xy[1], math.cos(self.yaw), math.sin(self.yaw), float(self.resolution_m),
            int(rows), int(cols), 0.5 * (rows - 1), 0.5 * (cols - 1), max(rows - 2, 0), max(cols - 2, 0)))

    @property
    def rows(self) -> int:
        """Number of cells along the horizontal-frame x axis (forward)."""
        return int(self.heights.shape[0])

    @property
    def cols(self) -> int:
        """Number of cells along the horizontal-frame y axis (left)."""
        return int(self.heights.shape[1])

    def cell_world_xy(self) -> FloatArray:
        """World x, y [m] of every cell centre, shape (rows, cols, 2)."""
        return cell_centers_world_xy(self.center_xy, self.yaw, self.rows, self.cols, self.resolution_m)

    def fractional_index(self, x: ArrayLike, y: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Continuous cell coordinates (r, c) of world points (x, y) [m]; integers are cell centres."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        cos_yaw, sin_yaw = math.cos(self.yaw), math.sin(self.yaw)
        offset_x, offset_y = x - self.center_xy[0], y - self.center_xy[1]
        forward = cos_yaw * offset_x + sin_yaw * offset_y  # world -> horizontal frame (inverse rotation)
        left = -sin_yaw * offset_x + cos_yaw * offset_y
        rows = forward / self.resolution_m + 0.5 * (self.rows - 1)
        cols = left / self.resolution_m + 0.5 * (self.cols - 1)
        return rows, cols

    def cell_index(self, x: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """Index (r, c) of the cell containing world point (x, y) [m]; (-1, -1) outside the grid."""
        rows, cols = self.fractional_index(x, y)
        r, c = np.floor(rows + 0.5), np.floor(cols + 0.5)
        inside = self._inside(rows, cols)
        return (np.where(inside, r, -1).astype(np.intp), np.where(inside, c, -1).astype(np.intp))

    def height_at(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Bilinear height [m] at world points (x, y) [m] between the surrounding cell centres.

        Within half a cell of the border the edge cells are extended; outside the grid, or next to a NaN
        cell, the result is NaN. A scalar (x, y) takes a scalar path with the same arithmetic in the same
        order (a float, bit-identical to the array path's value): controllers query a few points per tick,
        where numpy's per-call overhead was 17 us a point.
        """
        if (isinstance(x, float) and isinstance(y, float)) or (np.ndim(x) == 0 and np.ndim(y) == 0):
            return self._height_at_point(float(x), float(y))
        rows, cols = self.fractional_index(x, y)
        inside = self._inside(rows, cols)
        rows = np.clip(rows, 0.0, self.rows - 1.0)
        cols = np.clip(cols, 0.0, self.cols - 1.0)
        r0 = np.minimum(np.floor(rows), max(self.rows - 2, 0)).astype(np.intp)
        c0 = np.minimum(np.floor(cols), max(self.cols - 2, 0)).astype(np.intp)
        r1, c1 = np.minimum(r0 + 1, self.rows - 1), np.minimum(c0 + 1, self.cols - 1)
        wr, wc = rows - r0, cols - c0
        h = self.heights.astype(np.float64)
        top = (1.0 - wc) * h[r0, c0] + wc * h[r0, c1]
        bottom = (1.0 - wc) * h[r1, c0] + wc * h[r1, c1]
        return np.where(inside, (1.0 - wr) * top + wr * bottom, np.nan)

    def _height_at_point(self, x: float, y: float) -> float:
        cx, cy, cos_yaw, sin_yaw, resolution, n_rows, n_cols, half_rows, half_cols, r_max, c_max = \
            self._point_constants  # type: ignore[attr-defined]
        offset_x, offset_y = x - cx, y - cy
        rows = (cos_yaw * offset_x + sin_yaw * offset_y) / resolution + half_rows
        cols = (-sin_yaw * offset_x + cos_yaw * offset_y) / resolution + half_cols
        if not (-0.5 <= rows < n_rows - 0.5 and -0.5 <= cols < n_cols - 0.5):
            return math.nan
        rows = min(max(rows, 0.0), n_rows - 1.0)
        cols = min(max(cols, 0.0), n_cols - 1.0)
        r0, c0 = min(math.floor(rows), r_max), min(math.floor(cols), c_max)
        r1, c1 = min(r0 + 1, n_rows - 1), min(c0 + 1, n_cols - 1)
        wr, wc = rows - r0, cols - c0
        item = self.heights.item
        top = (1.0 - wc) * item(r0, c0) + wc * item(r0, c1)
        bottom = (1.0 - wc) * item(r1, c0) + wc * item(r1, c1)
        return (1.0 - wr) * top + wr * bottom

    def normals_at(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Unit terrain normals (n, 3) (world) at world points (x, y) [m] (arrays of n), from central
        differences one cell apart of the bilinear heights; straight up where a difference is unknown.
        One array look-up for all points (a controller asks for its four feet every tick)."""
        x = np.asarray(x, dtype=float).reshape(-1)
        y = np.asarray(y, dtype=float).reshape(-1)
        if x.shape != y.shape:
            raise InputError(f"heightmap normals_at needs as many x as y, got {x.size} and {y.size}")
        h = self.resolution_m
        z = self.height_at(np.concatenate([x + h, x - h, x, x]), np.concatenate([y, y, y + h, y - h]))
        z = z.reshape(4, x.size)
        normals = np.empty((x.size, 3))
        normals[:, 0] = -(z[0] - z[1]) / (2 * h)
        normals[:, 1] = -(z[2] - z[3]) / (2 * h)
        normals[:, 2] = 1.0
        normals[~np.isfinite(normals).all(axis=1)] = (0.0, 0.0, 1.0)
        return normals / np.sqrt((normals * normals).sum(axis=1))[:, None]

    def _inside(self, rows: FloatArray, cols: FloatArray) -> NDArray[np.bool_]:
        return (rows >= -0.5) & (rows < self.rows - 0.5) & (cols >= -0.5) & (cols < self.cols - 0.5)


class GridHeights:
    """A heightmap's surface as estimators and controllers take it: ``heights(x, y)`` -> float [m] for one
    point, ``heights.many(xs, ys)`` -> array for several in one look-up (the same values, bit for bit)."""

    __slots__ = ("grid",)

    def __init__(self, grid: HeightMapGrid) -> None:
        self.grid = grid

    def __call__(self, x: float, y: float) -> float:
        return float(self.grid.height_at(x, y))

    def many(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        return self.grid.height_at(x, y)


class GridNormals:
    """A heightmap's terrain normal as the motion generator takes it: ``normals(x, y)`` -> (3,) for one point,
    ``normals.many(xs, ys)`` -> (n, 3) for several in one look-up."""

    __slots__ = ("grid",)

    def __init__(self, grid: HeightMapGrid) -> None:
        self.grid = grid

    def __call__(self, x: float, y: float) -> FloatArray:
        return self.grid.normals_at(x, y)[0]

    def many(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        return self.grid.normals_at(x, y)


def _check_pose(center_xy: ArrayLike, yaw: float, resolution_m: float) -> None:
    center = np.asarray(center_xy, dtype=float)
    if center.shape != (2,) or not np.all(np.isfinite(center)):
        raise InputError(f"heightmap center_xy must be 2 finite values [m], got {center_xy!r}")
    if not math.isfinite(yaw):
        raise InputError(f"heightmap yaw must be finite [rad], got {yaw!r}")
    if not (math.isfinite(resolution_m) and resolution_m > 0.0):
        raise InputError(f"heightmap resolution_m must be a finite value > 0 [m], got {resolution_m!r}")


def cell_centers_world_xy(
    center_xy: tuple[float, float], yaw: float, rows: int, cols: int, resolution_m: float
) -> FloatArray:
    """World x, y [m] of the centres of a rows x cols grid (HeightMap convention), shape (rows, cols, 2)."""
    forward = (np.arange(rows) - 0.5 * (rows - 1)) * resolution_m
    left = (np.arange(cols) - 0.5 * (cols - 1)) * resolution_m
    forward, left = np.meshgrid(forward, left, indexing="ij")
    cos_yaw, sin_yaw = math.cos(yaw), math.sin(yaw)
    world_x = center_xy[0] + cos_yaw * forward - sin_yaw * left
    world_y = center_xy[1] + sin_yaw * forward + cos_yaw * left
    return np.stack([world_x, world_y], axis=-1)


def extract_heightmap(
    course: Course,
    center_xy: tuple[float, float],
    yaw: float,
    rows: int = 33,
    cols: int = 33,
    resolution_m: float = 0.02,
) -> HeightMapGrid:
    """Sample the course's height [m] at the cell centres of a robot-centric grid.

    center_xy [m] world frame (usually the base position), yaw [rad] the base heading. Cells outside the
    course extent are NaN.
    """
    _check_pose(center_xy, yaw, resolution_m)
    for label, count in (("rows", rows), ("cols", cols)):
        if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
            raise InputError(f"heightmap {label} must be an integer >= 1, got {count!r}")
    center = (float(center_xy[0]), float(center_xy[1]))
    xy = cell_centers_world_xy(center, yaw, int(rows), int(cols), resolution_m)
    heights = np.asarray(course.height(xy[..., 0], xy[..., 1]), dtype=np.float32)
    return HeightMapGrid(center_xy=center, yaw=float(yaw), resolution_m=float(resolution_m), heights=heights)
