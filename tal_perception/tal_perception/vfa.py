"""Vision-based Foothold Adaptation (VFA) with the exact foothold evaluation g (thesis, ViTAL chapter).

Pipeline per swinging leg: (1) heightmap extraction: a patch of the robot's map centred on the
nominal foothold, aligned with the horizontal frame (base yaw); (2) foothold evaluation: the FEC
(``fec``) and g = the safe candidate closest to the nominal foothold; (3) trajectory adjustment is the
swing generator's job (``tal_control.motion.swing.SwingTrajectory.retarget``).

The evaluation is lazy: candidates are visited in order of distance from the nominal (ties: row-major
order) in chunks (the 16 closest, then 64, then the rest), and only the cells a chunk needs (its
candidates and their neighbours within the uncertainty margin) are evaluated. After the first chunk,
the terrain roughness of the whole patch is computed and candidates that fail it within the margin are
skipped. The first safe candidate is g; the result equals a full evaluation followed by the argmin
(``select_foothold(..., lazy=False)`` does exactly that, and the tests check it).

A leg with no safe candidate, a missing map or a stale map never raises: the nominal foothold is
passed through and the result says why (``VfaStatus``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tal_core.heightmap import HeightMapGrid
from tal_core.legs import Leg
from tal_perception.errors import FecConfigError, PerceptionInputError
from tal_perception.fec import FootholdEvaluator, PreparedPatch
from tal_perception.fec_grid import disc_offsets
from tal_perception.fec_settings import FecInput, GaitTiming

FloatArray = NDArray[np.float64]
_FUTURE_TOLERANCE_S = 1e-3  # [s] a map stamped this far after "now" is still accepted (clock jitter)
# Lazy search schedule: the closest viable candidates in chunks of these sizes, then all the rest at once
# (one large batch is cheaper than many small ones once the neighbourhood of the nominal is unsafe).
_CHUNKS = (16, 64)


class VfaStatus(Enum):
    """Why the selected foothold is what it is."""

    SELECTED = "selected"  # a safe candidate was found (possibly the nominal itself)
    NO_SAFE_CANDIDATE = "no_safe_candidate"  # every candidate is unsafe: nominal passed through
    NO_MAP = "no_map"  # no heightmap yet: nominal passed through
    STALE_MAP = "stale_map"  # heightmap older than max_map_age_s: nominal passed through


@dataclass(frozen=True, eq=False)
class VfaResult:
    """Foothold decision for one leg. Positions (3,) [m] world frame; the selected z is the terrain
    height of the selected cell (the nominal's own z when it is passed through)."""

    leg: Leg
    nominal: FloatArray
    selected: FloatArray
    any_safe: bool
    status: VfaStatus
    safe_candidates: int | None  # number of safe candidates (None: unknown, lazy search or no map)
    offset_cells: tuple[int, int] | None  # (d_row, d_col) of the selection from the patch centre

    @property
    def adapted(self) -> bool:
        """True if the selected foothold differs from the nominal one."""
        return bool(self.offset_cells is not None and self.offset_cells != (0, 0))


@dataclass(frozen=True, eq=False)
class FootholdRequest:
    """One leg's VFA inputs (the arguments of ``FootholdSelector.select`` for that leg)."""

    leg: Leg
    nominal_world: ArrayLike  # (3,) [m] world frame
    hip_height_m: float  # [m] world z of the leg's HAA joint
    twist: ArrayLike  # (6,) [m/s, rad/s] horizontal frame
    gait: GaitTiming
    liftoff_world: ArrayLike | None = None  # (3,) [m]; the CNN selector: only its exact verification uses it
    hip_touchdown_world: ArrayLike | None = None  # (2,) [m]; likewise


def check_map_age(map_age_s: float, who: str) -> None:
    """PerceptionInputError unless ``map_age_s`` [s] (now minus the map's stamp) is finite and not more
    than the clock jitter tolerance in the future; ``who`` names the caller in the message."""
    if isinstance(map_age_s, bool) or not isinstance(map_age_s, (int, float, np.floating)) \
            or not math.isfinite(map_age_s):
        raise PerceptionInputError(f"{who}: map_age_s must be finite [s], got {map_age_s!r}")
    if map_age_s < -_FUTURE_TOLERANCE_S:
        raise PerceptionInputError(
            f"{who}: the heightmap is stamped {-map_age_s:.4f} s in the future (out-of-order stamps)")


def map_status(grid: HeightMapGrid | None, map_age_s: float, max_map_age_s: float) -> VfaStatus | None:
    """NO_MAP / STALE_MAP when the nominal is to be passed through (``map_age_s`` [s], already checked by
    ``check_map_age``, older than ``max_map_age_s``), else None."""
    if grid is None:
        return VfaStatus.NO_MAP
    return VfaStatus.STALE_MAP if map_age_s > max_map_age_s else None


def patch_heading(grid: HeightMapGrid, yaw: float | None) -> float:
    """The patches' heading [rad] (world): ``yaw``, or the map's when None; PerceptionInputError if not finite."""
    heading = grid.yaw if yaw is None else float(yaw)
    if not math.isfinite(heading):
        raise PerceptionInputError(f"VFA: yaw must be finite [rad], got {yaw!r}")
    return heading


def extract_patch(grid: HeightMapGrid, center_xy: ArrayLike, yaw: float, cells: int, resolution_m: float) -> FloatArray:
    """Heights (cells, cells) [m] around ``center_xy`` [m] (world), rows along the heading ``yaw``
    [rad]: nearest cell of ``grid`` at each patch cell centre; outside ``grid`` NaN (unknown).
    ``extract_patches`` for one centre."""
    return extract_patches(grid, np.asarray(center_xy, dtype=float)[:2], yaw, cells, resolution_m)[0]


def extract_patches(
    grid: HeightMapGrid, centers_xy: ArrayLike, yaw: float, cells: int, resolution_m: float,
    out: NDArray[np.floating] | None = None,
) -> NDArray[np.floating]:
    """Heights (B, cells, cells) [m] around each of ``centers_xy`` (B, 2) [m] (world), rows along ``yaw``
    [rad]: the nearest cell of ``grid`` at each patch cell centre, NaN outside ``grid``. A patch with the
    grid's heading and resolution is a shifted slice of it. Written into ``out`` when given (float32 holds
    the grid's float32 heights exactly), else into a new float64 array.

    Why batched: the CNN selector and the VPA extract one patch per leg per call; one pass saves the
    meshgrid and index set-up of each (~10 us per patch)."""
    centers = np.asarray(centers_xy, dtype=float).reshape(-1, 2)
    b = centers.shape[0]
    if out is None:
        out = np.empty((b, cells, cells))
    if abs(math.remainder(yaw - grid.yaw, 2.0 * math.pi)) < 1e-9 and abs(resolution_m - grid.resolution_m) < 1e-12:
        for k, (x, y) in enumerate(centers.tolist()):
            r0, c0 = _nearest_cell(grid, x, y)
            _copy_aligned(grid, r0 - cells // 2, c0 - cells // 2, out[k])
        return out
    forward, left = _patch_offsets(cells, resolution_m)
    c, s = math.cos(yaw), math.sin(yaw)
    x = centers[:, 0, None, None] + c * forward - s * left
    y = centers[:, 1, None, None] + s * forward + c * left
    rows, cols = grid.cell_index(x, y)
    inside = rows >= 0
    out[...] = np.nan
    out[inside] = grid.heights[rows[inside], cols[inside]]
    return out


def _nearest_cell(grid: HeightMapGrid, x: float, y: float) -> tuple[int, int]:
    """(row, col) of the cell whose centre is nearest to world (x, y) [m] (may lie outside ``grid``):
    ``HeightMapGrid.fractional_index`` then floor(. + 0.5), in the same order of double-precision operations
    on Python floats (the same result as ``cell_index`` inside the grid; ~8 us less than the array call)."""
    cos_yaw, sin_yaw = math.cos(grid.yaw), math.sin(grid.yaw)
    offset_x, offset_y = x - grid.center_xy[0], y - grid.center_xy[1]
    forward = cos_yaw * offset_x + sin_yaw * offset_y
    left = -sin_yaw * offset_x + cos_yaw * offset_y
    rows = forward / grid.resolution_m + 0.5 * (grid.rows - 1)
    cols = left / grid.resolution_m + 0.5 * (grid.cols - 1)
    return math.floor(rows + 0.5), math.floor(cols + 0.5)


def _copy_aligned(grid: HeightMapGrid, r0: int, c0: int, out: NDArray[np.floating]) -> None:
    """The aligned patch into ``out`` (cells, cells): the grid's cells from row ``r0``, column ``c0`` on, NaN
    off the grid."""
    cells = out.shape[0]
    src_r = slice(max(r0, 0), min(r0 + cells, grid.rows))
    src_c = slice(max(c0, 0), min(c0 + cells, grid.cols))
    if src_r.stop - src_r.start == cells and src_c.stop - src_c.start == cells:
        out[...] = grid.heights[src_r, src_c]  # the common case: the patch lies inside the map
        return
    out[...] = np.nan
    if src_r.start < src_r.stop and src_c.start < src_c.stop:
        out[src_r.start - r0 : src_r.stop - r0, src_c.start - c0 : src_c.stop - c0] = grid.heights[src_r, src_c]


@lru_cache(maxsize=4)
def _patch_offsets(cells: int, resolution_m: float) -> tuple[FloatArray, FloatArray]:
    """(forward, left) (cells, cells) [m] of each patch cell centre from the patch centre (read-only)."""
    offsets = (np.arange(cells) - 0.5 * (cells - 1)) * resolution_m
    forward, left = np.meshgrid(offsets, offsets, indexing="ij")
    forward.setflags(write=False)
    left.setflags(write=False)
    return forward, left


class FootholdSelector:
    """The VFA's foothold evaluation for all legs: owns the FEC evaluator and the search order."""

    def __init__(self, evaluator: FootholdEvaluator, max_map_age_s: float = 0.5) -> None:
        if not (math.isfinite(max_map_age_s) and max_map_age_s > 0.0):
            raise FecConfigError(f"max_map_age_s must be a finite value > 0 [s], got {max_map_age_s!r}")
        self.evaluator = evaluator
        self.max_map_age_s = float(max_map_age_s)
        settings = evaluator.settings
        n = settings.patch_cells
        centre = n // 2
        r, c = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        dist_sq = ((r - centre) ** 2 + (c - centre) ** 2).reshape(-1)
        self._order = np.argsort(dist_sq, kind="stable")  # closest first, ties in row-major order
        offsets = disc_offsets(settings.uncertainty_margin_m, settings.resolution_m, include_centre=True)
        rows = r.reshape(-1)[:, None] + np.array([o[0] for o in offsets])
        cols = c.reshape(-1)[:, None] + np.array([o[1] for o in offsets])
        inside = (rows >= 0) & (rows < n) & (cols >= 0) & (cols < n)
        self._neighbours = np.where(inside, rows * n + cols, -1)  # (n*n, k), -1 = outside (ignored)

    def select(
        self,
        leg: Leg,
        nominal_world: ArrayLike,
        grid: HeightMapGrid | None,
        *,
        hip_height_m: float,
        twist: ArrayLike,
        gait: GaitTiming,
        yaw: float | None = None,
        map_age_s: float = 0.0,
        liftoff_world: ArrayLike | None = None,
        hip_touchdown_world: ArrayLike | None = None,
        lazy: bool = True,
    ) -> VfaResult:
        """g: the safe foothold closest to ``nominal_world`` (3,) [m] (world frame).

        grid: the robot's heightmap (None: no map yet). hip_height_m [m] world z of the leg's HAA
        joint; twist (6,) base twist [m/s, rad/s] in the horizontal frame; gait the leg's timing; yaw
        [rad] heading of the horizontal frame (default: the map's); map_age_s [s] now minus the map's
        stamp; liftoff_world (3,) [m] the foothold the swing started from (default: one step behind);
        hip_touchdown_world (2,) [m] where the leg's HAA joint will be at touchdown (default: half a
        stance behind the nominal, the Raibert rule).
        """
        nominal = _vector(nominal_world, 3, "nominal_world")
        check_map_age(map_age_s, "VFA")
        leg = Leg(leg)
        status = map_status(grid, map_age_s, self.max_map_age_s)
        if status is not None:
            return VfaResult(leg, nominal, nominal.copy(), False, status, None, None)
        settings = self.evaluator.settings
        heading = patch_heading(grid, yaw)
        heights = extract_patch(grid, nominal[:2], heading, settings.patch_cells, settings.resolution_m)
        c, s = math.cos(heading), math.sin(heading)
        liftoff = None
        if liftoff_world is not None:
            lo = _vector(liftoff_world, 3, "liftoff_world")
            dx, dy = lo[0] - nominal[0], lo[1] - nominal[1]
            liftoff = np.array([c * dx + s * dy, -s * dx + c * dy, lo[2]])
        hip_td = None
        if hip_touchdown_world is not None:
            hip = _vector(hip_touchdown_world, 2, "hip_touchdown_world")
            dx, dy = hip[0] - nominal[0], hip[1] - nominal[1]
            hip_td = np.array([c * dx + s * dy, -s * dx + c * dy])
        inp = FecInput(leg, heights, hip_height_m, twist, gait, hip_touchdown_xy=hip_td, liftoff_xyz=liftoff)
        if lazy:
            index, count = self._lazy_search(inp), None
        else:
            result = self.evaluator.evaluate(inp)
            safe = result.safe.reshape(-1)[self._order]
            index = int(self._order[np.argmax(safe)]) if safe.any() else None
            count = result.safe_count
        if index is None:
            return VfaResult(leg, nominal, nominal.copy(), False, VfaStatus.NO_SAFE_CANDIDATE, count, None)
        n = settings.patch_cells
        d_row, d_col = index // n - n // 2, index % n - n // 2
        forward, left = d_row * settings.resolution_m, d_col * settings.resolution_m
        selected = np.array(
            [nominal[0] + c * forward - s * left, nominal[1] + s * forward + c * left, heights.reshape(-1)[index]]
        )
        return VfaResult(leg, nominal, selected, True, VfaStatus.SELECTED, count, (int(d_row), int(d_col)))

    def _lazy_search(self, inp: FecInput) -> int | None:
        """Flat index of the closest candidate that is safe after erosion, or None."""
        self.evaluator.check_patch(inp)
        prep = self.evaluator.prepare(inp)
        n_cells = inp.heights.size
        raw = np.full(n_cells + 1, -1, dtype=np.int8)  # -1 unknown, 0 unsafe, 1 safe; last: outside
        raw[-1] = 1
        head = self._order[: _CHUNKS[0]]
        found = self._search_chunk(prep, head, raw)
        if found is not None:
            return found
        # The nominal's neighbourhood is unsafe: TR of the whole patch now tells which candidates can
        # never be safe (TR fails within the margin); only the others are visited, closest first.
        smooth = self.evaluator.roughness_ok(prep)
        raw[:-1][~smooth] = 0
        viable = self.evaluator.grids(*inp.heights.shape).erode(smooth.reshape(inp.heights.shape)).reshape(-1)
        rest = self._order[_CHUNKS[0] :]
        order = rest[viable[rest]]
        bounds = [0, *np.cumsum(_CHUNKS[1:]).tolist(), order.size]
        for start, stop in zip(bounds[:-1], bounds[1:]):
            found = self._search_chunk(prep, order[start:stop], raw)
            if found is not None:
                return found
        return None

    def _search_chunk(self, prep: PreparedPatch, candidates: NDArray[np.intp], raw: NDArray[np.int8]) -> int | None:
        """Evaluate what ``candidates`` need (themselves and their margin neighbours, cached in ``raw``)
        and return the first one (in the given order) that is safe after erosion."""
        if candidates.size == 0:
            return None
        needed = self._neighbours[candidates]  # (m, k), -1 = outside the patch (index -1 of raw: safe)
        todo = np.unique(needed[needed >= 0])
        todo = todo[raw[todo] < 0]
        if todo.size:
            raw[todo] = self.evaluator.raw_safety(prep, todo)
        safe = np.all(raw[needed] == 1, axis=1)
        return int(candidates[np.argmax(safe)]) if safe.any() else None


def select_foothold(
    selector: FootholdSelector,
    leg: Leg,
    nominal_world: ArrayLike,
    grid: HeightMapGrid | None,
    **kwargs: object,
) -> VfaResult:
    """Functional form of ``FootholdSelector.select`` (same arguments)."""
    return selector.select(leg, nominal_world, grid, **kwargs)  # type: ignore[arg-type]


def _vector(value: object, size: int, name: str) -> FloatArray:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as error:
        raise PerceptionInputError(f"VFA: {name}: cannot convert to a float array ({error})") from None
    if array.shape != (size,) or not np.isfinite(array).all():
        raise PerceptionInputError(f"VFA: {name} must be {size} finite values, got {value!r}")
    return array


__all__ = [
    "FootholdRequest", "FootholdSelector", "VfaResult", "VfaStatus", "extract_patch", "extract_patches", "map_status",
    "patch_heading", "select_foothold",
]  # fmt: skip
