"""Vision-based Pose Adaptation (VPA): the body pose that maximises the legs' chances of safe footholds.

Pipeline (thesis ViTAL, VPA): (1) heightmap extraction: one map per leg centred on the projection of
its hip, and per receding-horizon stage j the same maps shifted by (j - 1) * shift along the body
velocity (overlapping maps, default shift half the map diagonal); (2) pose evaluation: NSF of every map
over the sampled hip heights, exact (``vpa_evaluation``) or by the CNN (``vpa_cnn``); (3) function
approximation: RBF weights (``rbf``; the CNN predicts them directly); (4) pose optimisation
(``vpa_optimizer``). The output is the first stage's pose in the world: base height [m] (world z of the
base origin), roll and pitch [rad] (Cardan, horizontal frame), i.e. ``tal_msgs/BodyPoseReference``.

Bad input: NaN heightmap cells are unknown and never safe (FEC); a missing or stale map holds the
default pose (nominal height above the last known terrain reference, level), flagged in the status;
malformed inputs (wrong shapes, NaN twist, stamps from the future) raise ``PerceptionInputError``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from enum import Enum
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import ThreadpoolController

from tal_core.heightmap import HeightMapGrid
from tal_core.legs import LEGS, Leg
from tal_core.robot_model import RobotModel
from tal_perception.errors import PerceptionInputError, VpaConfigError
from tal_perception.fec import FootholdEvaluator
from tal_perception.fec_settings import GaitTiming
from tal_perception.rbf import RbfBasis
from tal_perception.vfa import check_map_age, extract_patches
from tal_perception.vpa_evaluation import PoseEvaluator
from tal_perception.vpa_optimizer import HipHeightModel, PoseOptimizer, PoseProblem, Solver
from tal_perception.vpa_settings import VpaSettings

FloatArray = NDArray[np.float64]
_NO_FOOTHOLD = 0.5  # [footholds] a curve below this everywhere has no safe foothold


class VpaStatus(Enum):
    """Why the pose reference is what it is."""

    OK = "ok"  # optimised pose
    NO_MAP = "no_map"  # no heightmap yet: default pose held
    STALE_MAP = "stale_map"  # heightmap older than max_map_age_s: default pose held
    NO_SAFE_FOOTHOLD = "no_safe_foothold"  # no leg has a safe foothold at any height: previous pose held


class NsfModel(Protocol):
    """Anything that predicts normalised-NSF RBF weights of leg maps (the CNN, ``vpa_cnn.CnnNsfModel``)."""

    def predict(self, legs: list[Leg], heights: FloatArray, twists: FloatArray) -> tuple[FloatArray, FloatArray]: ...


@dataclass(frozen=True, eq=False)
class VpaDiagnostics:
    """What the update computed: stage poses (N_h, 3) relative to the body reference [m, rad, rad];
    weights (N_h, 4, E); map references (N_h, 4) [m] world z (NaN: nothing known); body reference [m];
    map centres (N_h, 4, 2) [m] world xy; exact NSF samples (N_h, 4, N) (None with the CNN); timings [s]."""

    stage_poses: FloatArray | None = None
    weights: FloatArray | None = None
    map_references: FloatArray | None = None
    body_reference_m: float = float("nan")
    map_centres: FloatArray | None = None
    nsf_samples: NDArray[np.int64] | None = None
    solver_iterations: int = 0
    evaluation_s: float = 0.0
    optimisation_s: float = 0.0


@dataclass(frozen=True, eq=False)
class VpaResult:
    """Body pose reference (world): base_height_m [m] world z of the base origin, roll_rad, pitch_rad
    [rad]; hip_heights_m (4,) [m] world z implied by the pose; safe_footholds (4,) NSF per leg at the
    pose (stage 1); horizon_s [s] time span to the last stage (0 when standing); optimal: the solver
    converged (False also when a pose was held)."""

    status: VpaStatus
    base_height_m: float
    roll_rad: float
    pitch_rad: float
    hip_heights_m: FloatArray
    safe_footholds: NDArray[np.int64]
    horizon_s: float
    optimal: bool
    diagnostics: VpaDiagnostics = field(default_factory=VpaDiagnostics)

    @property
    def pose(self) -> FloatArray:
        """(3,) [m, rad, rad] base height (world z), roll, pitch."""
        return np.array([self.base_height_m, self.roll_rad, self.pitch_rad])


class PoseAdapter:
    """The VPA of one robot: exact evaluation by default, the CNN when ``nsf_model`` is given."""

    def __init__(
        self,
        model: RobotModel,
        settings: VpaSettings | None = None,
        evaluator: FootholdEvaluator | None = None,
        nsf_model: NsfModel | None = None,
        solver: Solver = Solver.LBFGSB,
    ) -> None:
        self.settings = settings if settings is not None else VpaSettings()
        self.evaluator = evaluator if evaluator is not None else FootholdEvaluator(model)
        self.pose_evaluator = PoseEvaluator(self.evaluator, self.settings.hip_heights, self.settings.swing_hip_model)
        self.basis = RbfBasis(self.settings.hip_heights, self.settings.rbf_count, self.settings.rbf_intersection)
        self.hips = HipHeightModel.from_model(model)
        self.optimizer = PoseOptimizer(self.settings, self.basis, self.hips)
        self.nsf_model = nsf_model
        self.solver = solver
        fec = self.evaluator.settings
        self.cells = fec.patch_cells * fec.patch_cells
        if nsf_model is not None and hasattr(nsf_model, "check"):
            nsf_model.check(self.settings.rbf_count, fec.patch_cells)
        if nsf_model is not None and self.settings.swing_hip_model != "level":
            raise VpaConfigError(
                f"VpaSettings.swing_hip_model {self.settings.swing_hip_model!r} needs the exact evaluation: the VPA "
                "CNN was trained on the thesis' level-hip curves"
            )
        self.default_relative = np.array([model.nominal_base_height_m, 0.0, 0.0])
        # The update is single-threaded numpy; the optimiser's BLAS/LAPACK calls are tiny (6 variables)
        # and gain nothing from OpenBLAS threads, whose workers busy-wait after each call and so take
        # the update's core on a loaded machine (one L-BFGS-B solve: 11.6 ms with 2 BLAS threads, 1.0 ms
        # with 1, while another job kept one of 2 cores busy). Limited during ``update`` only; the
        # results do not depend on it.
        self._blas = ThreadpoolController()
        self._previous_world: FloatArray | None = None  # last output pose (world height, roll, pitch)
        self._reference_m: float | None = None  # last body reference [m] world z

    def reset(self) -> None:
        """Forget the previous pose and terrain reference (e.g. after a relocalisation)."""
        self._previous_world, self._reference_m = None, None

    def update(
        self,
        grid: HeightMapGrid | None,
        base_position: ArrayLike,
        yaw: float,
        twist: ArrayLike,
        gait: GaitTiming,
        map_age_s: float = 0.0,
    ) -> VpaResult:
        """One VPA update. base_position (3,) [m] world; yaw [rad] base heading; twist (6,) base twist in
        the horizontal frame [m/s, rad/s]; gait the timing the legs will step with; map_age_s [s] now
        minus the map's stamp."""
        base, twist_h = _vector(base_position, 3, "base_position"), _vector(twist, 6, "twist")
        if not (isinstance(yaw, (int, float, np.floating)) and math.isfinite(yaw)):
            raise PerceptionInputError(f"VPA: yaw must be a finite number [rad], got {yaw!r}")
        check_map_age(map_age_s, "VPA")
        if not isinstance(gait, GaitTiming):
            raise PerceptionInputError(f"VPA: gait must be a GaitTiming, got {type(gait).__name__}")
        if grid is None:
            return self._hold_default(VpaStatus.NO_MAP, base)
        if map_age_s > self.settings.max_map_age_s:
            return self._hold_default(VpaStatus.STALE_MAP, base)
        with self._blas.limit(limits=1, user_api="blas"):
            return self._adapt(grid, base, float(yaw), twist_h, gait)

    # -- stages ----------------------------------------------------------------------------------------
    def map_centres(self, base: FloatArray, yaw: float, twist: FloatArray) -> tuple[FloatArray, float]:
        """(N_h, 4, 2) [m] world xy of the leg maps and the horizon time span [s]: the hips projected
        with the base level at ``yaw``, then shifted along the horizontal velocity per stage."""
        c, s = math.cos(yaw), math.sin(yaw)
        rotation = np.array([[c, -s], [s, c]])
        hips = base[:2] + self.hips.offsets[:, :2] @ rotation.T  # (4, 2)
        velocity = rotation @ twist[:2]
        speed = float(np.hypot(*velocity))
        fec = self.evaluator.settings
        shift = self.settings.shift_m(fec.patch_cells, fec.resolution_m)
        moving = speed >= self.settings.min_speed_for_shift_mps
        step = velocity / speed * shift if moving else np.zeros(2)
        stages = np.arange(self.settings.horizon)[:, None, None]
        horizon_s = (self.settings.horizon - 1) * shift / speed if moving else 0.0
        return hips[None] + stages * step, horizon_s

    def _adapt(
        self, grid: HeightMapGrid, base: FloatArray, yaw: float, twist: FloatArray, gait: GaitTiming
    ) -> VpaResult:
        fec = self.evaluator.settings
        started = time.perf_counter()
        centres, horizon_s = self.map_centres(base, yaw, twist)
        n_h = self.settings.horizon
        maps = extract_patches(grid, centres.reshape(-1, 2), yaw, fec.patch_cells, fec.resolution_m).reshape(
            n_h, 4, fec.patch_cells, fec.patch_cells)
        # Standing still: all stages see the same maps, evaluated once.
        distinct = 1 if np.allclose(centres, centres[:1]) else n_h
        weights, references, samples = self._evaluate(maps[:distinct], twist, gait)
        if distinct < n_h:
            weights = np.repeat(weights, n_h, axis=0)
            references = np.repeat(references, n_h, axis=0)
            samples = None if samples is None else np.repeat(samples, n_h, axis=0)
        evaluated = time.perf_counter()
        known = references[0][~np.isnan(references[0])]
        if known.size == 0 and self._reference_m is None:
            return self._hold_default(VpaStatus.NO_SAFE_FOOTHOLD, base)
        body_reference = float(np.mean(known)) if known.size else float(self._reference_m)
        offsets = body_reference - np.where(np.isnan(references), body_reference, references)
        previous = self._previous_relative(body_reference)
        problem = PoseProblem(self._weighted(weights), offsets, previous)
        diagnostics = dict(
            weights=weights, map_references=references, body_reference_m=body_reference, map_centres=centres,
            nsf_samples=samples, evaluation_s=evaluated - started,
        )  # fmt: skip
        curves = self.basis.evaluate(weights[0][None], self.settings.hip_heights[:, None])  # (N, 4)
        peak = float(curves.max()) * self.cells
        if not np.isfinite(peak) or peak < _NO_FOOTHOLD:
            lower, upper = self.optimizer.bounds(problem)
            held = np.clip(previous, lower[0], upper[0])
            return self._result(VpaStatus.NO_SAFE_FOOTHOLD, held, body_reference, weights, horizon_s, False,
                                VpaDiagnostics(stage_poses=np.repeat(held[None], n_h, axis=0), **diagnostics))
        solution = self.optimizer.solve(problem, self.solver)
        diag = VpaDiagnostics(stage_poses=solution.poses, solver_iterations=solution.iterations,
                              optimisation_s=time.perf_counter() - evaluated, **diagnostics)  # fmt: skip
        status, converged = VpaStatus.OK, solution.converged
        return self._result(status, solution.poses[0], body_reference, weights, horizon_s, converged, diag)

    def _weighted(self, weights: FloatArray) -> FloatArray:
        """The curves' weights (N_h, 4, E) as the optimiser sees them: unchanged (``leg_weighting`` "none"),
        or each (stage, leg) curve divided by its peak over the sampled heights, at least
        ``leg_weight_floor`` ("peak"; the RBF model is linear in its weights)."""
        if self.settings.leg_weighting == "none":
            return weights
        curves = self.basis.evaluate(weights[:, :, None, :], self.settings.hip_heights[None, None, :])  # (N_h, 4, N)
        return weights / np.maximum(curves.max(axis=-1), self.settings.leg_weight_floor)[..., None]

    def _evaluate(
        self, maps: FloatArray, twist: FloatArray, gait: GaitTiming
    ) -> tuple[FloatArray, FloatArray, NDArray[np.int64] | None]:
        """Weights (S, 4, E), references (S, 4) [m] and exact NSF samples (S, 4, N) (None: CNN)."""
        stages = maps.shape[0]
        legs = [leg for _ in range(stages) for leg in LEGS]
        flat_maps = maps.reshape(stages * 4, *maps.shape[2:])
        if self.nsf_model is not None:
            weights, references = self.nsf_model.predict(legs, flat_maps, np.tile(twist, (len(legs), 1)))
            return weights.reshape(stages, 4, -1), references.reshape(stages, 4), None
        evaluations = [self.pose_evaluator.evaluate(leg, m, twist, gait) for leg, m in zip(legs, flat_maps)]
        samples = np.array([e.nsf for e in evaluations]).reshape(stages, 4, -1)
        references = np.array([e.reference_m for e in evaluations]).reshape(stages, 4)
        return self.basis.fit(samples / self.cells), references, samples

    # -- results ---------------------------------------------------------------------------------------
    def _previous_relative(self, body_reference: float) -> FloatArray:
        if self._previous_world is None:
            return self.default_relative.copy()
        return self._previous_world - np.array([body_reference, 0.0, 0.0])

    def _hold_default(self, status: VpaStatus, base: FloatArray) -> VpaResult:
        """The default pose: nominal height above the last terrain reference (or, with none yet, the
        current base height), level."""
        reference = self._reference_m if self._reference_m is not None else float(base[2] - self.default_relative[0])
        pose = self.default_relative.copy()
        hips = reference + self.hips.heights(pose)
        self._previous_world = pose + np.array([reference, 0.0, 0.0])
        return VpaResult(status, float(reference + pose[0]), 0.0, 0.0, hips, np.zeros(4, dtype=np.int64), 0.0, False)

    def _result(
        self, status: VpaStatus, pose: FloatArray, reference: float, weights: FloatArray, horizon_s: float,
        optimal: bool, diagnostics: VpaDiagnostics,
    ) -> VpaResult:  # fmt: skip
        relative_hips = self.hips.heights(pose)  # (4,) [m] above the body reference
        map_references = np.nan_to_num(diagnostics.map_references[0], nan=reference)
        curve_z = relative_hips + (reference - map_references)  # above each leg map's reference
        nsf = np.clip(np.rint(self.basis.evaluate(weights[0], curve_z) * self.cells), 0, self.cells).astype(np.int64)
        self._previous_world = pose + np.array([reference, 0.0, 0.0])
        self._reference_m = reference
        return VpaResult(status, float(reference + pose[0]), float(pose[1]), float(pose[2]), reference + relative_hips,
                         nsf, float(horizon_s), bool(optimal), diagnostics)  # fmt: skip


def _vector(value: object, size: int, name: str) -> FloatArray:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as error:
        raise PerceptionInputError(f"VPA: {name}: cannot convert to a float array ({error})") from None
    if array.shape != (size,):
        raise PerceptionInputError(f"VPA: {name} must have shape ({size},), got {array.shape}")
    if not np.isfinite(array).all():
        bad = np.flatnonzero(~np.isfinite(array)).tolist()
        raise PerceptionInputError(f"VPA: {name} has non-finite value(s) at index {bad}")
    return array


__all__ = ["NsfModel", "PoseAdapter", "VpaDiagnostics", "VpaResult", "VpaStatus"]
