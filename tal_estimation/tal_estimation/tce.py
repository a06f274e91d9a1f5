"""Terrain Compliance Estimator (TCE) of the thesis, without ROS.

Per leg and contact-frame direction, a sliding window of stance samples (force F, penetration p and its
rate dp/dt) feeds a weighted linear least-squares fit of the Kelvin-Voigt model F = k p (+ d dp/dt):

    I = (P^T W P)^-1 P^T W F,   P = [p, dp/dt] (or [p]),   W = diag(w), recent samples weigh more.

Buffers take samples only while the leg is in contact (estimated force above a threshold) on a surface
flat around the foot (not at a step edge, where F = k p does not hold) and are kept
across swings, as in the thesis, so a new touchdown starts from the previous terrain's samples.

Contact states come from the robot model: the ground reaction force from the leg's actuated dynamics
(static: J_leg^T F = h_leg - tau_leg), the penetration from the undeformed terrain surface under the foot
(heightmap) and the foot kinematics with the base state, the rate from the foot velocity. Tangential
(optional): displacement of the foot along the two contact-frame tangents since touchdown, pooled into one
isotropic tangential window per leg.

All legs' windows live in one (legs, window) ring buffer and are fitted together from eight weighted sums,
so an update for four legs is a handful of vectorised operations (the thesis ran the TCE at 250 Hz).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from tal_core.errors import InputError
from tal_core.legs import NUM_LEGS
from tal_core.robot_description import NUM_JOINTS
from tal_core.robot_model import RobotModel
from tal_core.rotations import cross3

HeightFunction = Callable[[float, float], float]
NormalFunction = Callable[[float, float], np.ndarray]

PENETRATION_REFERENCES = ("surface", "touchdown")

# Index of each weighted sum in KelvinVoigtWindows._sums' last axis.
_W, _F, _FF, _PP, _PR, _RR, _PF, _RF, _P, _R, _T, _TT, _TP, _TR, _TF = range(15)


@dataclass(frozen=True)
class TceSettings:
    """Window and validity settings. Units: [N], [m], [N/m], [N s/m]."""

    window: int = 250                       # samples per leg (1 s at 250 Hz, thesis)
    min_samples: int = 50                   # fewer stance samples: no estimate
    contact_force_threshold_n: float = 30.0  # F_min of the contact status
    # Fitting damping too removes a +-2 % stiffness bias the unmodelled D dp/dt term leaves on soft ground
    # (measured on T1, results/stance); the thesis did not, because its foot velocity was noisy.
    estimate_damping: bool = True
    estimate_tangential: bool = False
    weighting: str = "linear"               # "linear" (w_i grows with recency) or "uniform"
    min_penetration_m: float = 2e-5         # weighted RMS penetration below this: degenerate window
    min_penetration_variation_m: float = 2e-6  # weighted std of p below this: no information on k
    stiffness_range_n_per_m: tuple[float, float] = (100.0, 1e8)
    damping_range_ns_per_m: tuple[float, float] = (0.0, 1e5)
    min_relative_determinant: float = 1e-8  # det(P^T W P) / (a c) below this: p and dp/dt collinear
    # Penetration offset: p comes from the base estimate and the undeformed surface, so a base-height error
    # or a map error shifts every sample of the window by about the same amount, and the fit through the
    # origin (the thesis') reads F / (p + offset). With the TCE on the drifting state estimate, a 1 cm offset
    # under a rigid foot gave ~4e4 N/m, the terrain-aware odometry sank the estimate further and the loop ran
    # away to ~400 N/m, confident in 16-30 % of the ticks (graph_tour replay, measured). A second fit with a
    # constant, F = k' (p - offset) + d' dp/dt, finds the offset from how p varies rather than where it sits;
    # a window whose |offset| exceeds max_penetration_offset_m is not confident (its penetrations are not the
    # foot's). The estimate stays the thesis' fit (the offset fit is 2-3 % less accurate on T1/T2 with a true
    # base: it absorbs the ground's nonlinearity). inf disables the check.
    max_penetration_offset_m: float = 0.01
    # Rigid ground: sub-millimetre sinkage is below what the kinematics resolve, so the LS slope is noise (R^2
    # ~ 0) and a leg stepping from soft onto rigid ground kept its soft estimate. A window whose force varies
    # by at least min_force_variation_n (std) while std(F) / std(p) >= rigid_stiffness_n_per_m shows ground at
    # least that stiff: the estimate is that ratio (>= |LS slope|), flagged rigid, confidence = fill ratio.
    rigid_stiffness_n_per_m: float = 5e4
    min_force_variation_n: float = 30.0
    # Edge contacts: where the undeformed surface within relief_radius_m of the foot centre spans more than
    # max_surface_relief_m (a foot at a stair edge or against a riser), one height under the centre is not
    # the surface the foot presses and F = k p does not hold: such samples are left out. On graph_tour's
    # stairs they drove the fit to the 100 N/m clamp on rigid steps (measured).
    relief_radius_m: float = 0.04
    max_surface_relief_m: float = 0.01
    # Terrain changes at a touchdown: the foot lands on a new patch while the window still holds the old one's
    # samples, a mix no spring fits (confidence 0 for ~1 s, a window, on graph_tour's T1 entry; the
    # terrain-aware odometry meanwhile missed the feet's sinking, +0.15 m of z). With window_restart, once
    # the current stance holds min_samples samples, its own fit is compared with the window's (and again every
    # RESTART_CHECK_EVERY samples up to RESTART_CHECK_UNTIL x min_samples): when the stance's fit is good (R^2
    # x offset consistency >= RESTART_MIN_QUALITY, or rigid) and the window's is not, or the two disagree
    # (rigid vs soft, or stiffness by more than RESTART_STIFFNESS_RATIO), the window restarts from the stance.
    window_restart: bool = True
    # Where p is measured from: "surface" (the thesis: the undeformed surface under the foot, from the map and
    # the base state; right when the base state is, e.g. motion capture) or "touchdown": the foot's height at
    # the first stance sample of each stance, which is then taken to be F / k deep (k: the leg's estimate,
    # rigid if none). A base estimate that drifts in height shifts a surface-referenced window by its drift;
    # only its motion within a stance reaches a touchdown-referenced one (on graph_tour with the TCE on the
    # drifting estimate, surface-referenced windows read rigid ground as soft: 10 % quantile 100 N/m). The
    # offset check (max_penetration_offset_m) does not apply to touchdown-referenced windows.
    penetration_reference: str = "surface"
    # Base drift (touchdown reference only): a base estimate whose vertical velocity is off by e makes every
    # stance's penetration read e t too shallow (t: time since its touchdown) and its rate e too small. On a
    # soft patch the TCE then reads the ground stiffer, the terrain-aware odometry counts less sinking, the
    # estimate's vertical velocity errs further the same way: the loop has no anchor (graph_tour, TCE on the
    # estimate: T1 read +94 %, the estimate rose 0.3-0.5 m per metre walked; measured). With base_drift_fit the
    # window is fitted as F = k p + d dp/dt + (k e) t + c, so k comes from how F and p vary together within the
    # stances, not from their drift; the rigid check uses the part of p that the drift does not explain.
    base_drift_fit: bool = False

    def __post_init__(self) -> None:
        if self.penetration_reference not in PENETRATION_REFERENCES:
            raise InputError(f"TCE penetration_reference must be one of {PENETRATION_REFERENCES}, got "
                             f"{self.penetration_reference!r}")
        if self.window < 2 or not 1 <= self.min_samples <= self.window:
            raise InputError(f"TCE window {self.window} and min_samples {self.min_samples} must satisfy "
                             f"1 <= min_samples <= window, window >= 2")
        if self.weighting not in ("linear", "uniform"):
            raise InputError(f"TCE weighting must be 'linear' or 'uniform', got {self.weighting!r}")
        if not (math.isfinite(self.contact_force_threshold_n) and self.contact_force_threshold_n >= 0.0):
            raise InputError(f"TCE contact_force_threshold_n must be finite and >= 0, "
                             f"got {self.contact_force_threshold_n!r}")
        for name in ("relief_radius_m", "max_surface_relief_m", "rigid_stiffness_n_per_m", "min_force_variation_n",
                     "max_penetration_offset_m"):
            value = getattr(self, name)
            if not (value >= 0.0 and (math.isfinite(value) or name == "max_penetration_offset_m")):
                raise InputError(f"TCE {name} must be finite and >= 0, got {value!r}")
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
    rigid: bool = False                     # the window shows ground at least rigid_stiffness_n_per_m stiff
    penetration_offset_m: float = 0.0       # how much the window's penetrations read too deep [m] (offset fit)


RESTART_MIN_QUALITY = 0.8
"""R^2 x offset consistency of a stance's own fit from which it may restart the window."""

