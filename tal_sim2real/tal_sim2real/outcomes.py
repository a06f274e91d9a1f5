"""Outcome types of the identification: settings, per-candidate findings, per-subsystem costs."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

from .model import SimModel
from .remainder import Remainder

LOG = logging.getLogger("tal.sim2real.identify")

GYRO_BIAS_FLOOR_RAD_S = 1e-3  # [rad/s] smaller biases are not worth naming
ACCEL_BIAS_FLOOR_M_S2 = 0.02  # [m/s^2]
IMU_T_STATISTIC = 6.0
STIFF_GROUND_N_PER_M = 1e5  # [N/m] stiffer ground sinks a loaded HyQ foot by < 4 mm


@dataclass
class Settings:
    """Windows [s], segment plan and decision thresholds (see the module docstring); ``segment_workers``:
    processes that share the re-simulation of each prediction's open-loop segments (1: this one alone; the
    results do not depend on it, only the time); ``holdout_floor_draws``: noise perturbations averaged for the
    held-out dynamics floor against which the remainder is judged (one draw's floor varied fourfold with the
    seed on a dataset of the benchmark)."""

    settle_s: float = 1.0
    holdout_fraction: float = 0.25
    segment_every_s: float = 0.2
    horizon_s: float = 0.1
    min_bic_drop: float = 10.0
    min_validation_gain: float = 0.1
    floor_factor: float = 1.5
    max_pair_candidates: int = 3
    torque_block_s: float = 0.5
    torque_holdout_every: int = 4
    segment_workers: int = 1
    holdout_floor_draws: int = 5


@dataclass
class Finding:
    """The outcome for one candidate effect."""

    candidate: str
    subsystem: str
    status: str  # named | rejected | not_excited | missing_signals | not_screened
    values: dict[str, float] = field(default_factory=dict)
    intervals: dict[str, tuple[float, float]] = field(default_factory=dict)
    cost_ratio: float | None = None  # fitted cost / nominal cost on the fitting data
    note: str = ""
    where: str = ""  # per-leg / per-joint variants (library.VARIANTS): the leg ("RF") or joint ("lh_kfe")

    @property
    def label(self) -> str:
        """The candidate's name with its leg or joint, e.g. ``leg_torque_gain[RF]``."""
        return f"{self.candidate}[{self.where}]" if self.where else self.candidate


@dataclass
class SubsystemResult:
    """Residual costs of one subsystem (nominal, fitted, noise floor) on fit, validation and hold-out."""

    name: str
    floor: float = math.nan
    nominal_cost: float = math.nan
    fitted_cost: float = math.nan
    holdout_before: float = math.nan
    holdout_after: float = math.nan
    holdout_floor: float = math.nan
    named: tuple[str, ...] = ()
    verdict: str = ""
    channels_before: dict[str, float] = field(default_factory=dict)
    channels_after: dict[str, float] = field(default_factory=dict)
    floor_updated: float = math.nan  # fitting-window floor re-estimated with the chosen model
    remainder: Remainder | None = None  # what the chosen model leaves on the held-out data, and where


@dataclass
class Identification:
    """Everything ``identify`` found, and the updated model."""

    bag: str
    nominal: SimModel
    updated: SimModel
    findings: list[Finding]
    subsystems: dict[str, SubsystemResult]
    windows_s: dict[str, tuple[float, float]]
    elapsed_s: float = 0.0
    simulated_steps: int = 0
    rejected_samples: dict[str, int] = field(default_factory=dict)
    gait: str = ""  # the gait the recording shows (phases.infer_gait)

    @property
    def named(self) -> list[Finding]:
        return [f for f in self.findings if f.status == "named"]

    @property
    def remainders(self) -> dict[str, Remainder]:
        """Subsystem -> its held-out remainder (subsystems that compute one)."""
        return {k: s.remainder for k, s in self.subsystems.items() if s.remainder is not None}

    @property
    def verdict(self) -> str:
        """One line: "explained" when every remainder is within its threshold, otherwise "partly explained"
        or "not explained by the library" with the subsystems concerned."""
        flagged = {k: r for k, r in self.remainders.items() if r.flagged}
        if not flagged:
            return "explained to the noise floor" if self.named else "no missing effect"
        explained_elsewhere = any(f.subsystem not in flagged for f in self.named)
        partly = explained_elsewhere or any(r.verdict.startswith("partly") for r in flagged.values())
        overall = "partly explained" if partly else "not explained by the library"
        return overall + ": " + "; ".join(f"{k}: {r.verdict}" for k, r in flagged.items())

    def gap(self, after: bool) -> float:
        """Held-out gap: sum over subsystems of cost / noise floor (1 per subsystem at the floor)."""
        total = 0.0
        for s in self.subsystems.values():
            cost = s.holdout_after if after else s.holdout_before
            if math.isfinite(cost) and math.isfinite(s.holdout_floor) and s.holdout_floor > 0:
                total += cost / s.holdout_floor
        return total
