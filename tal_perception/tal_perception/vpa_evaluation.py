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
(the lift-off sample) are evaluated once per height, and a height left without any possible safe cell
is dropped from the stack. Per instant, KF & LC equal the FEC's (an unreachable foot is never within
the limits, so ``clear | ~reachable`` reduces to ``clear``); the knee and hip joint positions are only
built for the legs within the joint limits, and the terrain is only looked up for the sample points
below the patch's highest terrain (of the segments whose lowest end reaches below it). The pairs of an
instant go to the IK and LC in blocks of a few whole layers (``_BLOCK_PAIRS``: larger arrays made the
allocator return memory to the kernel and page-fault it back on every instant). Every number is
computed with the same floating-point operations as the FEC's, so the counts are identical, not merely
close.

The result equals ``FootholdEvaluator.evaluate(...).safe_count`` at each height (tested);
``reference_counts`` is that slow loop. With the swing model "terrain" (``VpaSettings.swing_hip_model``,
ours) the hip at the swing samples is higher than the evaluated height by ``FecInput.hip_rise_at_liftoff_m``
times the swing still to go (``liftoff_rise``); the equality holds for it too.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tal_core.legs import Leg
from tal_perception.errors import PerceptionInputError, VpaConfigError
from tal_perception.fec import FootholdEvaluator, PreparedPatch, swing_hip_rise
from tal_perception.fec_grid import disc_offsets
from tal_perception.fec_settings import FecInput, GaitTiming
from tal_perception.leg_kinematics import CellTerms, JointOrigins
from tal_perception.vpa_settings import SWING_HIP_MODELS

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
# [-] most (height, cell) pairs per IK / LC batch (see _apply_instant): 5 whole layers of a 33 x 33 patch,
# float64 arrays of 43.6 kB. Whole update on the bench scenes, CPU time vs 4096: 0.94-0.95 (more
# faults, fewer batches); 6000 and more page-fault again (2,100 / 9,200 faults per update at 6000 / 8000).
_BLOCK_PAIRS = 5445


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

    def __init__(self, evaluator: FootholdEvaluator, hip_heights: FloatArray, swing_hip_model: str = "level") -> None:
        if swing_hip_model not in SWING_HIP_MODELS:
            raise VpaConfigError(f"swing_hip_model must be one of {SWING_HIP_MODELS}, got {swing_hip_model!r}")
        self.evaluator = evaluator
        self.hip_heights = np.asarray(hip_heights, dtype=float)
        self.swing_hip_model = swing_hip_model
        settings = evaluator.settings
        n = settings.patch_cells
        offsets = disc_offsets(settings.uncertainty_margin_m, settings.resolution_m, include_centre=False)
        self._margin_shifts = [_flat_shift(di, dj, n, n) for di, dj in offsets]
        self._shape = (n, n)

    # -- stacked morphology over heights --------------------------------------------------------------
    def _erode(self, ok: BoolArray) -> BoolArray:
        """Erosion of a (H, rows, cols) stack with the margin disc, outside the patch ignored (= safe)."""
        flat = ok.reshape(ok.shape[0], ok.shape[1] * ok.shape[2])  # (H, cells), also for H = 0
        result = flat.copy()
        for target, source, outside in self._margin_shifts:
            result[:, target] &= flat[:, source] if outside is None else flat[:, source] | outside
        return result.reshape(ok.shape)

    def _dilate(self, ok: BoolArray) -> BoolArray:
        """Dilation of a (H, rows, cols) stack with the margin disc, outside the patch = False."""
        flat = ok.reshape(ok.shape[0], ok.shape[1] * ok.shape[2])  # (H, cells), also for H = 0
        result = flat.copy()
        for target, source, outside in self._margin_shifts:
            result[:, target] |= flat[:, source] if outside is None else flat[:, source] & ~outside
        return result.reshape(ok.shape)

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
        rise = self.liftoff_rise(prep, reference)
        if rise:  # what prepare would give with the rise (only the hip's heights at the swing samples change)
            inp = dataclasses.replace(inp, hip_rise_at_liftoff_m=rise)
            prep = dataclasses.replace(prep, inp=inp, swing_hip_dz=swing_hip_rise(rise, prep.swing_times,
                                                                                 inp.gait.swing_duration_s))
        known = np.flatnonzero(~np.isnan(prep.cand_z))
        base = np.zeros(heights.size, dtype=bool)
        base[known] = ev._foot_trajectory_ok(prep, known)  # noqa: SLF001 - same package, height independent
        base &= ev.roughness_ok(prep)
        # The stack holds one layer per hip height still in play (``rows``: their indices): a height
        # without any possible safe cell left is dropped, the remaining instants never look at it again.
        layer = base.reshape(1, *self._shape)
        layer = self._dilate(self._erode(layer)) & layer  # cells that can matter for the count at all
        ok = np.broadcast_to(layer, (self.hip_heights.size, *self._shape)).copy()
        rows = np.arange(self.hip_heights.size)
        top = self._patch_top(prep)
        for instant in self._instants(prep):
            ok, rows = _drop_empty(ok, rows)
            if rows.size == 0:
                break
            ok = self._apply_instant(prep, instant, ok, self.hip_heights[rows], top)
            ok = self._dilate(self._erode(ok)) & ok
        ok, rows = _drop_empty(ok, rows)
        nsf[rows] = self._erode(ok).sum(axis=(1, 2))
        return PoseEvaluation(inp.leg, self.hip_heights.copy(), nsf, reference, heights.size)

    def reference_counts(self, leg: Leg, heights: FloatArray, twist: FloatArray, gait: GaitTiming) -> NDArray:
        """The slow reference: ``FootholdEvaluator.evaluate`` once per hip height (same inputs)."""
        heights = np.asarray(heights, dtype=float)
        reference = map_reference_height(heights)
        if np.isnan(reference):
            return np.zeros(self.hip_heights.size, dtype=np.int64)
        rise = 0.0
        if self.swing_hip_model != "level":  # the lift-off point, from a prepared patch
            prep = self.evaluator.prepare(self._input(leg, heights, reference, twist, gait))
            rise = self.liftoff_rise(prep, reference)
        counts = []
        for h in self.hip_heights:
            inp = dataclasses.replace(self._input(leg, heights, reference + h, twist, gait), hip_rise_at_liftoff_m=rise)
            counts.append(self.evaluator.evaluate(inp).safe_count)
        return np.array(counts, dtype=np.int64)

    def liftoff_rise(self, prep: PreparedPatch, reference_m: float) -> float:
        """[m] how much higher the hip is at lift-off than at touchdown under ``swing_hip_model``: 0 for
        "level" (the thesis: the evaluated hip height for the whole swing); for "terrain" the lift-off
        foot's terrain height minus the map reference ``reference_m`` [m] (the trunk follows the terrain:
        the hip starts the swing as high above the lift-off terrain as it ends above the map reference).

        Why: stepping down a stair, the lift-off foot is still on the upper tread behind the hip. With the
        hip held at a height that reaches the lower tread, that leg would be folded past its joint limits
        at lift-off, so (level model) the front legs' safe footholds only exist at hip heights from which
        the lower tread is barely reachable, and the VPA kept the trunk high going down."""
        if self.swing_hip_model == "level":
            return 0.0
        return float(prep.liftoff_centre[2] - self.evaluator.foot_radius_m - reference_m)

    def _input(self, leg: Leg, heights: FloatArray, height: float, twist: FloatArray, gait: GaitTiming) -> FecInput:
        if not isinstance(gait, GaitTiming):
            raise PerceptionInputError(f"VPA: gait must be a GaitTiming, got {type(gait).__name__}")
        # The map is centred on the hip's projection at touchdown: hip_touchdown_xy = patch origin.
        return FecInput(leg, heights, height, twist, whole_swing(gait), hip_touchdown_xy=np.zeros(2))

    @staticmethod
    def _patch_top(prep: PreparedPatch) -> float:
        """[m] highest value of the leg-radius max-filtered terrain (the LC look-up table)."""
        return float(np.max(prep.leg_terrain.flat[:-1]))

    def _instants(self, prep: PreparedPatch) -> list[_Instant]:
        """The KF/LC instants, patch frame: next lift-off and touchdown first (they reject most), then the
        swing samples from the latest; instants with one foot point for every cell first of all (see
        ``_Instant``).

        Any order gives the same counts (an instant only removes pairs, and the pruning after each one
        keeps every pair that can still matter), but the later instants see fewer pairs when the ones
        that reject most come first. Each alone, on the pairs left after the swing start of the 320
        bench leg maps: lift-off rejects 41 %, touchdown 38 %, the swing samples 25 / 17 / 9 % (latest
        first); this order evaluates 1.4 % fewer pairs than touchdown, lift-off, earliest sample first."""
        ev = self.evaluator
        gait = prep.inp.gait
        every = np.arange(prep.cand_x.size)
        sx, sy, sz = ev._swing_centres(prep, every, prep.swing_times)  # noqa: SLF001 - same package
        td_z = prep.cand_z + ev.foot_radius_m
        hips = (
            prep.hip_touchdown
            + prep.hip_velocity
            * np.concatenate([[0.0, gait.stance_duration_s], prep.swing_times - gait.swing_duration_s])[:, None]
        )
        points = [(prep.cand_x, prep.cand_y, td_z), (prep.cand_x, prep.cand_y, td_z)]
        points += [(sx[i], sy[i], sz[i]) for i in range(sx.shape[0])]
        hip_dz = [0.0, 0.0, *prep.swing_hip_dz.tolist()]  # next lift-off, touchdown: at the evaluated height
        instants = [
            _Instant(x, y, z, hip, _same_point(x, y, z), dz) for (x, y, z), hip, dz in zip(points, hips, hip_dz)
        ]
        instants = [instants[1], instants[0], *instants[:1:-1]]  # lift-off, touchdown, latest sample first
        # Instants with one foot point for all cells (the swing start) cost one IK per height and can
        # remove whole heights: they go first (stable sort keeps the order of the others).
        return sorted(instants, key=lambda instant: not instant.uniform)

    def _apply_instant(
        self, prep: PreparedPatch, instant: _Instant, ok: BoolArray, hip_heights: FloatArray, top: float
    ) -> BoolArray:
        """ok & (IK within limits and leg clear of the terrain at this instant) for the alive pairs of the
        stack ok (H', rows, cols) whose layers are at ``hip_heights`` (H',) [m] above the reference; top
        [m] the patch top (``_patch_top``).

        The pairs go to the IK and LC in blocks of at most ``_BLOCK_PAIRS`` (whole layers), so that the
        IK's float arrays stay below 64 kB: when glibc frees a chunk that reaches 64 kB (merged with its
        free neighbours) it consolidates the heap and returns the free top to the kernel, and the next
        arrays are page-faulted in again. With one batch per instant (up to ~13,000 pairs) an update
        took ~5,100 minor faults (~2 us each on this VM), with these blocks ~500-800. The numbers are
        element-wise, so blocks give the same results."""
        g = self.evaluator.kinematics.geometry[prep.inp.leg]
        flat = ok.reshape(ok.shape[0], -1)
        # patch frame -> base frame (level base at hip height z_h): subtract the hip, add the HAA origin.
        # x and y only depend on the cell, z only on the cell and the height: both sums are made on the
        # small per-cell / per-height arrays and gathered (the same sums, element by element).
        shift = (float(g.haa_origin[0] - instant.hip[0]), float(g.haa_origin[1] - instant.hip[1]))
        terms = self.evaluator.kinematics.cell_terms(prep.inp.leg, instant.x + shift[0], instant.y + shift[1])
        bz_height = float(g.haa_origin[2]) - ((prep.inp.hip_height_m + hip_heights) + instant.hip_dz)  # (H',)
        if instant.uniform:  # same foot point for every cell (swing start): once per alive height
            alive = np.flatnonzero(flat.any(axis=1))
            cells = np.full(alive.size, int(np.flatnonzero(~np.isnan(instant.z))[0]))
            good = self._pairs_ok(prep, instant, terms, cells, bz_height[alive], shift, top)
            passed = np.zeros(hip_heights.size, dtype=bool)
            passed[alive[good]] = True
            return (flat & passed[:, None]).reshape(ok.shape)
        result = flat.copy()
        for rows in _layer_blocks(flat.sum(axis=1), _BLOCK_PAIRS):
            pair_h, pair_c = np.nonzero(flat[rows])
            good = self._pairs_ok(prep, instant, terms, pair_c, bz_height[rows][pair_h], shift, top)
            result[rows][flat[rows]] = good  # np.nonzero's pairs are in the order of the boolean mask
        return result.reshape(ok.shape)

    def _pairs_ok(
        self, prep: PreparedPatch, instant: _Instant, terms: CellTerms, cells: NDArray[np.intp], bz: FloatArray,
        shift: tuple[float, float], top: float,
    ) -> BoolArray:  # fmt: skip
        """KF & LC of N (height, cell) pairs: foot cells (N,), terms the cells' part of the IK's frame
        change (``LegKinematics.cell_terms``), bz (N,) the pairs' z shift, base frame [m]; shift the x
        and y patch -> base shift [m]; top [m] the patch top."""
        z = instant.z[cells] + bz
        within, origins = self.evaluator.kinematics.within_limits_cells(prep.inp.leg, terms, z, cells)
        good = within  # becomes within & clear below
        idx = np.flatnonzero(within)
        if idx.size:
            good[idx] = self._leg_clear(prep, instant, origins, cells[idx], (*shift, bz[idx]), top)
        return good

    def _leg_clear(
        self, prep: PreparedPatch, instant: _Instant, origins: JointOrigins, cells: NDArray[np.intp],
        shift: tuple[float, float, FloatArray], top: float,
    ) -> BoolArray:  # fmt: skip
        """LC of M feasible legs: thigh and shin points (patch frame) clear of the leg-radius max-filtered
        terrain. origins (M) in the base frame, cells (M,) their foot cells, shift the base -> patch
        shift (bx, by, bz (M,)) [m], top [m] the patch top."""
        ev = self.evaluator
        s = ev.settings
        thigh_f, shin_f = ev._segment_fractions[prep.inp.leg]  # noqa: SLF001 - same package
        lift = s.leg_radius_m + s.leg_clearance_m
        knee_z, hfe_z, foot_z = origins.knee(2) - shift[2], origins.hfe(2) - shift[2], instant.z[cells]
        # Exact shortcut: a segment whose every point is above the patch's highest terrain is clear
        # without looking anything up (unknown cells count as the highest known, see fec_grid). A point
        # a + (b - a) f is monotonic in f in floating point too (each rounding is), so the lowest point
        # of a segment is one of its two end samples. (min(p) - lift is the min of p - lift exactly, as
        # rounding is monotonic.)
        thigh_low = _lowest_end(hfe_z, knee_z, thigh_f) - lift
        shin_low = _lowest_end(knee_z, foot_z, shin_f) - lift
        clear = np.ones(cells.size, dtype=bool)  # a leg collides iff a point below the top collides
        segments = ((True, thigh_f, hfe_z, knee_z, thigh_low), (False, shin_f, knee_z, foot_z, shin_low))
        for on_thigh, fractions, start_z, end_z, low in segments:
            legs = np.flatnonzero(~(low >= top))  # ~(>=): a NaN would be looked up, as the FEC does
            if legs.size:
                hit = self._segment_hits(prep, instant, origins, cells, shift, top, on_thigh, legs, fractions,
                                         (start_z[legs], end_z[legs]))  # fmt: skip
                clear[hit] = False
        return clear

    def _segment_hits(
        self, prep: PreparedPatch, instant: _Instant, origins: JointOrigins, cells: NDArray[np.intp],
        shift: tuple[float, float, FloatArray], top: float, on_thigh: bool, legs: NDArray[np.intp],
        fractions: FloatArray, ends_z: tuple[FloatArray, FloatArray],
    ) -> NDArray[np.intp]:  # fmt: skip
        """Entries of ``legs`` (K,) whose thigh (``on_thigh``) or shin has a sample point in collision;
        ends_z (K,) the segment's start and end z [m] patch frame, fractions (P,) its samples.

        Only the points below the patch top are built in x and y and looked up (most legs in doubt
        have one or two, near the foot): a point at or above the top is clear of any cell's terrain
        (same comparison, same numbers as looking every point up)."""
        s = self.evaluator.settings
        lift = s.leg_radius_m + s.leg_clearance_m
        start_z, end_z = ends_z
        z = (start_z + (end_z - start_z) * fractions[:, None]) - lift  # (P, K), as the FEC samples it
        point, k = np.nonzero(~(z >= top))
        selected, f = legs[k], fractions[point]
        xy = []
        for i in range(2):
            knee = origins.knee(i, selected) - shift[i]
            if on_thigh:
                start, end = origins.hfe(i, selected) - shift[i], knee
            else:
                start, end = knee, (instant.x, instant.y)[i][cells[selected]]
            xy.append(start + (end - start) * f)
        return selected[~(z[point, k] >= prep.leg_terrain(xy[0], xy[1]))]


