"""Vertical alignment of a world-frame heightmap with a drifting state estimate.

A proprioceptive estimator's height is unobservable and drifts (on soft ground by centimetres per minute).
The trunk reference puts the base ``nominal_height_m`` above the terrain under the stance feet; if that
terrain comes from a heightmap in the true world frame while the base height comes from the estimate,
every centimetre of estimator drift becomes a centimetre of leg extension. On the STANCE course the
estimate sank 0.13 m below the truth, the legs straightened and HyQ fell in the T3 strip.

On a robot the elevation map is built in the estimate's (odometry) frame and shares its drift. Here the
map comes from the simulator, so :class:`HeightmapAligner` estimates the offset between the two frames
from the loaded stance feet: offset = mean(foot_z - foot_radius - map_z(foot_xy)), low-passed. Feet that
sink into soft ground make the offset include the sinking, so the body keeps its nominal height above
the feet it stands on (what the controller does without a map).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from tal_core.errors import InputError

HeightFunction = Callable[[float, float], float]


class HeightmapAligner:
    """Low-passed z offset [m] from a world heightmap to the state estimate's frame.

    time_constant_s: first-order filter time constant [s] of the offset; max_rate_m_s: bound on its rate
    [m/s] (a touchdown on an unmapped step must not yank the body); load_threshold: a stance foot counts
    once its load factor (0..1) reaches this.
    """

    def __init__(self, time_constant_s: float = 1.0, max_rate_m_s: float = 0.05,
                 load_threshold: float = 0.99) -> None:
        for name, value in (("time_constant_s", time_constant_s), ("max_rate_m_s", max_rate_m_s)):
            if not (math.isfinite(value) and value > 0.0):
                raise InputError(f"{name} must be > 0, got {value!r}")
        if not 0.0 < load_threshold <= 1.0:
            raise InputError(f"load_threshold must be in (0, 1], got {load_threshold!r}")
        self.time_constant_s = float(time_constant_s)
        self.max_rate_m_s = float(max_rate_m_s)
        self.load_threshold = float(load_threshold)
        self.offset_m = 0.0
        self.updates = 0
        self._last_t: float | None = None

    def reset(self) -> None:
        """Forget the offset (e.g. after an estimator restart)."""
        self.offset_m = 0.0
        self.updates = 0
        self._last_t = None

    def residual(self, foot_positions: np.ndarray, loaded: np.ndarray, foot_radius_m: float,
                 height_fn: HeightFunction) -> float | None:
        """Mean (foot sole z - map z) [m] over the loaded feet with a finite map height, None if none."""
        values = []
        for (x, y, z), use in zip(np.asarray(foot_positions, dtype=float), np.asarray(loaded, dtype=bool),
                                  strict=True):
            if not use:
                continue
            ground = float(height_fn(float(x), float(y)))
            if math.isfinite(ground) and math.isfinite(z):
                values.append(z - foot_radius_m - ground)
        return float(np.mean(values)) if values else None

    def update(self, t_s: float, foot_positions: np.ndarray, load_factor: np.ndarray, foot_radius_m: float,
               height_fn: HeightFunction) -> float:
        """Advance the offset to time ``t_s`` [s] with the feet (N, 3) [m, estimate frame] and their load
        factors (N,); returns the offset [m]. Time going backwards resets the filter."""
        if self._last_t is not None and t_s < self._last_t:
            self.reset()
        residual = self.residual(foot_positions, np.asarray(load_factor) >= self.load_threshold,
                                 foot_radius_m, height_fn)
        if residual is None:
            self._last_t = t_s
            return self.offset_m
        if self._last_t is None:
            self.offset_m = residual
        else:
            dt = t_s - self._last_t
            step = (residual - self.offset_m) * (1.0 - math.exp(-dt / self.time_constant_s))
            bound = self.max_rate_m_s * dt
            self.offset_m += float(np.clip(step, -bound, bound))
        self._last_t = t_s
        self.updates += 1
        return self.offset_m

    def aligned(self, height_fn: HeightFunction) -> HeightFunction:
        """``height_fn`` shifted into the estimate's frame (uses the offset current at call time)."""
        return lambda x, y: float(height_fn(x, y)) + self.offset_m
