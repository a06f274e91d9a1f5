"""Settings of the Vision-based Pose Adaptation (VPA), thesis ViTAL chapter and its implementation details.

Heights in the VPA are *relative*: a leg map's hip heights are measured from that map's reference
terrain height (the median of its known cells), and the body height is measured from the body reference
(the mean of the current leg maps' references, i.e. the terrain under the robot). The thesis writes
world heights for a robot that starts on the ground at z = 0; relative heights keep the same numbers
(0.2-0.8 m) meaningful on a staircase one metre up, and they make the exact evaluation and the CNN
translation invariant (the FEC only depends on height differences).

Where the thesis gives a value it is the default and the comment says so; the rest is ours.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from tal_perception.errors import VpaConfigError

FloatArray = NDArray[np.float64]


class CostKind(Enum):
    """The thesis' pose-optimiser costs (to be maximised)."""

    SUM = "sum"  # C_sum = sum_l F_l(z_l)^2
    PROD = "prod"  # C_prod = prod_l F_l(z_l)^2
    INT = "int"  # C_int = sum_l (m (F_l(z_l - m) + F_l(z_l + m)))^2, margin m


SWING_HIP_MODELS = ("level", "terrain")  # VpaSettings.swing_hip_model
LEG_WEIGHTINGS = ("none", "peak")  # VpaSettings.leg_weighting


