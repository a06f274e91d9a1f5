"""VPA planner: when to update the body pose reference, from the gait state and the latest heightmap.

The ``vpa`` node is a thin adapter over this module (no rclpy here). It updates on the gait state's
stamps (the control ticks, sim time): every ``update_period_s`` of them (thesis: 5 Hz; with the CNN the
default is 20 Hz), so a lockstep simulation gives the same references on every run. The base pose comes
from the gait state as the vfa's does: heading from the hips (front minus hind), base origin from the
hips' centre and the robot's hip offsets (level base), twist = the commanded twist in the horizontal
frame. Two sources:

* ``vpa``: ``PoseAdapter`` (exact pose evaluation or the CNN, receding horizon N_h, L-BFGS-B);
* ``tbr``: the thesis' baseline, a plane through the latest selected footholds (the vfa's, else the
  gait state's targets) and a constant height above it.

A missing or stale map holds the default pose (flagged in the result's status); malformed gait states
raise ``VfaInputError`` (from ``GaitSnapshot``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tal_core.heightmap import HeightMapGrid
from tal_core.legs import NUM_LEGS
from tal_core.robot_model import RobotModel
from tal_perception.errors import VfaInputError, VpaConfigError
from tal_perception.fec_settings import GaitTiming
from tal_perception.tbr import TerrainBasedReference
from tal_perception.vfa_planner import GaitSnapshot, HipFrame
from tal_perception.vpa import PoseAdapter, VpaStatus
from tal_perception.vpa_settings import VpaSettings

FloatArray = NDArray[np.float64]
SOURCES = ("vpa", "tbr")
CLOCK_RESET_S = 0.5  # [s] a stamp this far behind the last one is a restarted clock


@dataclass(frozen=True, eq=False)
class PoseReference:
    """One body pose reference (``tal_msgs/BodyPoseReference``): source "vpa" or "tbr"; base_height_m [m]
    world z of the base origin; roll_rad, pitch_rad [rad]; hip_heights_m (4,) [m] world z implied;
    safe_footholds (4,) [-] (VPA, stage 1; zeros for TBR); horizon_s [s]; optimal: the solver converged
    (False when a pose was held); status: the VPA's status value or "tbr"; elapsed_s [s] computation."""

    stamp_s: float
    source: str
    base_height_m: float
    roll_rad: float
    pitch_rad: float
    hip_heights_m: FloatArray
    safe_footholds: NDArray[np.int64]
    horizon_s: float
    optimal: bool
    status: str
    elapsed_s: float


