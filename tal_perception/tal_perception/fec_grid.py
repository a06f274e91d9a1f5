"""Grid operations of the FEC on a heightmap patch: roughness, disc max-filter, erosion, look-ups.

Heights are world z [m] on a rows x cols grid (patch frame, see ``fec_settings``); NaN = unknown.
Two kinds of "no data" are kept apart: cells outside the patch carry no information (ignored), cells
inside the patch that are NaN are unknown terrain (unsafe to step on, treated as an obstacle).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def disc_offsets(radius_m: float, resolution_m: float, include_centre: bool = False) -> list[tuple[int, int]]:
    """Cell offsets (di, dj) within ``radius_m`` [m] of a cell centre (small tolerance for round-off)."""
    k = int(np.floor(radius_m / resolution_m + 1e-9))
    offsets = []
    for di in range(-k, k + 1):
        for dj in range(-k, k + 1):
            if (di or dj or include_centre) and (di * di + dj * dj) * resolution_m**2 <= radius_m**2 + 1e-12:
                offsets.append((di, dj))
    return offsets


def _shifted(padded: NDArray, k: int, di: int, dj: int, rows: int, cols: int) -> NDArray:
    """View of ``padded`` (padded by k) aligned so that [r, c] reads the original cell (r + di, c + dj)."""
    return padded[k + di : k + di + rows, k + dj : k + dj + cols]


def terrain_roughness(
    heights: FloatArray, resolution_m: float, radius_m: float, max_mean_slope: float, max_slope_std: float
) -> BoolArray:
    """TR criterion: True where a candidate is smooth enough (thesis: slope mean and std to neighbours).

    Slopes s_j = (h_j - h_c) / d_j to the neighbours within ``radius_m``; outside-patch neighbours are
    ignored, an unknown (NaN) neighbour or candidate makes the candidate rough.
    """
    rows, cols = heights.shape
    offsets = disc_offsets(radius_m, resolution_m)
    if not offsets:
        return ~np.isnan(heights)
    k = max(max(abs(di), abs(dj)) for di, dj in offsets)
    padded = np.pad(heights, k, constant_values=np.nan)
    inside = np.pad(np.ones_like(heights, dtype=bool), k, constant_values=False)
    unknown = np.isnan(heights)
    total_abs = np.zeros_like(heights)
    total = np.zeros_like(heights)
    total_sq = np.zeros_like(heights)
    count = np.zeros_like(heights)
    for di, dj in offsets:
        neighbour = _shifted(padded, k, di, dj, rows, cols)
        valid = _shifted(inside, k, di, dj, rows, cols)
        missing = np.isnan(neighbour)
        unknown |= valid & missing
        use = valid & ~missing
        slope = np.where(use, neighbour - heights, 0.0) / (resolution_m * np.hypot(di, dj))
        total_abs += np.abs(slope)
        total += slope
        total_sq += slope * slope
        count += use
    n = np.maximum(count, 1.0)
    mean_abs = total_abs / n
    variance = np.maximum(total_sq / n - (total / n) ** 2, 0.0)
    return ~unknown & (mean_abs <= max_mean_slope) & (np.sqrt(variance) <= max_slope_std)


def disc_max(heights: FloatArray, resolution_m: float, radius_m: float) -> FloatArray:
    """Highest terrain [m] within ``radius_m`` of every cell centre, outside-patch cells ignored.

    Unknown cells count as terrain as high as the highest known cell of the patch (a conservative
    finite guess: an occluded hole is not a wall, an unseen wall cannot be guessed), +inf if nothing
    is known."""
    rows, cols = heights.shape
    offsets = disc_offsets(radius_m, resolution_m, include_centre=True)
    k = max(max(abs(di), abs(dj)) for di, dj in offsets)
    unknown = np.isnan(heights)
    fill = float(np.max(heights[~unknown])) if not unknown.all() else np.inf
    solid = np.where(unknown, fill, heights)
    padded = np.pad(solid, k, constant_values=-np.inf)
    result = np.full_like(heights, -np.inf)
    for di, dj in offsets:
        np.maximum(result, _shifted(padded, k, di, dj, rows, cols), out=result)
    return result


def erode(safe: BoolArray, resolution_m: float, radius_m: float) -> BoolArray:
    """Uncertainty margin: a candidate stays safe only if every cell within ``radius_m`` is safe too
    (outside-patch cells ignored). Binary erosion with a disc."""
    rows, cols = safe.shape
    offsets = disc_offsets(radius_m, resolution_m)
    if not offsets:
        return safe.copy()
    k = max(max(abs(di), abs(dj)) for di, dj in offsets)
    padded = np.pad(safe, k, constant_values=True)
    result = safe.copy()
    for di, dj in offsets:
        result &= _shifted(padded, k, di, dj, rows, cols)
    return result


class PatchLookup:
    """Nearest-cell look-up of a (rows, cols) grid at patch-frame points (x, y) [m]; points outside
    the patch get ``outside_value``."""

    def __init__(self, grid: FloatArray, resolution_m: float, outside_value: float = -np.inf) -> None:
        self.rows, self.cols = grid.shape
        self.inv_res = 1.0 / resolution_m
        self.flat = np.append(grid.reshape(-1), outside_value)  # last entry: outside
        self.half_r, self.half_c = 0.5 * (self.rows - 1), 0.5 * (self.cols - 1)

    def __call__(self, x: FloatArray, y: FloatArray) -> FloatArray:
        r = np.rint(x * self.inv_res + self.half_r)
        c = np.rint(y * self.inv_res + self.half_c)
        inside = (r >= 0) & (r < self.rows) & (c >= 0) & (c < self.cols)
        index = np.where(inside, r * self.cols + c, self.rows * self.cols).astype(np.intp)
        return self.flat[index]


def cell_xy(rows: int, cols: int, resolution_m: float) -> tuple[FloatArray, FloatArray]:
    """Patch-frame x, y [m] of every cell centre, each (rows, cols)."""
    x = (np.arange(rows) - 0.5 * (rows - 1)) * resolution_m
    y = (np.arange(cols) - 0.5 * (cols - 1)) * resolution_m
    return np.meshgrid(x, y, indexing="ij")


class DiscGather:
    """Precomputed neighbour gathers of a rows x cols grid for a disc of offsets: ``values(grid, fill)``
    gives (n_offsets, rows * cols) neighbour values (``fill`` outside the grid) in one indexing
    operation, which is much faster than one shifted view per offset on a 33 x 33 patch."""

    def __init__(self, rows: int, cols: int, offsets: list[tuple[int, int]], resolution_m: float) -> None:
        self.rows, self.cols = rows, cols
        self.k = max([max(abs(di), abs(dj)) for di, dj in offsets] + [0])
        width = cols + 2 * self.k
        r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
        base = ((r + self.k) * width + (c + self.k)).reshape(-1)
        self.index = np.array([base + di * width + dj for di, dj in offsets], dtype=np.intp).reshape(len(offsets), -1)
        rr = r.reshape(-1)[None, :] + np.array([o[0] for o in offsets], dtype=int)[:, None]
        cc = c.reshape(-1)[None, :] + np.array([o[1] for o in offsets], dtype=int)[:, None]
        self.inside = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)
        self.inv_distance = 1.0 / np.maximum(resolution_m * np.hypot(*np.array(offsets, dtype=float).T), 1e-12)

    def values(self, grid: NDArray, fill: float | bool, cells: NDArray[np.intp] | None = None) -> NDArray:
        """(n_offsets, n) neighbour values of all cells, or of the flat indices ``cells``."""
        padded = np.full((self.rows + 2 * self.k, self.cols + 2 * self.k), fill, dtype=grid.dtype)
        padded[self.k : self.k + self.rows, self.k : self.k + self.cols] = grid
        return padded.reshape(-1)[self.index if cells is None else self.index[:, cells]]


class PatchGrids:
    """The FEC's grid operations for one patch shape and the settings' radii (tables built once)."""

    def __init__(
        self, rows: int, cols: int, resolution_m: float, roughness_radius_m: float, leg_radius_m: float,
        foot_radius_m: float, margin_radius_m: float,
    ) -> None:  # fmt: skip
        self.shape = (rows, cols)
        self.resolution_m = resolution_m
        self.x, self.y = (a.reshape(-1) for a in cell_xy(rows, cols, resolution_m))
        self.roughness = DiscGather(rows, cols, disc_offsets(roughness_radius_m, resolution_m), resolution_m)
        self.leg = DiscGather(rows, cols, disc_offsets(leg_radius_m, resolution_m, True), resolution_m)
        self.foot = DiscGather(rows, cols, disc_offsets(foot_radius_m, resolution_m, True), resolution_m)
        self.margin = DiscGather(rows, cols, disc_offsets(margin_radius_m, resolution_m), resolution_m)

    def roughness_ok(
        self, heights: FloatArray, max_mean_slope: float, max_slope_std: float, cells: NDArray[np.intp] | None = None
    ) -> BoolArray:
        """Same as ``terrain_roughness``, flat result for the flat indices ``cells`` (all if None)."""
        h = heights.reshape(-1)
        g = self.roughness
        inside = g.inside
        if cells is not None:
            h, inside = h[cells], inside[:, cells]
        unknown = np.isnan(h)
        if g.index.size == 0:
            return ~unknown
        neighbours = g.values(heights, np.nan, cells)
        missing = np.isnan(neighbours)
        unknown = unknown | np.any(inside & missing, axis=0)
        use = inside & ~missing
        slope = np.where(use, neighbours - h, 0.0) * g.inv_distance[:, None]
        count = np.maximum(use.sum(axis=0), 1)
        mean = slope.sum(axis=0) / count
        mean_abs = np.abs(slope).sum(axis=0) / count
        variance = np.maximum((slope * slope).sum(axis=0) / count - mean * mean, 0.0)
        return ~unknown & (mean_abs <= max_mean_slope) & (variance <= max_slope_std * max_slope_std)

    def highest(self, heights: FloatArray, gather: DiscGather) -> FloatArray:
        """Same as ``disc_max`` with the gather's disc, shape (rows, cols)."""
        unknown = np.isnan(heights)
        fill = float(np.max(heights[~unknown])) if not unknown.all() else np.inf
        solid = np.where(unknown, fill, heights)
        return gather.values(solid, -np.inf).max(axis=0).reshape(self.shape)

    def erode(self, safe: BoolArray) -> BoolArray:
        """Same as ``erode`` with the margin disc, shape (rows, cols)."""
        if self.margin.index.size == 0:
            return safe.copy()
        return safe & self.margin.values(safe, True).all(axis=0).reshape(self.shape)
