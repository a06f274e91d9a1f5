"""Heightmaps in the state estimate's (odometry) frame, ROS-free.

A robot builds its elevation map from its own sensors, placed with its own state estimate: the map shares the
estimate's drift, so terrain and base agree where the robot stands, whatever the drift. The simulator knows
the terrain in the true world frame; a controller on the state estimate that reads a world-frame map puts its
footholds where the drifted estimate says the steps are (on the tour's stairs the estimate trailed the truth by
0.1 m in x, 40 % of a step's depth). ``grid_in_estimate_frame`` re-expresses a robot-centric map captured at the
true base pose at the estimated base pose of the same instant: the cells keep their place relative to the
robot (a body-mounted sensor sees the same terrain wherever the estimate puts it), the map's centre and heading
become the estimate's, and the heights move by the estimate's height error. Roll and pitch errors (the attitude
is observable, a few mrad) are not modelled.

``EstimateFrameMaps`` decides which estimate places which map: the map captured at stamp t takes the estimate
of the newest tick of the estimator's grid at or before t (``estimate_period_ns``), and waits for it, so a
lockstep run repeats bit for bit whatever the order in which DDS delivers maps' estimates. A map whose estimate
was skipped is placed with the newest estimate before it once a later one arrives (counted in
``late_estimate_maps``); ``flush`` places every waiting map with the newest estimate there is (a wall-clock
timeout of the caller's, or real time: no waiting). Before any estimate the map stays in the world frame (the
estimator starts from the true pose).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from tal_core.errors import InputError
from tal_core.heightmap import HeightMapGrid
from tal_core.rotations import yaw_from_quat_xyzw
from tal_core.ticks import RecentByStamp

MAX_PENDING_MAPS = 64
"""Maps waiting for their estimate (about 3 s at 20 Hz); the oldest is placed with the newest estimate beyond."""

KEPT_ESTIMATES = 64
"""Recent estimates kept by stamp (0.19 s at 333 Hz): a map's estimate may come before the map."""