@dataclass(frozen=True)
class VpaSettings:
    """Pose evaluation grid, RBF model, optimiser bounds and horizon of the VPA (SI units)."""

    hip_height_min_m: float = 0.2  # [m] lowest sampled hip height above the map reference (thesis)
    hip_height_max_m: float = 0.8  # [m] highest sampled hip height (thesis)
    hip_height_step_m: float = 0.02  # [m] sampling step: 31 samples (thesis)
    rbf_count: int = 30  # [-] E, Gaussians of the function approximation (thesis)
    rbf_intersection: float = 0.7  # [-] neighbouring Gaussians cross at this value (ours; the thesis'
    # example uses 0.5, which leaves a 22 % ripple between the centres of E = 30 narrow Gaussians and so
    # spurious local optima for the pose optimiser; at 0.7 a constant is reproduced within 0.9 %)
    pose_lower: tuple[float, float, float] = (0.2, -0.35, -0.35)  # [m, rad, rad] u_min (thesis)
    pose_upper: tuple[float, float, float] = (0.8, 0.35, 0.35)  # [m, rad, rad] u_max (thesis)
    max_change: tuple[float, float, float] = (0.05, 0.1, 0.1)  # [m, rad, rad] |u - u_prev| per update (ours)
    cost: CostKind = CostKind.INT  # the thesis' robust choice
    cost_margin_m: float = 0.025  # [m] m of C_int (thesis)
    horizon: int = 2  # [-] N_h (thesis)
    horizon_shift_m: float | None = None  # [m] map overlap step; None: half the map diagonal (issue)
    smoothness_weight: float = 1.0  # [-] weight of |u_j - u_j+1|^2 between horizon stages (ours)
    # [-] an optimum away from the previous pose replaces the one reached from it only when its objective is
    # higher by this fraction (ours): with several starts, two optima of nearly equal value made the pose jump
    # back and forth between updates (open loop on the stairs, ``vpa_open_loop``).
    switch_margin: float = 0.0
    max_map_age_s: float = 0.5  # [s] older heightmaps are stale: the default pose is held (ours)
    min_speed_for_shift_mps: float = 0.02  # [m/s] below this the future map equals the current one (ours)
    # How the hip moves during the evaluated swing (``PoseEvaluator.liftoff_rise``): "level" (thesis, at the
    # evaluated height throughout) or "terrain" (ours: from as high above the lift-off terrain to the
    # evaluated height above the map reference, linearly in time).
    swing_hip_model: str = "level"
    # The thesis' Q in ||F_l||_Q: "none" (Q = 1, thesis) or "peak" (ours: each leg's curve divided by its own
    # peak over the sampled heights, at least leg_weight_floor, so that a leg with few safe footholds, e.g. a
    # front leg stepping down, weighs as much as one with many).
    leg_weighting: str = "none"
    leg_weight_floor: float = 0.05  # [-] normalised NSF; peaks below it are not scaled up further

    def __post_init__(self) -> None:
        for field in fields(self):
            value = getattr(self, field.name)
            if field.name == "cost":
                if not isinstance(value, CostKind):
                    raise VpaConfigError(f"VpaSettings.cost must be a CostKind, got {value!r}")
                continue
            if field.name in ("swing_hip_model", "leg_weighting"):
                allowed = SWING_HIP_MODELS if field.name == "swing_hip_model" else LEG_WEIGHTINGS
                if value not in allowed:
                    raise VpaConfigError(f"VpaSettings.{field.name} must be one of {allowed}, got {value!r}")
                continue
            if field.name in ("rbf_count", "horizon"):
                if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                    raise VpaConfigError(f"VpaSettings.{field.name} must be an integer >= 1, got {value!r}")
                continue
            if field.name == "horizon_shift_m" and value is None:
                continue
            values = value if isinstance(value, tuple) else (value,)
            if not all(_finite(v) for v in values) or (isinstance(value, tuple) and len(value) != 3):
                raise VpaConfigError(f"VpaSettings.{field.name} must be finite number(s), got {value!r}")
        if not 0.0 < self.hip_height_min_m < self.hip_height_max_m:
            raise VpaConfigError(
                f"VpaSettings: need 0 < hip_height_min_m < hip_height_max_m, got "
                f"{self.hip_height_min_m} and {self.hip_height_max_m}"
            )
        if self.hip_height_step_m <= 0.0:
            raise VpaConfigError(f"VpaSettings.hip_height_step_m must be > 0, got {self.hip_height_step_m}")
        if not 0.0 < self.rbf_intersection < 1.0:
            raise VpaConfigError(f"VpaSettings.rbf_intersection must be in (0, 1), got {self.rbf_intersection}")
        lower, upper = np.array(self.pose_lower), np.array(self.pose_upper)
        if not (lower < upper).all():
            raise VpaConfigError(f"VpaSettings: pose_lower {self.pose_lower} must be < pose_upper {self.pose_upper}")
        if not (np.array(self.max_change) > 0.0).all():
            raise VpaConfigError(f"VpaSettings.max_change must be > 0, got {self.max_change}")
        if not 0.0 < self.leg_weight_floor <= 1.0:
            raise VpaConfigError(f"VpaSettings.leg_weight_floor must be in (0, 1], got {self.leg_weight_floor}")
        for name in ("cost_margin_m", "smoothness_weight", "min_speed_for_shift_mps", "switch_margin"):
            if getattr(self, name) < 0.0:
                raise VpaConfigError(f"VpaSettings.{name} must be >= 0, got {getattr(self, name)}")
        if self.max_map_age_s <= 0.0:
            raise VpaConfigError(f"VpaSettings.max_map_age_s must be > 0 [s], got {self.max_map_age_s}")
        if self.horizon_shift_m is not None and not (_finite(self.horizon_shift_m) and self.horizon_shift_m >= 0):
            raise VpaConfigError(f"VpaSettings.horizon_shift_m must be >= 0 or None, got {self.horizon_shift_m!r}")

    @property
    def hip_heights(self) -> FloatArray:
        """(N,) [m] sampled hip heights above the map reference (31 with the thesis' values)."""
        count = int(round((self.hip_height_max_m - self.hip_height_min_m) / self.hip_height_step_m)) + 1
        return self.hip_height_min_m + self.hip_height_step_m * np.arange(count)

    def shift_m(self, patch_cells: int, resolution_m: float) -> float:
        """[m] distance between the horizon stages' map centres (default half the map diagonal)."""
        if self.horizon_shift_m is not None:
            return float(self.horizon_shift_m)
        return 0.5 * math.sqrt(2.0) * patch_cells * resolution_m


def _finite(value: object) -> bool:
    return isinstance(value, (int, float, np.floating)) and not isinstance(value, bool) and math.isfinite(value)
