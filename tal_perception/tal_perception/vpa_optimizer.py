"""Pose optimiser of the VPA: the body pose u = [z_b, roll, pitch] that maximises the legs' safe footholds.

Thesis (ViTAL, pose optimisation and receding horizon): maximise sum_j C_j(F_lj(z_lj(u_j))) over the
stages j = 1..N_h, minus a smoothness term between consecutive stages, subject to u_min <= u <= u_max
and bounds on the change per update. The thesis writes "+ ||u_j - u_j+1||" in a maximisation; it is
meant to connect the stages smoothly, so it is subtracted here, squared (differentiable) and weighted.

Hip heights from the body pose (thesis appendix, Cardan roll beta then pitch gamma):
z_h = z_b - x_h sin(gamma) + y_h cos(gamma) sin(beta) + z_h^b cos(gamma) cos(beta), with (x_h, y_h, z_h^b)
the HAA joint in the base frame read from the robot model. Heights are relative (see ``vpa_settings``):
z_b above the body reference, leg curve F_lj over the hip height above its own map reference, so the
leg term is evaluated at z_b + dz_l(beta, gamma) + (body reference - map reference).

Costs (normalised NSF F in [0, 1]; all maximised): C_sum = sum_l F_l^2, C_prod = prod_l F_l^2 and
C_int = sum_l (mean of F_l over [z - m, z + m])^2 with the thesis' two-point rule
(F(z - m) + F(z + m)) / 2 (the thesis' m (F(z - m) + F(z + m)) divided by the constant 2m, which keeps
the three costs on one scale and the optimum unchanged).

The change bound of stage j is |u_j - u_prev| <= j * max_change (a box per stage: the future stage may
have moved further by the time it is reached). Solvers: SciPy ``trust-constr`` (the thesis' trust-region
interior point method, the reference) and ``L-BFGS-B`` (the fast one, same optimum on the tested cases);
both start from the best of the previous pose and a few heights and, a second time, from the pose that
puts every leg nearest its own best hip height (``peak_pose``); the better optimum wins.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import BFGS, Bounds, minimize

from tal_core.robot_model import RobotModel
from tal_perception.errors import VpaConfigError
from tal_perception.rbf import RbfBasis
from tal_perception.vpa_settings import CostKind, VpaSettings

FloatArray = NDArray[np.float64]
_START_HEIGHTS = 7  # [-] body heights tried for the initial guess (spread over the allowed range)
_MIN_SCALE = 1e-6  # [-] objective magnitudes below this are not scaled up further (flat, empty curves)


class Solver(Enum):
    TRUST_CONSTR = "trust-constr"  # reference (thesis)
    LBFGSB = "L-BFGS-B"  # fast


class HipHeightModel:
    """Hip heights of the four legs as a function of the body pose (thesis appendix)."""

    def __init__(self, hip_offsets_base: ArrayLike) -> None:
        offsets = np.asarray(hip_offsets_base, dtype=float)
        if offsets.shape != (4, 3) or not np.isfinite(offsets).all():
            raise VpaConfigError(f"hip offsets must be (4, 3) finite values [m], got shape {offsets.shape}")
        self.offsets = offsets  # (4, 3) [m] HAA joints in the base frame, rows LF, RF, LH, RH
        self._x, self._y, self._z = (offsets[:, i].copy() for i in range(3))

    @classmethod
    def from_model(cls, model: RobotModel) -> HipHeightModel:
        """Read the HAA joint positions in the base frame from the model (nominal pose, level base)."""
        height = model.nominal_base_height_m
        model.update(model.neutral_q(height), np.zeros(model.nv))
        return cls(model.hip_positions() - np.array([0.0, 0.0, height]))

    def relative(self, roll: FloatArray, pitch: FloatArray) -> FloatArray:
        """(..., 4) [m] hip height minus base height for roll, pitch (...) [rad]."""
        x, y, z = (self.offsets[:, i] for i in range(3))
        sb, cb = np.sin(roll)[..., None], np.cos(roll)[..., None]
        sg, cg = np.sin(pitch)[..., None], np.cos(pitch)[..., None]
        return -x * sg + y * cg * sb + z * cg * cb

    def heights(self, pose: ArrayLike) -> FloatArray:
        """(..., 4) [m] hip heights for poses (..., 3) = [z_b, roll, pitch] (same reference as z_b)."""
        u = np.asarray(pose, dtype=float)
        return u[..., 0:1] + self.relative(u[..., 1], u[..., 2])

    def jacobian(self, pose: ArrayLike) -> FloatArray:
        """(..., 4, 3) d z_h / d [z_b, roll, pitch]."""
        return self.heights_and_jacobian(pose)[1]

    def heights_and_jacobian(self, pose: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """``heights`` and ``jacobian`` with one evaluation of the sines and cosines (optimiser loop)."""
        u = np.asarray(pose, dtype=float)
        x, y, z = self._x, self._y, self._z
        sb, cb = np.sin(u[..., 1:2]), np.cos(u[..., 1:2])
        sg, cg = np.sin(u[..., 2:3]), np.cos(u[..., 2:3])
        cg_sb, cg_cb = cg * sb, cg * cb
        heights = u[..., 0:1] - x * sg + y * cg_sb + z * cg_cb
        jacobian = np.empty((*heights.shape, 3))
        jacobian[..., 0] = 1.0
        jacobian[..., 1] = y * cg_cb - z * cg_sb
        jacobian[..., 2] = -x * cg - sg * (y * sb + z * cb)
        return heights, jacobian


@dataclass(frozen=True, eq=False)
class PoseProblem:
    """One VPA optimisation: weights (N_h, 4, E) of the normalised NSF curves, offsets (N_h, 4) [m] body
    reference minus map reference, previous (3,) pose [m, rad, rad] relative to the body reference."""

    weights: FloatArray
    offsets: FloatArray
    previous: FloatArray

    @property
    def stages(self) -> int:
        return int(self.weights.shape[0])


@dataclass(frozen=True, eq=False)
class PoseSolution:
    """poses (N_h, 3) [m, rad, rad] relative to the body reference; objective (maximised) value;
    converged: the solver reported success; iterations; solver."""

    poses: FloatArray
    objective: float
    converged: bool
    iterations: int
    solver: Solver


class PoseOptimizer:
    """Builds the bounds and the objective of a ``PoseProblem`` and solves it."""

    def __init__(self, settings: VpaSettings, basis: RbfBasis, hips: HipHeightModel) -> None:
        self.settings = settings
        self.basis = basis
        self.hips = hips
        self.lower = np.array(settings.pose_lower, dtype=float)
        self.upper = np.array(settings.pose_upper, dtype=float)
        self.max_change = np.array(settings.max_change, dtype=float)
        self._scaled_centres = basis.centres / basis.sigma

    # -- bounds and objective ----------------------------------------------------------------------------
    def bounds(self, problem: PoseProblem) -> tuple[FloatArray, FloatArray]:
        """(N_h, 3) lower and upper bounds: u_min..u_max intersected with u_prev +- j * max_change."""
        stage = np.arange(1, problem.stages + 1)[:, None]
        previous = np.clip(problem.previous, self.lower, self.upper)
        lower = np.maximum(self.lower, previous - stage * self.max_change)
        upper = np.minimum(self.upper, previous + stage * self.max_change)
        return lower, upper

    def leg_terms(self, problem: PoseProblem, poses: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Leg terms L (N_h, 4) (F, or its margin mean for C_int) and dL/dz_h at poses (N_h, 3)."""
        return self._leg_terms(problem, self.hips.heights(poses) + problem.offsets)

    def _leg_terms(self, problem: PoseProblem, z: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Leg terms at hip heights z (N_h, 4) [m] above the map references: one exp for values and
        slopes (this runs in the solver loop)."""
        inv_sigma = 1.0 / self.basis.sigma
        if self.settings.cost is CostKind.INT:
            m = self.settings.cost_margin_m
            points = np.stack([z - m, z + m])  # (2, N_h, 4)
        else:
            points = z[None]
        d = points[..., None] * inv_sigma - self._scaled_centres  # (k, N_h, 4, E)
        weighted = problem.weights * np.exp(-0.5 * d * d)
        values = weighted.sum(axis=-1)
        slopes = (weighted * d).sum(axis=-1) * -inv_sigma
        if values.shape[0] == 2:  # margin mean of C_int
            return 0.5 * (values[0] + values[1]), 0.5 * (slopes[0] + slopes[1])
        return values[0], slopes[0]

    def objective(self, problem: PoseProblem, flat: FloatArray) -> tuple[float, FloatArray]:
        """Maximised objective and its gradient w.r.t. the stacked poses (N_h * 3,)."""
        poses = flat.reshape(problem.stages, 3)
        heights, jacobian = self.hips.heights_and_jacobian(poses)
        values, slopes = self._leg_terms(problem, heights + problem.offsets)
        if self.settings.cost is CostKind.PROD:
            squares = values * values
            total = float(np.prod(squares, axis=1).sum())
            others = np.stack([np.prod(np.delete(squares, leg, axis=1), axis=1) for leg in range(4)], axis=1)
            d_z = 2.0 * values * slopes * others
        else:
            total = float(np.sum(values * values))
            d_z = 2.0 * values * slopes
        grad = np.einsum("jl,jlk->jk", d_z, jacobian)
        lam = self.settings.smoothness_weight
        if problem.stages > 1 and lam > 0.0:
            diff = poses[:-1] - poses[1:]
            total -= lam * float(np.sum(diff * diff))
            grad[:-1] -= 2.0 * lam * diff
            grad[1:] += 2.0 * lam * diff
        return total, grad.reshape(-1)

    # -- solving --------------------------------------------------------------------------------------
    def initial_guess(self, problem: PoseProblem) -> FloatArray:
        """Best (highest objective) of: the previous pose in every stage, and a few body heights with
        the previous roll and pitch, clipped into the bounds."""
        lower, upper = self.bounds(problem)
        previous = np.clip(problem.previous, lower, upper)  # (N_h, 3)
        candidates = [previous]
        for height in np.linspace(lower[0, 0], upper[0, 0], _START_HEIGHTS):
            guess = previous.copy()
            guess[:, 0] = height
            candidates.append(np.clip(guess, lower, upper))
        scores = [self.objective(problem, c.reshape(-1))[0] for c in candidates]
        scores[0] += self.settings.switch_margin * abs(scores[0])  # stay near the previous pose unless clearly worse
        return candidates[int(np.argmax(scores))].reshape(-1)

    def peak_pose(self, problem: PoseProblem) -> FloatArray:
        """(N_h, 3) per stage, the pose whose hip heights come closest (least squares, each leg weighted
        by its curve's peak) to the middle of each leg's best hip heights (where F >= 0.9 of its peak).

        Why: the objective is flat where a leg's curve is zero. On stairs at 0.4 m/s the front legs
        have safe footholds only 0.56-0.64 m above their tread and none at the previous pose, so a
        local solver started there (or from a level pose at any height) never finds the nose-up pose
        that serves both pairs of legs; a second start here does."""
        z = np.asarray(self.settings.hip_heights, dtype=float)  # (N,) above the map references
        curves = self.basis.evaluate(problem.weights[:, :, None, :], z[None, None, :])  # (N_h, 4, N)
        peaks = curves.max(axis=-1)  # (N_h, 4)
        near_peak = curves >= 0.9 * peaks[..., None]
        best = (near_peak * z).sum(axis=-1) / np.maximum(near_peak.sum(axis=-1), 1)  # (N_h, 4)
        targets = best - problem.offsets  # hip heights above the body reference
        weights = np.clip(peaks, 0.0, None)
        poses = np.repeat(np.clip(problem.previous, self.lower, self.upper)[None], problem.stages, axis=0)
        for j in range(problem.stages):
            if weights[j].max() <= 0.0:
                continue
            root = np.sqrt(weights[j])
            for _ in range(3):  # Gauss-Newton: the hip heights are nearly linear in the pose
                heights, jacobian = self.hips.heights_and_jacobian(poses[j])
                step, *_ = np.linalg.lstsq(jacobian * root[:, None], (targets[j] - heights) * root, rcond=None)
                poses[j] = np.clip(poses[j] + step, self.lower, self.upper)
        return poses

    def solve(self, problem: PoseProblem, solver: Solver = Solver.LBFGSB, x0: FloatArray | None = None) -> PoseSolution:
        """Maximise the objective within the bounds with ``solver`` from ``x0``; by default from two
        starts, ``initial_guess`` and ``peak_pose`` (clipped into the bounds), keeping the better optimum."""
        if x0 is not None:
            return self._solve_from(problem, solver, np.asarray(x0, dtype=float).reshape(-1))
        first = self._solve_from(problem, solver, self.initial_guess(problem))
        lower, upper = self.bounds(problem)
        peak = np.clip(self.peak_pose(problem), lower, upper).reshape(-1)
        if np.abs(peak - first.poses.reshape(-1)).max() < 1e-3:
            return first
        second = self._solve_from(problem, solver, peak)
        return self._keep_or_switch(problem, first, second)

    def _keep_or_switch(self, problem: PoseProblem, first: PoseSolution, second: PoseSolution) -> PoseSolution:
        """``second`` if it is the better optimum, else ``first``; the one whose first stage lies farther from the
        previous pose must beat the other by ``switch_margin`` (relative). A tie keeps ``first`` (margin 0: the
        plain comparison, bit for bit)."""
        previous = problem.previous[0] if problem.previous.ndim == 2 else problem.previous
        margin = self.settings.switch_margin

        def distance(solution: PoseSolution) -> float:
            return float(np.abs(solution.poses[0] - previous).sum())

        if distance(second) < distance(first):  # second stays nearer: its bonus
            return second if second.objective + margin * abs(second.objective) > first.objective else first
        return second if second.objective > first.objective + margin * abs(first.objective) else first

    def _solve_from(self, problem: PoseProblem, solver: Solver, start: FloatArray) -> PoseSolution:
        lower, upper = self.bounds(problem)

        # The solvers' tolerances are absolute: C_prod of four normalised NSF is ~1e-4, so the objective is
        # divided by its magnitude at the start (same optimum, gradients of order one for every cost).
        start_value = self.objective(problem, start)[0]  # also the fallback below (evaluated once)
        scale = 1.0 / min(max(abs(start_value), _MIN_SCALE), 1.0)

        def negative(flat: FloatArray) -> tuple[float, FloatArray]:
            value, grad = self.objective(problem, flat)
            return -value * scale, -grad * scale

        box = Bounds(lower.reshape(-1), upper.reshape(-1))
        if solver is Solver.TRUST_CONSTR:
            with warnings.catch_warnings():  # "delta_grad == 0.0": BFGS skips an update on flat regions
                warnings.simplefilter("ignore", UserWarning)
                result = minimize(
                    negative, start, jac=True, hess=BFGS(), method="trust-constr", bounds=box,
                    options={"gtol": 1e-9, "xtol": 1e-10, "maxiter": 500},
                )  # fmt: skip
            iterations = int(result.nit)
        else:
            result = minimize(
                negative, start, jac=True, method="L-BFGS-B", bounds=box,
                options={"ftol": 1e-10, "gtol": 1e-7, "maxiter": 200},
            )  # fmt: skip
            iterations = int(result.nit)
        poses = np.clip(result.x, box.lb, box.ub).reshape(problem.stages, 3)
        value = self.objective(problem, poses.reshape(-1))[0]
        if not math.isfinite(value) or value < start_value:  # never worse than where it started
            poses, value = start.reshape(problem.stages, 3), start_value
        return PoseSolution(poses, float(value), bool(result.success), iterations, solver)