@dataclass(frozen=True, eq=False)
class _Instant:
    """One KF/LC instant, patch frame: foot centres x, y, z (cells,) [m], hip xy (2,) [m], whether
    every known cell has the same foot point (the swing start: evaluated once per height), and the hip's
    height above the evaluated one at this instant, hip_dz [m] (``FecInput.hip_rise_at_liftoff_m``)."""

    x: FloatArray
    y: FloatArray
    z: FloatArray
    hip: FloatArray
    uniform: bool
    hip_dz: float = 0.0


def _lowest_end(start: FloatArray, end: FloatArray, fractions: FloatArray) -> FloatArray:
    """[m] the lower of a segment's first and last sample points (the lowest sample, see ``_leg_clear``)."""
    return np.minimum(_segment_sample(start, end, fractions[0]), _segment_sample(start, end, fractions[-1]))


def _layer_blocks(counts: NDArray[np.intp], limit: int) -> list[slice]:
    """Consecutive layers of a stack grouped so that each group holds at most ``limit`` pairs (a layer
    with more forms a group alone); counts (H',) the pairs per layer."""
    blocks, first, total = [], 0, 0
    for layer, count in enumerate(counts.tolist()):
        if total + count > limit and layer > first:
            blocks.append(slice(first, layer))
            first, total = layer, 0
        total += count
    blocks.append(slice(first, len(counts)))
    return blocks


