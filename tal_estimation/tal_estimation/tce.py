"""Terrain Compliance Estimator (TCE) of the thesis, without ROS.

Per leg and contact-frame direction, a sliding window of stance samples (force F, penetration p and its
rate dp/dt) feeds a weighted linear least-squares fit of the Kelvin-Voigt model F = k p (+ d dp/dt):

    I = (P^T W P)^-1 P^T W F,   P = [p, dp/dt] (or [p]),   W = diag(w), recent samples weigh more.

Buffers take samples only while the leg is in contact (estimated force above a threshold) and are kept
across swings, as in the thesis, so a new touchdown starts from the previous terrain's samples.

Contact states come from the robot model: the ground reaction force from the leg's actuated dynamics
(static: J_leg^T F = h_leg - tau_leg), the penetration from the undeformed terrain surface under the foot
(heightmap) and the foot kinematics with the base state, the rate from the foot velocity.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from tal_core.errors import InputError
from tal_core.legs import NUM_LEGS
from tal_core.robot_model import RobotModel

HeightFunction = Callable[[float, float], float]
NormalFunction = Callable[[float, float], np.ndarray]


@dataclass(frozen=True)
class TceSettings:
    """Window and validity settings. Units: [N], [m], [N/m], [N s/m]."""

    window: int = 250                       # samples per leg (1 s at 250 Hz, thesis)
    min_samples: int = 50                   # fewer stance samples: no estimate
    contact_force_threshold_n: float = 30.0  # F_min of the contact status
    estimate_damping: bool = False          # thesis: damping not estimated (foot velocity noise)
    weighting: str = "linear"               # "linear" (w_i grows with recency) or "uniform"
    min_penetration_m: float = 2e-5         # RMS penetration below this: degenerate window
    stiffness_range_n_per_m: tuple[float, float] = (100.0, 1e8)
    damping_range_ns_per_m: tuple[float, float] = (0.0, 1e5)
    max_condition_number: float = 1e10

    def __post_init__(self) -> None:
        if self.window < 2 or not 1 <= self.min_samples <= self.window:
            raise InputError(f"TCE window {self.window} and min_samples {self.min_samples} must satisfy "
                             f"1 <= min_samples <= window, window >= 2")
        if self.weighting not in ("linear", "uniform"):
            raise InputError(f"TCE weighting must be 'linear' or 'uniform', got {self.weighting!r}")
        for name in ("stiffness_range_n_per_m", "damping_range_ns_per_m"):
            low, high = getattr(self, name)
            if not (math.isfinite(low) and math.isfinite(high) and 0.0 <= low < high):
                raise InputError(f"TCE {name} must be finite with 0 <= low < high, got {(low, high)}")


@dataclass
class LegEstimate:
    """Latest estimate of one leg and direction."""

    stiffness_n_per_m: float = float("nan")
    damping_ns_per_m: float = float("nan")
    confidence: float = 0.0                 # [0, 1]: fill ratio x fit quality (R^2)
    samples: int = 0
    valid: bool = False
    clamped: bool = False                   # the fit was outside the physical range and was clamped
    stale: bool = False                     # the last window could not be fitted: previous estimate kept


@dataclass
class WindowedKelvinVoigtFit:
    """Sliding window and weighted least squares of F = k p (+ d dp/dt) for one leg and direction."""

    settings: TceSettings
    _force: np.ndarray = field(init=False)
    _pen: np.ndarray = field(init=False)
    _rate: np.ndarray = field(init=False)
    _next: int = field(default=0, init=False)
    _count: int = field(default=0, init=False)
    estimate: LegEstimate = field(default_factory=LegEstimate, init=False)

    def __post_init__(self) -> None:
        m = self.settings.window
        self._force, self._pen, self._rate = np.zeros(m), np.zeros(m), np.zeros(m)

    def add(self, force_n: float, penetration_m: float, rate_m_s: float) -> None:
        """Append one stance sample; non-finite samples are ignored."""
        if not (math.isfinite(force_n) and math.isfinite(penetration_m) and math.isfinite(rate_m_s)):
            return
        i = self._next
        self._force[i], self._pen[i], self._rate[i] = force_n, penetration_m, rate_m_s
        self._next = (i + 1) % self.settings.window
        self._count = min(self._count + 1, self.settings.window)

    def _ordered(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Window samples oldest first."""
        n, m = self._count, self.settings.window
        index = (np.arange(self._next - n, self._next)) % m
        return self._force[index], self._pen[index], self._rate[index]

    def fit(self) -> LegEstimate:
        """Refit on the current window; keeps (and flags) the previous estimate when ill-posed."""
        s, est = self.settings, self.estimate
        est.samples = self._count
        if self._count < s.min_samples:
            est.stale = est.valid
            est.confidence = est.confidence * 0.99 if est.valid else 0.0
            return est
        force, pen, rate = self._ordered()
        if float(np.sqrt(np.mean(pen**2))) < s.min_penetration_m:
            return self._keep_previous()
        n = len(force)
        w = np.arange(1, n + 1, dtype=float) / n if s.weighting == "linear" else np.ones(n)
        P = np.column_stack([pen, rate]) if s.estimate_damping else pen[:, None]
        PtW = P.T * w
        normal_matrix = PtW @ P
        if not np.all(np.isfinite(normal_matrix)) or np.linalg.cond(normal_matrix) > s.max_condition_number:
            return self._keep_previous()
        try:
            params = np.linalg.solve(normal_matrix, PtW @ force)
        except np.linalg.LinAlgError:
            return self._keep_previous()
        residual = force - P @ params
        total = float(np.sum(w * (force - np.average(force, weights=w)) ** 2))
        r2 = 1.0 - float(np.sum(w * residual**2)) / total if total > 0.0 else 1.0
        k = float(params[0])
        d = float(params[1]) if s.estimate_damping else float("nan")
        k_clamped = float(np.clip(k, *s.stiffness_range_n_per_m))
        d_clamped = float(np.clip(d, *s.damping_range_ns_per_m)) if s.estimate_damping else d
        est.clamped = k_clamped != k or (s.estimate_damping and d_clamped != d)
        est.stiffness_n_per_m, est.damping_ns_per_m = k_clamped, d_clamped
        fill = self._count / s.window
        est.confidence = float(np.clip(fill * max(r2, 0.0), 0.0, 1.0)) * (0.5 if est.clamped else 1.0)
        est.valid, est.stale = True, False
        return est

    def _keep_previous(self) -> LegEstimate:
        est = self.estimate
        est.stale = True
        est.confidence *= 0.9   # an estimate that cannot be refreshed loses confidence
        return est