RESTART_STIFFNESS_RATIO = 1.3
"""A stance's stiffness this factor away from the window's (either way) restarts the window."""

RESTART_CHECK_EVERY = 10
RESTART_CHECK_UNTIL = 3
"""The stance's fit is compared with the window's at min_samples samples, then every RESTART_CHECK_EVERY up to
RESTART_CHECK_UNTIL x min_samples (a terrain change shows early in the stance that lands on it)."""


class KelvinVoigtWindows:
    """Sliding windows and weighted least squares of F = k p (+ d dp/dt) for ``n`` independent channels
    (legs), fitted together. Degenerate windows keep the previous estimate and lower its confidence."""

    def __init__(self, settings: TceSettings, n: int) -> None:
        self.settings, self.n = settings, int(n)
        m = settings.window
        self._data = np.zeros((self.n, 4, m))          # force, penetration, rate, time since touchdown
        self._next = np.zeros(self.n, dtype=int)
        self._count = np.zeros(self.n, dtype=int)       # ring slots in use (samples and lost ticks)
        self._valid = np.zeros((self.n, m), dtype=bool)  # slots holding a sample (not a lost tick)
        self._slots = np.arange(m)
        self._rows = np.arange(self.n)
        self._segment = np.zeros(self.n, dtype=int)     # slots of the current stance (since the last gap)
        self.restarts = np.zeros(self.n, dtype=np.int64)  # windows restarted at a terrain change
        self.estimates = [LegEstimate() for _ in range(self.n)]

    def add(self, mask: np.ndarray, force: np.ndarray, penetration: np.ndarray, rate: np.ndarray,
            elapsed: np.ndarray | None = None) -> None:
        """Append one sample to each channel where ``mask``; non-finite samples are ignored. ``elapsed``: time
        since the stance's touchdown (any unit; base_drift_fit), zeros when None."""
        elapsed = np.zeros(self.n) if elapsed is None else np.asarray(elapsed, float)
        sample = np.stack([np.asarray(force, float), np.asarray(penetration, float), np.asarray(rate, float),
                           elapsed], 1)
        take = np.asarray(mask, dtype=bool) & np.all(np.isfinite(sample), axis=1)
        self._segment = np.where(take, self._segment + 1, 0)
        if not take.any():
            return
        rows = self._rows[take]
        self._data[rows, :, self._next[rows]] = sample[take]
        self._valid[rows, self._next[rows]] = True
        self._next[rows] = (self._next[rows] + 1) % self.settings.window
        self._count[rows] = np.minimum(self._count[rows] + 1, self.settings.window)

    def skip(self, mask: np.ndarray, slots: int) -> None:
        """Lost ticks: ``slots`` empty slots in each channel where ``mask``, so that the window still spans the
        time it would have (old samples leave it on time when a consumer loses ticks)."""
        rows = self._rows[np.asarray(mask, dtype=bool)]
        self._segment[rows] += int(slots)
        for _ in range(min(int(slots), self.settings.window)):
            if not len(rows):
                return
            self._valid[rows, self._next[rows]] = False
            self._next[rows] = (self._next[rows] + 1) % self.settings.window
            self._count[rows] = np.minimum(self._count[rows] + 1, self.settings.window)

    def samples(self, weights: np.ndarray | None = None) -> np.ndarray:
        """(n,) samples in each channel's window (slots of lost ticks left out); ``weights`` if already had."""
        return np.count_nonzero((self.weights() if weights is None else weights) > 0.0, axis=1)

    def weights(self) -> np.ndarray:
        """(n, window) weight of every ring slot: zero for empty slots and lost ticks, otherwise linear in
        recency (the newest slot weighs 1, the oldest 1/count) or uniform."""
        m = self.settings.window
        age = (self._next[:, None] - 1 - self._slots[None, :]) % m       # 0 = newest
        count = np.maximum(self._count, 1)[:, None]
        filled = (age < self._count[:, None]) & self._valid
        if self.settings.weighting == "linear":
            return np.where(filled, (count - age) / count, 0.0)
        return filled.astype(float)

    def fit(self, mask: np.ndarray | None = None) -> list[LegEstimate]:
        """Refit the channels where ``mask`` (all when None) and return every channel's estimate."""
        mask = np.ones(self.n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        w = self.weights()
        counts = self.samples(w)
        force, pen, rate, elapsed = self._data[:, 0], self._data[:, 1], self._data[:, 2], self._data[:, 3]
        columns = [np.ones_like(force), force, force * force, pen * pen, pen * rate, rate * rate,
                   pen * force, rate * force, pen, rate]
        if self._drift_fit:
            columns += [elapsed, elapsed * elapsed, elapsed * pen, elapsed * rate, elapsed * force]
        products = np.stack(columns, axis=1)
        sums = np.einsum("lm,lkm->lk", w, products)
        for leg in np.flatnonzero(mask):
            self._fit_channel(self.estimates[leg], int(counts[leg]), sums[leg], pen[leg], w[leg])
            if self.settings.window_restart and self._restart_due(int(leg), int(counts[leg])):
                self._check_restart(int(leg), products[leg], pen[leg], w[leg])
        return self.estimates

    @property
    def _drift_fit(self) -> bool:
        return self.settings.base_drift_fit and self.settings.penetration_reference == "touchdown"

    def _restart_due(self, leg: int, count: int) -> bool:
        """Whether the current stance is at a point where its fit is compared with the window's."""
        first = self.settings.min_samples
        segment = int(self._segment[leg])
        return (count > segment >= first and segment <= RESTART_CHECK_UNTIL * first
                and (segment - first) % RESTART_CHECK_EVERY == 0)

    def _check_restart(self, leg: int, products: np.ndarray, pen: np.ndarray, w: np.ndarray) -> None:
        """Fit the current stance alone; restart the window from it at a terrain change (``window_restart``)."""
        m = self.settings.window
        age = (self._next[leg] - 1 - self._slots) % m
        segment = int(self._segment[leg])
        w_stance = np.where(age < segment, w, 0.0)
        count = int(np.count_nonzero(w_stance))
        stance = LegEstimate()
        self._fit_channel(stance, count, products @ w_stance, pen, w_stance)
        window = self.estimates[leg]
        low, high = self.settings.stiffness_range_n_per_m
        if not (stance.valid and not stance.stale and low < stance.stiffness_n_per_m < high):
            return
        quality_stance = 1.0 if stance.rigid else stance.confidence * m / max(count, 1)
        if quality_stance < RESTART_MIN_QUALITY:
            return
        if window.valid and not window.stale:
            quality_window = 1.0 if window.rigid else window.confidence * m / max(window.samples, 1)
            ratio = stance.stiffness_n_per_m / window.stiffness_n_per_m
            changed = (stance.rigid != window.rigid or quality_window < 0.5 * RESTART_MIN_QUALITY
                       or (not stance.rigid and not 1.0 / RESTART_STIFFNESS_RATIO <= ratio <= RESTART_STIFFNESS_RATIO))
        else:
            changed = True
        if not changed:
            return
        self._valid[leg, age >= segment] = False
        self._count[leg] = min(segment, m)
        self.restarts[leg] += 1
        w_new = self.weights()[leg]
        self._fit_channel(window, int(np.count_nonzero(w_new)), products @ w_new, pen, w_new)

    def _fit_channel(self, est: LegEstimate, count: int, sums: np.ndarray, pen: np.ndarray, w: np.ndarray) -> None:
        s = self.settings
        est.samples = count
        if count < s.min_samples:
            est.stale = est.valid
            est.confidence = est.confidence * 0.99 if est.valid else 0.0
            return
        if self._drift_fit:
            self._fit_with_drift(est, count, sums)
            return
        total_w = sums[_W]
        mean_p = float(w @ pen) / total_w
        variance_p = max(sums[_PP] / total_w - mean_p**2, 0.0)
        if self._rigid(est, count, sums, math.sqrt(variance_p)):
            return
        if math.sqrt(sums[_PP] / total_w) < s.min_penetration_m or math.sqrt(variance_p) < \
                s.min_penetration_variation_m:
            self._keep_previous(est)
            return
        a, b, c = sums[_PP], sums[_PR], sums[_RR]
        g_p, g_r = sums[_PF], sums[_RF]
        solved = self._solve(a, b, c, g_p, g_r)
        if solved is None:
            self._keep_previous(est)
            return
        k, d = solved
        explained = k * g_p + (d * g_r if s.estimate_damping else 0.0)
        total = sums[_FF] - sums[_F] ** 2 / total_w       # weighted total sum of squares of F
        residual = max(sums[_FF] - explained, 0.0)         # at the LS optimum: F'WF - theta'P'WF
        r2 = 1.0 - residual / total if total > 0.0 else 1.0
        offset = self._penetration_offset(sums, total_w, mean_p)
        k_clamped = float(np.clip(k, *s.stiffness_range_n_per_m))
        d_clamped = float(np.clip(d, *s.damping_range_ns_per_m)) if s.estimate_damping else d
        est.clamped = k_clamped != k or (s.estimate_damping and d_clamped != d)
        est.stiffness_n_per_m, est.damping_ns_per_m = k_clamped, d_clamped
        est.penetration_offset_m = offset
        fill = count / s.window
        consistent = abs(offset) <= s.max_penetration_offset_m   # False for NaN (no offset fit possible)
        est.confidence = float(np.clip(fill * max(r2, 0.0), 0.0, 1.0)) * (0.5 if est.clamped else 1.0) * consistent
        est.valid, est.stale, est.rigid = True, False, False

    def _rigid(self, est: LegEstimate, count: int, sums: np.ndarray, std_p: float) -> bool:
        """Whether the window shows ground at least rigid_stiffness_n_per_m stiff (std F / ``std_p``, with F
        varying by min_force_variation_n); if so ``est`` becomes that lower bound, flagged rigid."""
        s = self.settings
        total_w = sums[_W]
        std_f = math.sqrt(max(sums[_FF] / total_w - (sums[_F] / total_w) ** 2, 0.0))
        if not (std_f >= s.min_force_variation_n and std_f >= s.rigid_stiffness_n_per_m * std_p):
            return False
        ratio = std_f / std_p if std_p > 0.0 else math.inf
        est.stiffness_n_per_m = float(min(ratio, s.stiffness_range_n_per_m[1]))
        est.confidence = count / s.window
        est.valid, est.stale, est.clamped, est.rigid = True, False, False, True
        return True

    def _fit_with_drift(self, est: LegEstimate, count: int, sums: np.ndarray) -> None:
        """``base_drift_fit``: F = k p (+ d dp/dt) + g t + c by weighted least squares (g = k e, c also takes
        d e and a touchdown depth that was off); the rigid check on the part of p that t and a constant do not
        explain; the confidence is the fill ratio x the partial R^2 of the ground's terms given (t, 1)."""
        s = self.settings
        total_w = sums[_W]
        # p's variance left after its regression on (t, 1): what the drift cannot have made
        drift = np.array([[sums[_TT], sums[_T]], [sums[_T], total_w]])
        det_drift = drift[0, 0] * drift[1, 1] - drift[0, 1] ** 2
        if not det_drift > 1e-12 * drift[0, 0] * drift[1, 1]:
            self._keep_previous(est)
            return
        # p and F on (t, 1) in one solve: what of p the drift cannot have made, and what of F it explains
        cross_p, cross_f = np.array([sums[_TP], sums[_P]]), np.array([sums[_TF], sums[_F]])
        on_drift = np.linalg.solve(drift, np.column_stack([cross_p, cross_f]))
        std_p = math.sqrt(max(sums[_PP] - float(cross_p @ on_drift[:, 0]), 0.0) / total_w)
        if self._rigid(est, count, sums, std_p):
            est.penetration_offset_m = 0.0
            return
        if std_p < s.min_penetration_variation_m:
            self._keep_previous(est)
            return
        if s.estimate_damping:
            normal = np.array([[sums[_PP], sums[_PR], sums[_TP], sums[_P]],
                               [sums[_PR], sums[_RR], sums[_TR], sums[_R]],
                               [sums[_TP], sums[_TR], sums[_TT], sums[_T]],
                               [sums[_P], sums[_R], sums[_T], total_w]])
            rhs = np.array([sums[_PF], sums[_RF], sums[_TF], sums[_F]])
        else:
            normal = np.array([[sums[_PP], sums[_TP], sums[_P]], [sums[_TP], sums[_TT], sums[_T]],
                               [sums[_P], sums[_T], total_w]])
            rhs = np.array([sums[_PF], sums[_TF], sums[_F]])
        diagonal = np.diag(normal)
        scale = np.sqrt(np.where(diagonal > 0.0, diagonal, 1.0))
        scaled = normal / np.outer(scale, scale)
        if not np.linalg.det(scaled) > s.min_relative_determinant:
            self._keep_previous(est)
            return
        theta = np.linalg.solve(scaled, rhs / scale) / scale
        k = float(theta[0])
        d = float(theta[1]) if s.estimate_damping else float("nan")
        # Confidence from what the ground's terms explain beyond the drift's (t, 1): F rises and falls with
        # the time since touchdown on any ground, so the plain R^2 stayed high where p only carried noise
        # (rigid ground under a noisy estimate read 3,600 N/m at its 10 % quantile, adopted; measured).
        residual_drift = max(sums[_FF] - float(cross_f @ on_drift[:, 1]), 0.0)
        residual = max(sums[_FF] - float(theta @ rhs), 0.0)
        r2 = 1.0 - residual / residual_drift if residual_drift > 0.0 else 0.0
        k_clamped = float(np.clip(k, *s.stiffness_range_n_per_m))
        d_clamped = float(np.clip(d, *s.damping_range_ns_per_m)) if s.estimate_damping else d
        est.clamped = k_clamped != k or (s.estimate_damping and d_clamped != d)
        est.stiffness_n_per_m, est.damping_ns_per_m = k_clamped, d_clamped
        est.penetration_offset_m = 0.0
        # A clamped fit is not confident here: with the drift's two extra terms a window whose p holds only
        # noise (a robot standing, rigid ground) fitted k to the 100 N/m bound with a partial R^2 that still
        # passed the c3WBC's gate (graph_tour replay on the estimate: most confident soft readings on rigid).
        est.confidence = 0.0 if est.clamped else float(np.clip(count / s.window * max(r2, 0.0), 0.0, 1.0))
        est.valid, est.stale, est.rigid = True, False, False

    def _solve(self, a: float, b: float, c: float, g_p: float, g_r: float) -> tuple[float, float] | None:
        """(k, d) of the normal equations [[a, b], [b, c]] (k, d) = (g_p, g_r) (d NaN without damping);
        None when p and dp/dt are collinear."""
        if not self.settings.estimate_damping:
            return g_p / a, float("nan")
        det = a * c - b * b
        if not (math.isfinite(det) and det > self.settings.min_relative_determinant * a * c):
            return None
        return (c * g_p - b * g_r) / det, (a * g_r - b * g_p) / det

    def _penetration_offset(self, sums: np.ndarray, total_w: float, mean_p: float) -> float:
        """The offset of F = k' (p - offset) (+ d' dp/dt): the LS with a constant, from centred moments. NaN
        when that fit is ill-posed or not a spring (k' <= 0); 0 when the check is off (also with the touchdown
        reference, where each stance starts at its own depth and an offset only says that the base estimate
        moved during the window's stances: on graph_tour's T1 with the wbc on the estimate the check left the
        TCE confident in 14 % of the ticks and HyQ fell at T2's entry; without it 99 %, and HyQ walked on)."""
        s = self.settings
        if not math.isfinite(s.max_penetration_offset_m) or s.penetration_reference == "touchdown":
            return 0.0
        mean_f, mean_r = sums[_F] / total_w, sums[_R] / total_w
        a = sums[_PP] - total_w * mean_p**2
        b = sums[_PR] - total_w * mean_p * mean_r
        c = sums[_RR] - total_w * mean_r**2
        if not a > 0.0:
            return float("nan")
        solved = self._solve(a, b, c, sums[_PF] - total_w * mean_p * mean_f, sums[_RF] - total_w * mean_r * mean_f)
        if solved is None or not solved[0] > 0.0:
            return float("nan")
        k, d = solved
        constant = mean_f - k * mean_p - (d * mean_r if self.settings.estimate_damping else 0.0)
        return float(-constant / k)

    @staticmethod
    def _keep_previous(est: LegEstimate) -> None:
        est.stale = est.valid   # stale: a previous estimate is being kept
        est.confidence *= 0.9   # an estimate that cannot be refreshed loses confidence


class WindowedKelvinVoigtFit:
    """One channel of ``KelvinVoigtWindows``: the sliding window and fit of a single leg and direction."""

    def __init__(self, settings: TceSettings) -> None:
        self.settings = settings
        self._windows = KelvinVoigtWindows(settings, 1)

    @property
    def estimate(self) -> LegEstimate:
        return self._windows.estimates[0]

    def add(self, force_n: float, penetration_m: float, rate_m_s: float) -> None:
        """Append one stance sample; non-finite samples are ignored."""
        self._windows.add(np.ones(1, bool), np.array([force_n]), np.array([penetration_m]), np.array([rate_m_s]))

    def fit(self) -> LegEstimate:
        """Refit on the current window; keeps (and flags) the previous estimate when ill-posed."""
        return self._windows.fit()[0]


@dataclass(frozen=True)
class ContactSample:
    """Estimated contact state of one leg (world frame unless stated)."""

    in_contact: bool
    force_n: np.ndarray          # (3,) ground reaction force on the foot
    normal: np.ndarray           # (3,) unit terrain normal under the foot
    penetration_m: float         # along the normal, contact frame
    penetration_rate_m_s: float  # along the normal, contact frame
    foot_position_m: np.ndarray | None = None   # (3,) foot-sphere centre
    foot_velocity_m_s: np.ndarray | None = None  # (3,)
    surface_relief_m: float = 0.0  # height span of the surface around a stance foot (NaN: partly unknown)


def foot_penetration(foot_centre_m: np.ndarray, radius_m: float, surface_z_m: float, normal: np.ndarray) -> float:
    """Penetration [m] of a foot sphere into the undeformed surface along the unit normal (< 0: above it):
    the surface point under the foot centre minus the sphere's lowest point along -normal, projected on it."""
    surface = np.array([foot_centre_m[0], foot_centre_m[1], surface_z_m])
    return float(normal @ (surface - (foot_centre_m - radius_m * normal)))


class FiniteDifferenceAcceleration:
    """Generalised accelerations vdot = (v_k - v_{k-1}) / dt from consecutive ticks; None after a gap longer
    than ``max_gap_s`` [s] (a skipped or out-of-order tick) or on the first call."""

    def __init__(self, max_gap_s: float) -> None:
        self.max_gap_s = float(max_gap_s)
        self._previous: tuple[float, np.ndarray] | None = None

    def update(self, t_s: float, v: np.ndarray) -> np.ndarray | None:
        previous, self._previous = self._previous, (float(t_s), np.array(v, dtype=float))
        if previous is None or not 0.0 < t_s - previous[0] <= self.max_gap_s:
            return None
        return (self._previous[1] - previous[1]) / (t_s - previous[0])


def contact_tangents(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents of the contact frame: t1 along the world x axis projected on the terrain plane
    (world y when the normal is along x), t2 = n x t1."""
    reference = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = reference - (reference @ normal) * normal
    t1 /= np.linalg.norm(t1)
    return t1, cross3(normal, t1)


class TerrainComplianceEstimator:
    """Contact-state estimation plus one windowed fit per leg for the normal direction (and, optionally,
    one pooled tangential fit per leg)."""

    def __init__(self, model: RobotModel, settings: TceSettings | None = None) -> None:
        self.model = model
        self.settings = settings or TceSettings()
        self.normal = KelvinVoigtWindows(self.settings, NUM_LEGS)
        self.tangential = KelvinVoigtWindows(self.settings, NUM_LEGS) if self.settings.estimate_tangential else None
        self._anchor: list[np.ndarray | None] = [None] * NUM_LEGS   # foot position at touchdown (tangential)
        self._was_in_contact = np.zeros(NUM_LEGS, dtype=bool)
        self._touchdown_offset = np.zeros(NUM_LEGS)   # penetration_reference touchdown: p = p_surface - offset
        self._stance_ticks = np.zeros(NUM_LEGS)        # updates since each stance's first sample (base_drift_fit)
        self._relief_offsets = self._offsets(self.settings.relief_radius_m)
        self.edge_samples = np.zeros(NUM_LEGS, dtype=np.int64)   # stance samples left out at edges, per leg

    @staticmethod
    def _offsets(r: float) -> tuple[tuple[float, float], ...]:
        return ((r, 0.0), (-r, 0.0), (0.0, r), (0.0, -r))

    def reconfigure(self, settings: TceSettings) -> None:
        """Apply ``settings`` from the next update (thresholds, validity limits), keeping the windows and the
        estimates. The window length and estimate_tangential shape the buffers and are fixed (InputError)."""
        if settings.window != self.settings.window or settings.estimate_tangential != self.settings.estimate_tangential:
            raise InputError("TCE window and estimate_tangential are fixed for the estimator's lifetime")
        self.settings = settings
        self.normal.settings = settings
        if self.tangential is not None:
            self.tangential.settings = settings
        self._relief_offsets = self._offsets(settings.relief_radius_m)

    @property
    def estimates(self) -> list[LegEstimate]:
        """Normal-direction estimates per leg (LF, RF, LH, RH)."""
        return self.normal.estimates

    @property
    def tangential_estimates(self) -> list[LegEstimate] | None:
        return None if self.tangential is None else self.tangential.estimates

    def contact_states(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, height: HeightFunction,
                       normal: NormalFunction | None = None, vdot: np.ndarray | None = None) -> list[ContactSample]:
        """Contact states from (q, v) (Pinocchio convention) and measured joint torques tau [N m]
        (canonical order). ``height(x, y)`` is the undeformed terrain surface [m] (e.g. a heightmap).
        ``vdot``: generalised accelerations (e.g. finite differences of v); with it the force comes from the
        full leg dynamics J_leg^T F = M_leg vdot + h_leg - tau_leg (touchdown impacts), without it the static
        part only."""
        tau = np.asarray(tau, dtype=float)
        if tau.shape != (NUM_JOINTS,) or not np.all(np.isfinite(tau)):
            raise InputError(f"TCE needs {NUM_JOINTS} finite joint torques, got {tau!r}")
        m = self.model
        # Foot kinematics and h alone (RobotModel.foot_dynamics, about 4x cheaper than a full update), M only
        # with accelerations; the four legs' forces in one batched solve.
        dyn = m.foot_dynamics(q, v, with_mass_matrix=vdot is not None)
        h = dyn.nonlinear_effects
        if vdot is not None:
            vdot = np.asarray(vdot, dtype=float)
            if vdot.shape != (m.nv,) or not np.all(np.isfinite(vdot)):
                raise InputError(f"TCE vdot must be {m.nv} finite values, got shape {vdot.shape}")
            assert dyn.mass_matrix is not None
            h = h + dyn.mass_matrix @ vdot
        feet, velocities = dyn.foot_positions, dyn.foot_velocities
        forces = m.foot_forces_from_joint_torques(dyn.foot_jacobians, tau, h)
        radius = m.description.foot_radius_m
        up = np.array([0.0, 0.0, 1.0])
        many = getattr(height, "many", None)
        if many is not None:
            # One look-up for the four feet and their relief points (tal_core.heightmap.GridHeights).
            offsets = np.array(((0.0, 0.0), *self._relief_offsets))
            around_xy = feet[:, None, :2] + offsets[None]
            around_z = np.asarray(many(around_xy[..., 0].ravel(), around_xy[..., 1].ravel()),
                                  dtype=float).reshape(NUM_LEGS, len(offsets))
        samples = []
        for leg in range(NUM_LEGS):
            force = forces[leg]
            x, y = float(feet[leg, 0]), float(feet[leg, 1])
            n = up if normal is None else np.asarray(normal(x, y), dtype=float)
            n = n / np.linalg.norm(n)
            surface_z = float(height(x, y)) if many is None else float(around_z[leg, 0])
            penetration = foot_penetration(feet[leg], radius, surface_z, n)
            rate = float(-(n @ velocities[leg]))
            in_contact = bool(n @ force >= self.settings.contact_force_threshold_n)
            relief = 0.0  # only stance samples enter the fit: their relief (the look-ups' spread) alone
            if in_contact:
                around = (around_z[leg] if many is not None else
                          [surface_z] + [float(height(x + dx, y + dy)) for dx, dy in self._relief_offsets])
                relief = float(np.ptp(around))   # NaN where a look-up is unknown (Python's max would skip it)
            samples.append(ContactSample(in_contact, force, n, penetration, rate, feet[leg], velocities[leg],
                                         relief))   # rows of this call's own arrays
        return samples

    def skip(self, mask: np.ndarray, slots: int) -> None:
        """Lost ticks of the legs in ``mask`` (``KelvinVoigtWindows.skip``): their stances' clocks go on."""
        mask = np.asarray(mask, dtype=bool)
        self.normal.skip(mask, slots)
        self._stance_ticks = np.where(mask & self._was_in_contact, self._stance_ticks + slots, self._stance_ticks)

    def update(self, samples: list[ContactSample]) -> list[LegEstimate]:
        """Feed the stance legs' samples and refit them; swing legs keep their estimate. Returns the
        normal-direction estimates."""
        stance = np.array([s.in_contact for s in samples], dtype=bool)
        force = np.array([float(s.normal @ s.force_n) for s in samples])
        pen = np.array([s.penetration_m for s in samples])
        rate = np.array([s.penetration_rate_m_s for s in samples])
        relief = np.array([s.surface_relief_m for s in samples], dtype=float)
        if self.settings.penetration_reference == "touchdown":
            pen = self._from_touchdown(stance, force, pen, rate)
        edge = stance & ~(relief <= self.settings.max_surface_relief_m)   # NaN relief counts as an edge
        self.edge_samples += edge
        self._stance_ticks = np.where(stance & self._was_in_contact, self._stance_ticks + 1.0, 0.0)
        self.normal.add(stance & ~edge, force, pen, rate, self._stance_ticks)
        self.normal.fit(stance & ~edge)
        if self.tangential is not None:
            self._update_tangential(samples, stance)
        self._was_in_contact = stance
        return self.normal.estimates

    def _from_touchdown(self, stance: np.ndarray, force: np.ndarray, pen: np.ndarray, rate: np.ndarray) -> np.ndarray:
        """Penetrations measured from each stance's first sample, taken to be (F - d dp/dt) / k deep (the leg's
        estimate; 0 without one, or on rigid ground): a foot landing at 0.3 m/s on 400 N s/m ground reads 120 N
        of damping force with no depth yet."""
        for leg in np.flatnonzero(stance & ~self._was_in_contact):
            estimate = self.normal.estimates[leg]
            k, d = estimate.stiffness_n_per_m, estimate.damping_ns_per_m
            depth = 0.0
            if estimate.valid and not estimate.rigid and math.isfinite(k) and k > 0.0:
                spring = force[leg] - (d * rate[leg] if math.isfinite(d) else 0.0)
                depth = max(0.0, spring / k)
            self._touchdown_offset[leg] = pen[leg] - depth
        return np.where(stance, pen - self._touchdown_offset, pen)

    def _update_tangential(self, samples: list[ContactSample], stance: np.ndarray) -> None:
        """Two samples per stance leg (t1, t2): force along t against the foot's displacement along t
        since touchdown (positive when the ground is pushed, like the normal penetration)."""
        assert self.tangential is not None
        for axis in range(2):
            force, disp, rate = np.zeros(NUM_LEGS), np.zeros(NUM_LEGS), np.zeros(NUM_LEGS)
            for leg, s in enumerate(samples):
                if not s.in_contact or s.foot_position_m is None or s.foot_velocity_m_s is None:
                    self._anchor[leg] = None
                    continue
                if not self._was_in_contact[leg] or self._anchor[leg] is None:
                    self._anchor[leg] = s.foot_position_m.copy()
                t = contact_tangents(s.normal)[axis]
                force[leg] = float(t @ s.force_n)
                disp[leg] = -float(t @ (s.foot_position_m - self._anchor[leg]))
                rate[leg] = -float(t @ s.foot_velocity_m_s)
            self.tangential.add(stance, force, disp, rate)
        self.tangential.fit(stance)