def _segment_sample(start: FloatArray, end: FloatArray, fraction: float) -> FloatArray:
    """start + (end - start) * fraction [m], as the FEC samples a leg segment; fraction 0 gives start
    itself without arithmetic (the same value)."""
    return start if fraction == 0.0 else start + (end - start) * fraction


def _flat_shift(di: int, dj: int, rows: int, cols: int) -> tuple[slice, slice, BoolArray | None]:
    """The neighbour (r + di, c + dj) of every cell as a shift of the row-major flattened grid (one
    contiguous slice per layer, cheaper than 2-D slices): cell k of ``target`` pairs with cell k of
    ``source``; ``outside`` (len(target),) marks the cells whose neighbour is across a side edge (the
    flat shift wraps to the next row there), None if there are none."""
    shift, size = di * cols + dj, rows * cols
    target = slice(max(0, -shift), size - max(0, shift))
    source = slice(target.start + shift, target.stop + shift)
    col = np.arange(size)[target] % cols + dj
    outside = (col < 0) | (col >= cols)
    return target, source, (outside if outside.any() else None)


def _drop_empty(ok: BoolArray, rows: NDArray[np.intp]) -> tuple[BoolArray, NDArray[np.intp]]:
    """The layers of the stack ok (H', rows, cols) that still have a True cell, and their ``rows``."""
    keep = ok.any(axis=(1, 2))
    return (ok, rows) if keep.all() else (ok[keep], rows[keep])


def _same_point(x: FloatArray, y: FloatArray, z: FloatArray) -> bool:
    """True if every known (non-NaN z) cell has exactly the same foot point."""
    known = ~np.isnan(z)
    if not known.any():
        return False
    return bool(np.ptp(x[known]) == 0.0 and np.ptp(y[known]) == 0.0 and np.ptp(z[known]) == 0.0)