@dataclass(frozen=True)
class PlanarPose:
    """The part of a base pose a 2.5-D map depends on: position [m] (world or odometry frame) and yaw [rad]."""

    x: float
    y: float
    z: float
    yaw: float

    @classmethod
    def from_position_quat(cls, position, quat_xyzw) -> PlanarPose:
        p = np.asarray(position, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise InputError(f"PlanarPose: position must be 3 finite values, got {position!r}")
        yaw = float(yaw_from_quat_xyzw(np.asarray(quat_xyzw, dtype=float)))
        if not np.isfinite(yaw):
            raise InputError(f"PlanarPose: orientation has no finite yaw: {quat_xyzw!r}")
        return cls(float(p[0]), float(p[1]), float(p[2]), yaw)


def grid_in_estimate_frame(grid: HeightMapGrid, true_base: PlanarPose, estimate: PlanarPose) -> HeightMapGrid:
    """The robot-centric ``grid`` (world frame, captured with the base at ``true_base``) in the frame of the
    state estimate ``estimate`` of the same instant: each cell keeps its offset from the base, so the centre
    moves by the estimate's horizontal error, the heading by its yaw error and the heights by its height error."""
    dx, dy = grid.center_xy[0] - true_base.x, grid.center_xy[1] - true_base.y
    turn = estimate.yaw - true_base.yaw
    c, s = np.cos(turn), np.sin(turn)
    center = (estimate.x + c * dx - s * dy, estimate.y + s * dx + c * dy)
    yaw = float(np.arctan2(np.sin(grid.yaw + turn), np.cos(grid.yaw + turn)))
    heights = grid.heights + np.float32(estimate.z - true_base.z)
    return HeightMapGrid(center_xy=center, yaw=yaw, resolution_m=grid.resolution_m, heights=heights)


@dataclass(frozen=True)
class PlacedMap:
    stamp_ns: int
    grid: HeightMapGrid
    estimate_stamp_ns: int | None  # the estimate that placed it (None: world frame, no estimate yet)


class EstimateFrameMaps:
    """Places the maps captured at the true pose with the estimate of their instant; see the module docstring.
    ``estimate_period_ns``: the estimator's tick period (its ticks lie on k * period)."""

    def __init__(self, estimate_period_ns: int) -> None:
        if int(estimate_period_ns) <= 0:
            raise InputError(f"EstimateFrameMaps: estimate_period_ns must be > 0, got {estimate_period_ns!r}")
        self.period_ns = int(estimate_period_ns)
        self._pending: deque[tuple[int, HeightMapGrid, PlanarPose]] = deque()
        self._estimates = RecentByStamp(KEPT_ESTIMATES)
        self.placed_maps = 0
        self.late_estimate_maps = 0   # placed with an earlier estimate than their own (skipped or timed out)
        self.world_frame_maps = 0     # placed before any estimate (world frame)
        self.last_offset_m: tuple[float, float, float] | None = None  # estimate - truth of the last placed map

    def expected_stamp(self, map_stamp_ns: int) -> int:
        """The estimator tick whose estimate places a map captured at ``map_stamp_ns``."""
        return (int(map_stamp_ns) // self.period_ns) * self.period_ns

    @property
    def waiting(self) -> int:
        return len(self._pending)

    def add_map(self, stamp_ns: int, grid: HeightMapGrid, true_base: PlanarPose) -> list[PlacedMap]:
        """A map captured at ``stamp_ns`` with the base at ``true_base``: the maps now placed, oldest first."""
        self._pending.append((int(stamp_ns), grid, true_base))
        placed = self._release()
        while len(self._pending) > MAX_PENDING_MAPS:
            placed.append(self._place(*self._pending.popleft()))
        return placed

    def add_estimate(self, stamp_ns: int, pose: PlanarPose) -> list[PlacedMap]:
        """An estimate of ``stamp_ns`` (any order; a repeated stamp replaces nothing): the maps now placed."""
        self._estimates.add(stamp_ns, pose)
        return self._release()

    def flush(self) -> list[PlacedMap]:
        """Every waiting map, placed with the newest estimate at or before its instant, or the newest there is."""
        placed = []
        while self._pending:
            placed.append(self._place(*self._pending.popleft()))
        return placed

    def _release(self) -> list[PlacedMap]:
        placed = []
        while self._pending:
            expected = self.expected_stamp(self._pending[0][0])
            newest = self._estimates.newest_ns
            # its own estimate came, or a later one did (its own was skipped)
            if expected not in self._estimates and (newest is None or newest <= expected):
                break
            placed.append(self._place(*self._pending.popleft()))
        return placed

    def _estimate_for(self, stamp_ns: int) -> tuple[int, PlanarPose] | None:
        return self._estimates.at_or_before(self.expected_stamp(stamp_ns)) or self._estimates.newest()

    def _place(self, stamp_ns: int, grid: HeightMapGrid, true_base: PlanarPose) -> PlacedMap:
        found = self._estimate_for(stamp_ns)
        self.placed_maps += 1
        if found is None:
            self.world_frame_maps += 1
            return PlacedMap(stamp_ns, grid, None)
        estimate_stamp, estimate = found
        if estimate_stamp != self.expected_stamp(stamp_ns):
            self.late_estimate_maps += 1
        self.last_offset_m = (estimate.x - true_base.x, estimate.y - true_base.y, estimate.z - true_base.z)
        return PlacedMap(stamp_ns, grid_in_estimate_frame(grid, true_base, estimate), estimate_stamp)

    def summary(self) -> dict[str, object]:
        return {"placed_maps": self.placed_maps, "late_estimate_maps": self.late_estimate_maps,
                "world_frame_maps": self.world_frame_maps, "waiting_maps": self.waiting,
                "last_offset_m": None if self.last_offset_m is None else [round(v, 4) for v in self.last_offset_m]}