@dataclass(frozen=True)
class ContactSample:
    """Estimated contact state of one leg (world frame unless stated)."""

    in_contact: bool
    force_n: np.ndarray          # (3,) ground reaction force on the foot
    normal: np.ndarray           # (3,) unit terrain normal under the foot
    penetration_m: float         # along the normal, contact frame
    penetration_rate_m_s: float  # along the normal, contact frame


class TerrainComplianceEstimator:
    """Contact-state estimation plus one windowed fit per leg (normal direction)."""

    def __init__(self, model: RobotModel, settings: TceSettings | None = None) -> None:
        self.model = model
        self.settings = settings or TceSettings()
        self.fits = [WindowedKelvinVoigtFit(self.settings) for _ in range(NUM_LEGS)]
        self._joint_v = model.canonical_joint_v_indices()

    def contact_states(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, height: HeightFunction,
                       normal: NormalFunction | None = None) -> list[ContactSample]:
        """Contact states from (q, v) (Pinocchio convention) and measured joint torques tau [N m]
        (canonical order). ``height(x, y)`` is the undeformed terrain surface [m] (e.g. a heightmap)."""
        tau = np.asarray(tau, dtype=float)
        if tau.shape != (len(self._joint_v),) or not np.all(np.isfinite(tau)):
            raise InputError(f"TCE needs {len(self._joint_v)} finite joint torques, got {tau!r}")
        m = self.model
        m.update(q, v)
        h = m.nonlinear_effects()
        feet, velocities = m.foot_positions(), m.foot_velocities()
        radius = m.description.foot_radius_m
        samples = []
        for leg in range(NUM_LEGS):
            v_index = m.leg_joint_v_indices(leg)
            canonical = [int(np.flatnonzero(self._joint_v == i)[0]) for i in v_index]
            force = m.foot_force_from_leg_torques(leg, tau[canonical], h[v_index])
            x, y = float(feet[leg, 0]), float(feet[leg, 1])
            n = np.array([0.0, 0.0, 1.0]) if normal is None else np.asarray(normal(x, y), dtype=float)
            n = n / np.linalg.norm(n)
            surface = np.array([x, y, float(height(x, y))])
            contact_point = feet[leg] - radius * n
            penetration = float(n @ (surface - contact_point))
            rate = float(-(n @ velocities[leg]))
            in_contact = bool(n @ force >= self.settings.contact_force_threshold_n)
            samples.append(ContactSample(in_contact, force, n, penetration, rate))
        return samples

    def update(self, samples: list[ContactSample]) -> list[LegEstimate]:
        """Feed the stance legs' samples (normal direction) and refit; swing legs keep their estimate."""
        estimates = []
        for fit, sample in zip(self.fits, samples):
            if sample.in_contact:
                fit.add(float(sample.normal @ sample.force_n), sample.penetration_m, sample.penetration_rate_m_s)
                estimates.append(fit.fit())
            else:
                estimates.append(fit.estimate)
        return estimates
