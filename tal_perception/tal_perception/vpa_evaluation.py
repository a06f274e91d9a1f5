"""Pose evaluation of the VPA: the number of safe footholds NSF of one leg map at every sampled hip height.

Thesis (ViTAL, "pose evaluation"): the FEC tuple (H, z_h, twist, gait) is evaluated for every hip height
z_h of a finite set and NSF(z_h) = number of safe cells after the uncertainty margin. Calling the FEC
31 times redoes work that does not depend on z_h. What is shared here (patch frame, see ``fec_settings``):

* the grids, the hip motion, the lift-off point and the sample instants (``FootholdEvaluator.prepare``);
* terrain roughness (TR) and the foot-trajectory collision (FC): both compare terrain with terrain and the
  swing foot, none of which moves with the hip height;
* the swing-foot positions of every candidate at every instant, and the hip's horizontal positions.

Only kinematic feasibility (KF) and leg collision (LC) depend on z_h. They are evaluated on a shrinking
set of (height, cell) pairs, one instant at a time: a cell can only count if every cell within the
uncertainty margin is safe, so after each instant only the cells within the margin of a still possible
safe candidate are kept (dilate(erode(ok))). Instants whose foot position is the same for every cell
(the lift-off sample) are evaluated once per height. Per instant, KF & LC equal the FEC's (an
unreachable foot is never within the limits, so ``clear | ~reachable`` reduces to ``clear``).

The result equals ``FootholdEvaluator.evaluate(...).safe_count`` at each height (tested);
``reference_counts`` is that slow loop.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tal_core.legs import Leg
from tal_perception.errors import PerceptionInputError
from tal_perception.fec import FootholdEvaluator, PreparedPatch
from tal_perception.fec_grid import disc_offsets
from tal_perception.fec_settings import FecInput, GaitTiming

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def whole_swing(gait: GaitTiming) -> GaitTiming:
    """The VPA asks "how many footholds could this leg reach from here": the whole swing is evaluated."""
    return dataclasses.replace(gait, swing_time_left_s=gait.swing_duration_s)


def map_reference_height(heights: FloatArray) -> float:
    """[m] reference terrain height of a leg map: the median of its known cells (NaN if none known)."""
    known = heights[~np.isnan(heights)]
    return float(np.median(known)) if known.size else float("nan")


@dataclass(frozen=True, eq=False)
class PoseEvaluation:
    """NSF of one leg map over the sampled hip heights.

    hip_heights (N,) [m] above ``reference_m``; nsf (N,) number of safe cells; reference_m [m] world z of
    the map's reference terrain height (median of its known cells); cells the patch's cell count.
    """

    leg: Leg
    hip_heights: FloatArray
    nsf: NDArray[np.int64]
    reference_m: float
    cells: int


class PoseEvaluator:
    """Exact pose evaluation (FEC at every hip height) for the legs of the evaluator's robot."""

    def __init__(self, evaluator: FootholdEvaluator, hip_heights: FloatArray) -> None:
        self.evaluator = evaluator
        self.hip_heights = np.asarray(hip_heights, dtype=float)
        settings = evaluator.settings
        n = settings.patch_cells
        offsets = disc_offsets(settings.uncertainty_margin_m, settings.resolution_m, include_centre=True)
        self._margin_pad = max([max(abs(a), abs(b)) for a, b in offsets])
        self._margin_offsets = offsets
        self._shape = (n, n)

    # -- stacked morphology over heights --------------------------------------------------------------
    def _erode(self, ok: BoolArray) -> BoolArray:
        """Erosion of a (H, rows, cols) stack with the margin disc, outside the patch ignored (= safe)."""
        k, (rows, cols) = self._margin_pad, self._shape
        padded = np.pad(ok, ((0, 0), (k, k), (k, k)), constant_values=True)
        result = ok.copy()
        for di, dj in self._margin_offsets:
            result &= padded[:, k + di : k + di + rows, k + dj : k + dj + cols]
        return result

    def _dilate(self, ok: BoolArray) -> BoolArray:
        k, (rows, cols) = self._margin_pad, self._shape
        padded = np.pad(ok, ((0, 0), (k, k), (k, k)), constant_values=False)
        result = ok.copy()
        for di, dj in self._margin_offsets:
            result |= padded[:, k + di : k + di + rows, k + dj : k + dj + cols]
        return result

    # -- evaluation ------------------------------------------------------------------------------------
    def evaluate(self, leg: Leg, heights: FloatArray, twist: FloatArray, gait: GaitTiming) -> PoseEvaluation:
        """NSF at every sampled hip height of the map ``heights`` (rows, cols) [m] world z, centred on the
        leg's hip projection (patch frame = horizontal frame); twist (6,) [m/s, rad/s] horizontal frame."""
        heights = np.asarray(heights, dtype=float)
        reference = map_reference_height(heights) if heights.ndim == 2 else float("nan")
        nsf = np.zeros(self.hip_heights.size, dtype=np.int64)
        if np.isnan(reference):  # nothing known (or a malformed map, rejected by FecInput below)
            inp = self._input(leg, heights, 0.0, twist, gait)
            return PoseEvaluation(inp.leg, self.hip_heights.copy(), nsf, reference, heights.size)
        inp = self._input(leg, heights, reference, twist, gait)
        ev = self.evaluator
        ev.check_patch(inp)
        prep = ev.prepare(inp)
        known = np.flatnonzero(~np.isnan(prep.cand_z))
        base = np.zeros(heights.size, dtype=bool)
        base[known] = ev._foot_trajectory_ok(prep, known)  # noqa: SLF001 - same package, height independent
        base &= ev.roughness_ok(prep)
        ok = np.broadcast_to(base.reshape(self._shape), (self.hip_heights.size, *self._shape)).copy()
        ok = self._dilate(self._erode(ok)) & ok  # cells that can matter for the count at all
        for instant in self._instants(prep):
            if not ok.any():
                break
            ok = self._apply_instant(prep, instant, ok)
            ok = self._dilate(self._erode(ok)) & ok
        nsf = self._erode(ok).reshape(self.hip_heights.size, -1).sum(axis=1).astype(np.int64)
        return PoseEvaluation(inp.leg, self.hip_heights.copy(), nsf, reference, heights.size)

    def reference_counts(self, leg: Leg, heights: FloatArray, twist: FloatArray, gait: GaitTiming) -> NDArray:
        """The slow reference: ``FootholdEvaluator.evaluate`` once per hip height (same inputs)."""
        heights = np.asarray(heights, dtype=float)
        reference = map_reference_height(heights)
        if np.isnan(reference):
            return np.zeros(self.hip_heights.size, dtype=np.int64)
        return np.array(
            [
                self.evaluator.evaluate(self._input(leg, heights, reference + h, twist, gait)).safe_count
                for h in self.hip_heights
            ],
            dtype=np.int64,
        )

    def _input(
        self, leg: Leg, heights: FloatArray, height: float, twist: FloatArray, gait: GaitTiming
    ) -> FecInput:
        if not isinstance(gait, GaitTiming):
            raise PerceptionInputError(f"VPA: gait must be a GaitTiming, got {type(gait).__name__}")
        # The map is centred on the hip's projection at touchdown: hip_touchdown_xy = patch origin.
        return FecInput(leg, heights, height, twist, whole_swing(gait), hip_touchdown_xy=np.zeros(2))

    @staticmethod
    def _patch_top(prep: PreparedPatch) -> float:
        """[m] highest value of the leg-radius max-filtered terrain (the LC look-up table)."""
        return float(np.max(prep.leg_terrain.flat[:-1]))

    def _instants(self, prep: PreparedPatch) -> list[tuple[FloatArray, FloatArray, FloatArray, FloatArray]]:
        """Foot centres (x, y, z), each (cells,), and the hip xy (2,) [m] of every KF/LC instant, patch
        frame: touchdown and next lift-off first (they reject most), then the swing samples."""
        ev = self.evaluator
        gait = prep.inp.gait
        every = np.arange(prep.cand_x.size)
        sx, sy, sz = ev._swing_centres(prep, every, prep.swing_times)  # noqa: SLF001 - same package
        td_z = prep.cand_z + ev.foot_radius_m
        hips = prep.hip_touchdown + prep.hip_velocity * np.concatenate(
            [[0.0, gait.stance_duration_s], prep.swing_times - gait.swing_duration_s]
        )[:, None]
        instants = [(prep.cand_x, prep.cand_y, td_z, hips[0]), (prep.cand_x, prep.cand_y, td_z, hips[1])]
        instants += [(sx[i], sy[i], sz[i], hips[2 + i]) for i in range(sx.shape[0])]
        # Instants with one foot point for all cells (the swing start) cost one IK per height and can
        # remove whole heights: they go first (stable sort keeps the order of the others).
        return sorted(instants, key=lambda instant: not _same_point(instant[0], instant[1], instant[2]))

    def _apply_instant(
        self, prep: PreparedPatch, instant: tuple[FloatArray, FloatArray, FloatArray, FloatArray], ok: BoolArray
    ) -> BoolArray:
        """ok & (IK within limits and leg clear of the terrain at this instant) for the alive pairs."""
        fx, fy, fz, hip = instant
        ev = self.evaluator
        g = ev.kinematics.geometry[prep.inp.leg]
        s = ev.settings
        flat = ok.reshape(ok.shape[0], -1)
        alive_h, alive_c = np.nonzero(flat)
        uniform = _same_point(fx, fy, fz)
        if uniform:  # same foot point for every cell (swing start): once per alive height
            first = int(np.flatnonzero(~np.isnan(fz))[0])
            heights_alive = np.unique(alive_h)
            pair_h, pair_c = heights_alive, np.full(heights_alive.size, first)
        else:
            pair_h, pair_c = alive_h, alive_c
        # patch frame -> base frame (level base at hip height z_h): subtract the hip, add the HAA origin
        bx = float(g.haa_origin[0] - hip[0])
        by = float(g.haa_origin[1] - hip[1])
        bz = float(g.haa_origin[2]) - (prep.inp.hip_height_m + self.hip_heights[pair_h])
        px, py, pz = fx[pair_c], fy[pair_c], fz[pair_c]
        ik = ev.kinematics.inverse_xyz(prep.inp.leg, px + bx, py + by, pz + bz)
        good = ik.within_limits
        idx = np.flatnonzero(good)
        if idx.size:
            b = (bx, by, bz[idx])
            knee = [ik.knee_xyz[i][idx] - b[i] for i in range(3)]
            hfe = [ik.hfe_xyz[i][idx] - b[i] for i in range(3)]
            foot = (px[idx], py[idx], pz[idx])
            thigh_f, shin_f = (f[:, None] for f in ev._segment_fractions[prep.inp.leg])  # noqa: SLF001
            points = [np.concatenate([hfe[i] + (knee[i] - hfe[i]) * thigh_f, knee[i] + (foot[i] - knee[i]) * shin_f])
                      for i in range(3)]  # fmt: skip
            lowest = points[2] - (s.leg_radius_m + s.leg_clearance_m)
            # Exact shortcut: a leg whose every point is above the patch's highest terrain is clear
            # without looking anything up (unknown cells count as the highest known, see fec_grid).
            clear = lowest.min(axis=0) >= self._patch_top(prep)
            check = np.flatnonzero(~clear)
            if check.size:
                terrain = prep.leg_terrain(points[0][:, check], points[1][:, check])
                clear[check] = (lowest[:, check] >= terrain).all(axis=0)
            good[idx] = clear
        result = np.zeros_like(flat)
        if uniform:
            passed = np.zeros(self.hip_heights.size, dtype=bool)
            passed[pair_h[good]] = True
            result = flat & passed[:, None]
        else:
            result[alive_h[good], alive_c[good]] = True
        return result.reshape(ok.shape)


def _same_point(x: FloatArray, y: FloatArray, z: FloatArray) -> bool:
    """True if every known (non-NaN z) cell has exactly the same foot point."""
    known = ~np.isnan(z)
    if not known.any():
        return False
    return bool(np.ptp(x[known]) == 0.0 and np.ptp(y[known]) == 0.0 and np.ptp(z[known]) == 0.0)
