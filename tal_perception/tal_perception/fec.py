"""Foothold Evaluation Criteria (FEC): which cells of a heightmap patch are safe footholds for a leg.

Thesis (ViTAL chapter): mu = mu_TR AND mu_LC AND mu_KF AND mu_FC, then candidates within the
uncertainty margin of an unsafe candidate are discarded (erosion). Every cell of the patch is a
candidate foothold; all candidates are evaluated at once with numpy.

Motion model over the gait cycle (patch frame, see ``fec_settings``): the base stays level at the
given hip height; the hip moves at v_hip = v + w_z x r_hip (r_hip: the HAA joint in the base frame);
at touchdown it is at ``hip_touchdown_xy``, ``T_swing - t`` earlier at ``hip_td - v_hip (T_swing - t)``
and at the next lift-off at ``hip_td + v_hip T_stance``. The swing foot follows the shape of
``tal_control.motion.swing.SwingTrajectory`` (rest-to-rest quintics: x, y over the whole swing, z up
to the apex at mid-swing and down again), from the lift-off foothold to the candidate. Footholds are
terrain points; the foot sphere's centre is one foot radius above them.

* TR: slope statistics around the candidate (``fec_grid.terrain_roughness``).
* KF: IK of the leg (``leg_kinematics``) reaches the candidate within the joint limits at touchdown,
  at the next lift-off and at ``swing_samples`` instants of the remaining swing.
* LC: thigh and shin sampled at those instants and at the next lift-off stay clear of the terrain.
* FC: the foot sphere along the remaining swing stays above the terrain.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tal_core.legs import Leg
from tal_core.robot_model import RobotModel
from tal_perception.errors import PerceptionInputError
from tal_perception.fec_grid import PatchGrids, PatchLookup
from tal_perception.fec_settings import FecInput, FecSettings
from tal_perception.leg_kinematics import LegKinematics

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class FecResult:
    """Boolean (rows, cols) maps, True = safe: per criterion, their AND (``raw``) and after the
    uncertainty-margin erosion (``safe``, the thesis' mu). A criterion not evaluated on a cell (an
    earlier one already failed there) is False."""

    terrain_roughness: BoolArray
    kinematic_feasibility: BoolArray
    leg_collision: BoolArray
    foot_trajectory_collision: BoolArray
    raw: BoolArray
    safe: BoolArray

    @property
    def safe_count(self) -> int:
        """Number of safe footholds (NSF in the thesis' VPA)."""
        return int(self.safe.sum())


def swing_hip_rise(rise_m: float, swing_times: FloatArray, swing_duration_s: float) -> FloatArray:
    """(S,) [m] the hip's height above its touchdown height at ``swing_times`` [s] since lift-off, for a hip
    ``rise_m`` [m] higher at lift-off moving linearly in time to its touchdown height (zeros when 0)."""
    if not rise_m:
        return np.zeros(np.shape(swing_times))
    return rise_m * (1.0 - swing_times / swing_duration_s)


def min_jerk(s: FloatArray) -> FloatArray:
    """Rest-to-rest quintic profile 10 s^3 - 15 s^4 + 6 s^5 (s in [0, 1]; not clipped, callers keep
    s in range)."""
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


@dataclass(frozen=True, eq=False)
class PreparedPatch:
    """What every candidate of one FEC input shares (computed once per input, patch frame)."""

    inp: FecInput
    resolution_m: float
    cand_x: FloatArray  # (rows * cols,) [m]
    cand_y: FloatArray
    cand_z: FloatArray  # terrain height [m], NaN unknown
    roughness: NDArray[np.int8]  # (rows * cols,) TR per cell: -1 not evaluated yet, 0 rough, 1 smooth
    leg_terrain: PatchLookup  # highest terrain within the leg radius
    foot_terrain: PatchLookup  # highest terrain within the foot radius
    hip_velocity: FloatArray  # (2,) [m/s]
    hip_touchdown: FloatArray  # (2,) [m]
    liftoff_centre: FloatArray  # (3,) [m] foot centre at lift-off
    swing_times: FloatArray  # (swing_samples,) [s] since lift-off, KF and LC
    trajectory_times: FloatArray  # (trajectory_samples - 1,) [s] since lift-off, FC
    # (swing_samples,) [m] the hip's height above inp.hip_height_m at the swing samples (all 0 unless
    # inp.hip_rise_at_liftoff_m is set)
    swing_hip_dz: FloatArray


class FootholdEvaluator:
    """Evaluates the FEC for the legs of ``model`` with ``settings`` (exact evaluation, no CNN)."""

    def __init__(self, model: RobotModel, settings: FecSettings | None = None) -> None:
        self.settings = settings if settings is not None else FecSettings()
        self.kinematics = LegKinematics(
            model, reach_margin_m=self.settings.reach_margin_m, limit_margin_rad=self.settings.joint_limit_margin_rad
        )
        self.foot_radius_m = self.kinematics.foot_radius_m
        self._grid_cache: dict[tuple[int, int], PatchGrids] = {}
        s = self.settings
        thigh_f = np.linspace(0.0, 1.0, s.leg_points_per_segment)
        self._segment_fractions: dict[Leg, tuple[FloatArray, FloatArray]] = {}
        for g in self.kinematics.geometry:
            shin_length = float(np.linalg.norm(g.foot_xyw - g.knee_xyw))
            shin_end = max(0.0, 1.0 - s.foot_exclusion_m / shin_length)
            self._segment_fractions[g.leg] = (thigh_f, np.linspace(0.0, shin_end, s.leg_points_per_segment))

    def grids(self, rows: int, cols: int) -> PatchGrids:
        """Grid tables (``fec_grid.PatchGrids``) for a rows x cols patch, built on first use and cached."""
        grids = self._grid_cache.get((rows, cols))
        if grids is None:
            s = self.settings
            grids = PatchGrids(
                rows, cols, s.resolution_m, s.roughness_radius_m, s.leg_radius_m, self.foot_radius_m,
                s.uncertainty_margin_m,
            )  # fmt: skip
            self._grid_cache[(rows, cols)] = grids
        return grids

    # -- preparation --------------------------------------------------------------------------------
    def prepare(self, inp: FecInput) -> PreparedPatch:
        """Per-input quantities shared by all candidates: grids, hip motion, lift-off, sample times."""
        s = self.settings
        rows, cols = inp.heights.shape
        res = s.resolution_m
        grids = self.grids(rows, cols)
        heights = inp.heights
        g = self.kinematics.geometry[inp.leg]
        r_hip = g.haa_origin[:2]
        v, w_z = inp.twist[:2], float(inp.twist[5])
        hip_velocity = v + w_z * np.array([-r_hip[1], r_hip[0]])
        gait = inp.gait
        if inp.hip_touchdown_xy is not None:
            hip_td = inp.hip_touchdown_xy
        else:
            hip_td = -0.5 * gait.stance_duration_s * hip_velocity
        if inp.liftoff_xyz is not None:
            liftoff = inp.liftoff_xyz.copy()
        else:
            step = gait.step_length_m(hip_velocity)
            liftoff = np.array([-step[0], -step[1], np.nan])
            row, col = np.rint(-step / res + 0.5 * (np.array([rows, cols]) - 1)).astype(int)
            if 0 <= row < rows and 0 <= col < cols:
                liftoff[2] = heights[row, col]
            if np.isnan(liftoff[2]):
                known = heights[~np.isnan(heights)]
                liftoff[2] = float(np.median(known)) if known.size else inp.hip_height_m - g.max_reach_m
        liftoff[2] += self.foot_radius_m
        t_swing = gait.swing_duration_s
        t_start = t_swing - gait.swing_time_left_s
        swing_times = t_start + (t_swing - t_start) * np.arange(s.swing_samples) / s.swing_samples
        trajectory_times = t_start + (t_swing - t_start) * np.arange(1, s.trajectory_samples) / s.trajectory_samples
        swing_hip_dz = swing_hip_rise(inp.hip_rise_at_liftoff_m, swing_times, t_swing)
        return PreparedPatch(
            inp=inp,
            resolution_m=res,
            cand_x=grids.x,
            cand_y=grids.y,
            cand_z=heights.reshape(-1),
            roughness=np.full(rows * cols, -1, dtype=np.int8),
            leg_terrain=PatchLookup(grids.highest(heights, grids.leg), res),
            foot_terrain=PatchLookup(grids.highest(heights, grids.foot), res),
            hip_velocity=hip_velocity,
            hip_touchdown=np.asarray(hip_td, dtype=float),
            liftoff_centre=liftoff,
            swing_times=swing_times,
            trajectory_times=trajectory_times,
            swing_hip_dz=swing_hip_dz,
        )

    # -- evaluation ---------------------------------------------------------------------------------
    def evaluate(self, inp: FecInput) -> FecResult:
        """All four criteria on every candidate of the patch, their AND and the eroded result."""
        self.check_patch(inp)
        prep = self.prepare(inp)
        shape = inp.heights.shape
        known = ~np.isnan(prep.cand_z)
        everything = np.flatnonzero(known)
        kf, lc, fc = (np.zeros(known.size, dtype=bool) for _ in range(3))
        kf[everything], lc[everything] = self._kinematics_and_collision(prep, everything)
        fc[everything] = self._foot_trajectory_ok(prep, everything)
        tr = self.roughness_ok(prep)
        raw = tr & kf & lc & fc
        safe = self.grids(*shape).erode(raw.reshape(shape))
        return FecResult(
            tr.reshape(shape), kf.reshape(shape), lc.reshape(shape), fc.reshape(shape), raw.reshape(shape), safe
        )

    def roughness_ok(self, prep: PreparedPatch, cells: NDArray[np.intp] | None = None) -> BoolArray:
        """TR of the flat cell indices ``cells`` (all if None), evaluated once per cell and cached."""
        todo = np.flatnonzero(prep.roughness < 0) if cells is None else cells[prep.roughness[cells] < 0]
        if todo.size:
            s = self.settings
            grids = self.grids(*prep.inp.heights.shape)
            everything = todo.size == prep.roughness.size
            ok = grids.roughness_ok(prep.inp.heights, s.max_mean_slope, s.max_slope_std, None if everything else todo)
            prep.roughness[todo] = ok
        return (prep.roughness if cells is None else prep.roughness[cells]) == 1

    def raw_safety(self, prep: PreparedPatch, cells: NDArray[np.intp]) -> BoolArray:
        """AND of the four criteria on the flat cell indices ``cells`` only, cheapest criteria first
        (TR, FC, KF, then LC on the survivors). For lazy searches such as the VFA's."""
        result = np.zeros(cells.size, dtype=bool)
        alive = self.roughness_ok(prep, cells)
        if alive.any():
            idx = np.flatnonzero(alive)
            alive[idx] = self._foot_trajectory_ok(prep, cells[idx])
        if alive.any():
            idx = np.flatnonzero(alive)
            kf, lc = self._kinematics_and_collision(prep, cells[idx], skip_infeasible=True)
            result[idx] = kf & lc
        return result

    def check_patch(self, inp: FecInput) -> None:
        """PerceptionInputError unless the patch has the settings' shape (patch_cells x patch_cells)."""
        n = self.settings.patch_cells
        if inp.heights.shape != (n, n):
            raise PerceptionInputError(
                f"FEC: heights must have the settings' patch shape ({n}, {n}), got {inp.heights.shape}"
            )

    # -- criteria -------------------------------------------------------------------------------------
    def _swing_centres(
        self, prep: PreparedPatch, cells: NDArray[np.intp], times: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Foot-centre positions (len(times), n) [m] of the swing to each candidate at ``times`` [s]."""
        gait = prep.inp.gait
        t_swing = gait.swing_duration_s
        lo = prep.liftoff_centre
        td_x, td_y = prep.cand_x[cells], prep.cand_y[cells]
        td_z = prep.cand_z[cells] + self.foot_radius_m
        phase = (times / t_swing)[:, None]
        s_xy = min_jerk(phase)
        x = lo[0] + (td_x - lo[0]) * s_xy
        y = lo[1] + (td_y - lo[1]) * s_xy
        apex = np.maximum(lo[2], td_z) + gait.step_height_m
        rising = phase < 0.5
        s_z = min_jerk(np.where(rising, 2.0 * phase, 2.0 * phase - 1.0))
        z = np.where(rising, lo[2] + (apex - lo[2]) * s_z, apex + (td_z - apex) * s_z)
        return x, y, z

    def _foot_trajectory_ok(self, prep: PreparedPatch, cells: NDArray[np.intp]) -> BoolArray:
        """FC: the foot sphere along the remaining swing stays above the terrain (ends excluded)."""
        s = self.settings
        x, y, z = self._swing_centres(prep, cells, prep.trajectory_times)
        lo = prep.liftoff_centre
        td_x, td_y = prep.cand_x[cells], prep.cand_y[cells]
        td_z = prep.cand_z[cells] + self.foot_radius_m
        near_sq = s.foot_exclusion_m**2
        near_end = ((x - lo[0]) ** 2 + (y - lo[1]) ** 2 + (z - lo[2]) ** 2 < near_sq) | (
            (x - td_x) ** 2 + (y - td_y) ** 2 + (z - td_z) ** 2 < near_sq
        )
        clear = z - self.foot_radius_m - s.foot_clearance_m >= prep.foot_terrain(x, y)
        return np.all(clear | near_end, axis=0)

    def _kinematics_and_collision(
        self, prep: PreparedPatch, cells: NDArray[np.intp], skip_infeasible: bool = False
    ) -> tuple[BoolArray, BoolArray]:
        """KF and LC over the swing samples, touchdown and next lift-off: one batched IK call and one
        batched terrain look-up for all (instant, candidate) pairs. With ``skip_infeasible`` LC is only
        evaluated where KF holds (False elsewhere)."""
        inp = prep.inp
        leg, gait = inp.leg, inp.gait
        g = self.kinematics.geometry[leg]
        s = self.settings
        sx, sy, sz = self._swing_centres(prep, cells, prep.swing_times)  # (S, n)
        td_z = prep.cand_z[cells] + self.foot_radius_m
        fx = np.vstack([sx, prep.cand_x[cells], prep.cand_x[cells]])  # (C, n), C = S + 2 instants
        fy = np.vstack([sy, prep.cand_y[cells], prep.cand_y[cells]])
        fz = np.vstack([sz, td_z, td_z])
        dt = np.concatenate([prep.swing_times - gait.swing_duration_s, [0.0, gait.stance_duration_s]])
        hip = prep.hip_touchdown + prep.hip_velocity * dt[:, None]  # (C, 2)
        # patch frame -> base frame (level base): subtract the hip, add the HAA origin in the base frame
        b = ((g.haa_origin[0] - hip[:, 0])[:, None], (g.haa_origin[1] - hip[:, 1])[:, None])
        if inp.hip_rise_at_liftoff_m:  # the hip moves down (or up) during the swing: one height per instant
            hip_z = np.concatenate([inp.hip_height_m + prep.swing_hip_dz, [inp.hip_height_m] * 2])
            b = (*b, (float(g.haa_origin[2]) - hip_z)[:, None])
        else:
            b = (*b, float(g.haa_origin[2]) - inp.hip_height_m)
        ik = self.kinematics.inverse_xyz(leg, (fx + b[0]).ravel(), (fy + b[1]).ravel(), (fz + b[2]).ravel())
        shape = fx.shape
        kf = np.all(ik.within_limits.reshape(shape), axis=0)
        lc = np.zeros_like(kf)
        columns = np.flatnonzero(kf) if skip_infeasible else slice(None)
        if skip_infeasible and columns.size == 0:
            return kf, lc
        knee = [ik.knee_xyz[i].reshape(shape)[:, columns] - b[i] for i in range(3)]
        hfe = [ik.hfe_xyz[i].reshape(shape)[:, columns] - b[i] for i in range(3)]
        foot = (fx[:, columns], fy[:, columns], fz[:, columns])
        thigh_f, shin_f = (f[:, None, None] for f in self._segment_fractions[leg])  # (P, 1, 1)
        points = []
        for i in range(3):
            thigh = hfe[i] + (knee[i] - hfe[i]) * thigh_f  # (P, C, n)
            shin = knee[i] + (foot[i] - knee[i]) * shin_f
            points.append(np.concatenate([thigh, shin]))
        px, py, pz = points  # NaN where IK failed: the look-up sees "outside" there, reachable masks it
        clear = pz - (s.leg_radius_m + s.leg_clearance_m) >= prep.leg_terrain(px, py)
        reachable = ik.reachable.reshape(shape)[:, columns]
        lc[columns] = np.all(np.all(clear, axis=0) | ~reachable, axis=0)
        return kf, lc
