"""Settings and inputs of the Foothold Evaluation Criteria (FEC), ViTAL chapter of the thesis.

The FEC evaluate the tuple T = (H, z_hip, twist, gait) (thesis eq. fec_tuple): a heightmap patch H
around the nominal foothold, the hip height, the base twist and the gait parameters.

Patch frame: the axes of the robot's horizontal frame (x forward, y left, base yaw only), origin at
the centre of the patch (the nominal foothold, horizontally); z is world z. Cell (r, c) of a
rows x cols patch of resolution ``res`` has its centre at x = (r - (rows - 1) / 2) res,
y = (c - (cols - 1) / 2) res (the ``tal_msgs/HeightMap`` convention).

Where the thesis gives a value (33 x 33 cells of 0.02 m; an uncertainty margin of the foot radius and
map resolution, 0.02 m) it is the default; where it gives none (it names the criteria but not their
thresholds) the default is ours and its comment says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tal_core.legs import Leg
from tal_perception.errors import FecConfigError, PerceptionInputError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class FecSettings:
    """Thresholds and margins of the four criteria and the uncertainty margin (SI units).

    Terrain roughness (TR): for every candidate, the slopes to its neighbours within
    ``roughness_radius_m`` are (h_j - h_c) / d_j; the candidate is rough if the mean of their absolute
    values exceeds ``max_mean_slope`` or their standard deviation exceeds ``max_slope_std``. A plane of
    inclination a gives mean |slope| ~ 2 tan(a) / pi and std ~ tan(a) / sqrt(2); the defaults accept
    planes up to 26 deg (28 deg fails) and reject the cells next to a 2 cm step and within two cells of
    a 10 cm step (our values, none in the thesis).
    Leg collision (LC): thigh and shin are capsules of radius ``leg_radius_m`` sampled at
    ``leg_points_per_segment`` points each; a point collides when the terrain within ``leg_radius_m``
    of it (horizontally) is higher than the point minus ``leg_radius_m + leg_clearance_m``. Shin points
    closer than ``foot_exclusion_m`` to the foot centre are the foot's business (FC) and skipped.
    Kinematic feasibility (KF): IK at touchdown, next lift-off and ``swing_samples`` instants of the
    remaining swing, with ``reach_margin_m`` from full stretch and ``joint_limit_margin_rad`` from the
    position limits. Foot trajectory collision (FC): the foot sphere at ``trajectory_samples`` instants
    of the remaining swing must stay ``foot_clearance_m`` above the terrain within its radius.
    Uncertainty margin: candidates within ``uncertainty_margin_m`` of an unsafe one are unsafe too
    (thesis: foot radius and map resolution, 0.02 m).
    """

    patch_cells: int = 33  # [-] rows = cols of the evaluated patch (thesis: 33 x 33)
    resolution_m: float = 0.02  # [m] cell edge (thesis: 0.02 m)
    roughness_radius_m: float = 0.04  # [m] neighbourhood of the slope statistics (ours: 2 foot radii)
    max_mean_slope: float = 0.3  # [-] mean |dh/dx| to the neighbours (ours)
    max_slope_std: float = 0.35  # [-] standard deviation of dh/dx to the neighbours (ours)
    leg_radius_m: float = 0.03  # [m] thigh/shin capsule radius (ours; HyQ's shin is ~0.04 m wide)
    leg_clearance_m: float = 0.01  # [m] extra distance leg-terrain (ours)
    leg_points_per_segment: int = 4  # [-] samples along thigh and along shin (ours)
    foot_exclusion_m: float = 0.06  # [m] shin points this close to the foot centre are not checked (ours)
    reach_margin_m: float = 0.02  # [m] distance kept from the stretched / folded leg (ours)
    joint_limit_margin_rad: float = 0.05  # [rad] distance kept from the joint position limits (ours)
    swing_samples: int = 4  # [-] instants of the remaining swing checked by KF and LC (ours)
    trajectory_samples: int = 10  # [-] instants of the remaining swing checked by FC (ours)
    foot_clearance_m: float = -0.005  # [m] FC tolerance: negative allows grazing by 5 mm (ours)
    uncertainty_margin_m: float = 0.02  # [m] erosion radius (thesis: foot radius = resolution = 0.02 m)

    def __post_init__(self) -> None:
        positive = ("resolution_m", "leg_radius_m")
        non_negative = (
            "roughness_radius_m", "max_mean_slope", "max_slope_std", "leg_clearance_m", "foot_exclusion_m",
            "reach_margin_m", "joint_limit_margin_rad", "uncertainty_margin_m",
        )  # fmt: skip
        counts = {"patch_cells": 3, "leg_points_per_segment": 1, "swing_samples": 1, "trajectory_samples": 2}
        for field in fields(self):
            value = getattr(self, field.name)
            if field.name in counts:
                if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < counts[field.name]:
                    raise FecConfigError(
                        f"FecSettings.{field.name} must be an integer >= {counts[field.name]}, got {value!r}"
                    )
                continue
            if not (_is_finite_number(value)):
                raise FecConfigError(f"FecSettings.{field.name} must be a finite number, got {value!r}")
            if field.name in positive and value <= 0.0:
                raise FecConfigError(f"FecSettings.{field.name} must be > 0, got {value!r}")
            if field.name in non_negative and value < 0.0:
                raise FecConfigError(f"FecSettings.{field.name} must be >= 0, got {value!r}")
        if self.patch_cells % 2 == 0:
            raise FecConfigError(
                f"FecSettings.patch_cells must be odd (the nominal foothold is the centre cell), got {self.patch_cells}"
            )


@dataclass(frozen=True)
class GaitTiming:
    """Gait parameters of the FEC tuple for one swinging leg.

    step_frequency_hz [Hz] gait cycles per second; duty_factor [-] stance fraction in (0, 1);
    swing_time_left_s [s] time remaining until touchdown, in [0, swing duration]; step_height_m [m]
    swing apex above the higher of lift-off and touchdown (``tal_control.motion.swing``). The step
    length is not a separate input: it is the hip's travel over one cycle, ``step_length_m(v_hip)``.
    """

    step_frequency_hz: float
    duty_factor: float
    swing_time_left_s: float
    step_height_m: float

    def __post_init__(self) -> None:
        for field in fields(self):
            value = getattr(self, field.name)
            if not (_is_finite_number(value)):
                raise PerceptionInputError(f"GaitTiming.{field.name} must be a finite number, got {value!r}")
        if self.step_frequency_hz <= 0.0:
            raise PerceptionInputError(f"GaitTiming.step_frequency_hz must be > 0, got {self.step_frequency_hz}")
        if not 0.0 < self.duty_factor < 1.0:
            raise PerceptionInputError(
                f"GaitTiming.duty_factor must be in (0, 1) for a swinging leg, got {self.duty_factor}"
            )
        if self.step_height_m < 0.0:
            raise PerceptionInputError(f"GaitTiming.step_height_m must be >= 0, got {self.step_height_m}")
        if not 0.0 <= self.swing_time_left_s <= self.swing_duration_s + 1e-9:
            raise PerceptionInputError(
                f"GaitTiming.swing_time_left_s must be in [0, {self.swing_duration_s:.4g}] s (the swing "
                f"duration), got {self.swing_time_left_s}"
            )

    @property
    def stance_duration_s(self) -> float:
        return self.duty_factor / self.step_frequency_hz

    @property
    def swing_duration_s(self) -> float:
        return (1.0 - self.duty_factor) / self.step_frequency_hz

    def step_length_m(self, hip_velocity_xy: ArrayLike) -> FloatArray:
        """(2,) [m] hip travel over one gait cycle at ``hip_velocity_xy`` [m/s] (patch frame)."""
        return np.asarray(hip_velocity_xy, dtype=float) / self.step_frequency_hz


@dataclass(frozen=True, eq=False)
class FecInput:
    """One FEC tuple for one leg (patch frame, see the module docstring).

    heights (rows, cols) [m] world z, NaN = unknown; hip_height_m [m] world z of the leg's HAA joint;
    twist (6,) base twist in the horizontal frame: linear [m/s] then angular [rad/s] (only vx, vy and
    the yaw rate move the hip; the base is taken level, as in the horizontal frame); gait the timing.
    Optional: hip_touchdown_xy (2,) [m] where the hip is at touchdown (default: the Raibert rule puts
    the nominal foothold half a stance ahead of it, so -v_hip T_stance / 2); liftoff_xyz (3,) [m] where
    the swing started (default: one step length behind the nominal, at the height of the patch there,
    or the median known height if that is off the patch or unknown); hip_rise_at_liftoff_m [m] how much
    higher the hip was at lift-off than at touchdown (``hip_height_m``): the hip moves linearly in time
    from one to the other during the swing; touchdown and the next lift-off are at ``hip_height_m``.
    0 (default, the thesis): the hip stays at ``hip_height_m`` for the whole swing. Positive when the
    trunk steps down with the leg (the VPA's terrain-following swing model, ``VpaSettings.swing_hip_model``).
    """

    leg: Leg
    heights: NDArray[np.float64]
    hip_height_m: float
    twist: FloatArray
    gait: GaitTiming
    hip_touchdown_xy: FloatArray | None = None
    liftoff_xyz: FloatArray | None = None
    hip_rise_at_liftoff_m: float = 0.0

    def __post_init__(self) -> None:
        try:
            leg = Leg(self.leg)
        except ValueError:
            raise PerceptionInputError(f"FecInput.leg must be a Leg (LF, RF, LH, RH), got {self.leg!r}") from None
        object.__setattr__(self, "leg", leg)
        heights = np.asarray(self.heights, dtype=float)
        if heights.ndim != 2 or heights.shape[0] < 3 or heights.shape[1] < 3:
            raise PerceptionInputError(
                f"FecInput.heights must be a (rows, cols) array with rows, cols >= 3, got shape {heights.shape}"
            )
        if np.isinf(heights).any():
            raise PerceptionInputError("FecInput.heights must be finite or NaN (unknown), got +-inf")
        object.__setattr__(self, "heights", heights)
        object.__setattr__(self, "twist", check_motion_inputs(self.hip_height_m, self.twist, self.gait))
        if self.hip_touchdown_xy is not None:
            object.__setattr__(self, "hip_touchdown_xy", _vector(self.hip_touchdown_xy, 2, "hip_touchdown_xy"))
        if self.liftoff_xyz is not None:
            object.__setattr__(self, "liftoff_xyz", _vector(self.liftoff_xyz, 3, "liftoff_xyz"))
        if not _is_finite_number(self.hip_rise_at_liftoff_m):
            raise PerceptionInputError(
                f"FecInput.hip_rise_at_liftoff_m must be a finite number [m], got {self.hip_rise_at_liftoff_m!r}"
            )
        object.__setattr__(self, "hip_rise_at_liftoff_m", float(self.hip_rise_at_liftoff_m))


def check_motion_inputs(hip_height_m: object, twist: object, gait: object) -> FloatArray:
    """``FecInput``'s checks of a tuple's hip height [m], twist (6,) [m/s, rad/s] and gait timing
    (PerceptionInputError naming the field); returns the twist as a float64 array. Also used where the
    tuple's arrays are checked without building a ``FecInput`` (the CNN selector's batched path)."""
    if not (isinstance(hip_height_m, (int, float, np.floating)) and math.isfinite(hip_height_m)):
        raise PerceptionInputError(f"FecInput.hip_height_m must be a finite number [m], got {hip_height_m!r}")
    twist_array = _vector(twist, 6, "twist")
    if not isinstance(gait, GaitTiming):
        raise PerceptionInputError(f"FecInput.gait must be a GaitTiming, got {type(gait).__name__}")
    return twist_array


def _is_finite_number(value: object) -> bool:
    """A finite int, float or numpy floating scalar (bool is not a number here)."""
    return isinstance(value, (int, float, np.floating)) and not isinstance(value, bool) and math.isfinite(value)


def _vector(value: object, size: int, name: str) -> FloatArray:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as error:
        raise PerceptionInputError(f"FecInput.{name}: cannot convert to a float array ({error})") from None
    if array.shape != (size,):
        raise PerceptionInputError(f"FecInput.{name} must have shape ({size},), got {array.shape}")
    if not all(map(math.isfinite, array.tolist())):  # ~1 us less than np.isfinite(array).all() for (3,) / (6,)
        bad = np.flatnonzero(~np.isfinite(array)).tolist()
        raise PerceptionInputError(f"FecInput.{name} has non-finite value(s) at index {bad}")
    return array