class PosePlanner:
    """Body pose references for one robot from gait states, heightmaps and (TBR) selected footholds."""

    def __init__(self, model: RobotModel, source: str = "vpa", *, use_cnn: bool = True,
                 update_period_s: float = 0.05, tbr_height_m: float | None = None,
                 settings: VpaSettings | None = None) -> None:
        if source not in SOURCES:
            raise VpaConfigError(f"source must be one of {list(SOURCES)}, got {source!r}")
        if not (math.isfinite(update_period_s) and update_period_s > 0.0):
            raise VpaConfigError(f"update_period_s must be a finite value > 0 [s], got {update_period_s!r}")
        self.source = source
        self.update_period_s = float(update_period_s)
        self.settings = settings if settings is not None else VpaSettings()
        nsf_model = None
        if source == "vpa" and use_cnn:
            from tal_perception.vpa_cnn import CnnNsfModel  # torch: imported only when asked for

            nsf_model = CnnNsfModel.load()
        self.adapter = PoseAdapter(model, self.settings, nsf_model=nsf_model) if source == "vpa" else None
        height = model.nominal_base_height_m if tbr_height_m is None else float(tbr_height_m)
        self.tbr = TerrainBasedReference(height)
        self.hips = HipFrame.from_model(model)
        self._grid: HeightMapGrid | None = None
        self._map_stamp_s: float | None = None
        self._footholds: FloatArray | None = None  # (4, 3) latest selected footholds (TBR)
        self._last_update_s: float | None = None
        self._last_stamp_s: float | None = None
        self.updates = 0
        self.restarts = 0
        self.last_result = None  # the PoseAdapter's last VpaResult (source vpa), with its diagnostics

    def set_map(self, grid: HeightMapGrid, stamp_s: float) -> None:
        """The latest heightmap and its stamp [s]; older than the one in use: ``VfaInputError``."""
        if self._map_stamp_s is not None and stamp_s < self._map_stamp_s:
            if stamp_s < self._map_stamp_s - CLOCK_RESET_S:
                self._restart()
            else:
                raise VfaInputError("heightmap_out_of_order", f"heightmap stamp {stamp_s:.4f} s is before the "
                                    f"one in use ({self._map_stamp_s:.4f} s)")
        self._grid, self._map_stamp_s = grid, float(stamp_s)

    def set_foothold(self, leg: int, xyz: ArrayLike) -> None:
        """A selected foothold (3,) [m] world of ``leg`` (the vfa's), used by the TBR baseline."""
        point = np.asarray(xyz, dtype=float).reshape(-1)
        if point.shape != (3,) or not np.all(np.isfinite(point)):
            raise VfaInputError("foothold_invalid", f"foothold must be 3 finite values [m], got {xyz!r}")
        if not 0 <= int(leg) < NUM_LEGS:
            raise VfaInputError("foothold_invalid", f"unknown leg {leg!r}")
        if self._footholds is None:
            self._footholds = np.full((NUM_LEGS, 3), np.nan)
        self._footholds[int(leg)] = point

    def wants(self, stamp_ns: int) -> bool:
        """Whether ``update`` would do more than skip a gait state stamped ``stamp_ns`` (an update is due, or the
        stamp is behind the last one: a restart or an out-of-order sample to reject). A node may leave the
        others undeserialised (the gait state comes at 250 Hz, an update every ``update_period_s``)."""
        stamp = stamp_ns * 1e-9
        return (self._last_update_s is None or (self._last_stamp_s is not None and stamp < self._last_stamp_s)
                or stamp - self._last_update_s >= self.update_period_s - 1e-9)

    def update(self, gait: GaitSnapshot, targets_world: ArrayLike | None = None) -> PoseReference | None:
        """A new reference when ``update_period_s`` of gait-state time passed since the last one, else None.
        ``targets_world`` (4, 3) [m]: the gait state's touchdown targets (TBR without vfa footholds)."""
        stamp = float(gait.stamp_s)
        if self._last_stamp_s is not None and stamp < self._last_stamp_s:
            if stamp < self._last_stamp_s - CLOCK_RESET_S:
                self._restart()
            else:
                raise VfaInputError("gait_state_out_of_order", f"gait state stamp {stamp:.4f} s is before the "
                                    f"last one ({self._last_stamp_s:.4f} s)")
        self._last_stamp_s = stamp
        if self._last_update_s is not None and stamp - self._last_update_s < self.update_period_s - 1e-9:
            return None
        self._last_update_s = stamp
        self.updates += 1
        yaw = self.hips.heading(gait.hip_position)
        base = self.hips.base_position(gait.hip_position, yaw)
        start = time.perf_counter()
        if self.adapter is not None:
            map_age = math.inf if self._map_stamp_s is None else stamp - self._map_stamp_s
            timing = GaitTiming(float(gait.step_frequency_hz) if gait.step_frequency_hz > 0 else 1.0,
                                float(gait.duty_factor) if 0.0 < gait.duty_factor < 1.0 else 0.5, 0.0,
                                max(float(gait.step_height_m), 0.0))
            result = self.adapter.update(self._grid, base, yaw, gait.base_twist, timing,
                                         map_age_s=max(map_age, 0.0) if self._grid is not None else 0.0)
            self.last_result = result
            return PoseReference(stamp, "vpa", result.base_height_m, result.roll_rad, result.pitch_rad,
                                 np.asarray(result.hip_heights_m, dtype=float),
                                 np.asarray(result.safe_footholds, dtype=np.int64), result.horizon_s,
                                 bool(result.optimal), result.status.value, time.perf_counter() - start)
        footholds = self._footholds_for_tbr(targets_world)
        if footholds is None:
            return None
        tbr = self.tbr.reference(footholds, yaw)
        hips = self._hip_heights(np.array([tbr.base_height_m, tbr.roll_rad, tbr.pitch_rad]))
        return PoseReference(stamp, "tbr", tbr.base_height_m, tbr.roll_rad, tbr.pitch_rad, hips,
                             np.zeros(NUM_LEGS, dtype=np.int64), 0.0, True, "tbr", time.perf_counter() - start)

    # -- helpers ------------------------------------------------------------------------------------
    def _footholds_for_tbr(self, targets_world: ArrayLike | None) -> FloatArray | None:
        points = None if self._footholds is None else self._footholds.copy()
        if targets_world is not None:
            targets = np.asarray(targets_world, dtype=float).reshape(NUM_LEGS, 3)
            points = targets if points is None else np.where(np.isfinite(points), points, targets)
        if points is None or np.isfinite(points).all(axis=1).sum() < 3:
            return None
        return points[np.isfinite(points).all(axis=1)]

    def _hip_heights(self, pose: FloatArray) -> FloatArray:
        """(4,) [m] world z of the hips for pose (base height [m], roll, pitch [rad]; Cardan, roll first)."""
        height, roll, pitch = pose
        x, y, z = self.hips.offsets_base.T
        cp = math.cos(pitch)
        return height - math.sin(pitch) * x + cp * math.sin(roll) * y + cp * math.cos(roll) * z

    def _restart(self) -> None:
        self.restarts += 1
        self._grid, self._map_stamp_s, self._footholds = None, None, None
        self._last_update_s = self._last_stamp_s = None
        if self.adapter is not None:
            self.adapter.reset()


__all__ = ["SOURCES", "PosePlanner", "PoseReference", "VpaStatus"]
