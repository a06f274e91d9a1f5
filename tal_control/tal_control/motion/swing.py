"""Swing foot trajectories: quintic polynomials in the world frame, re-plannable mid-swing.

Horizontal (x, y): one quintic from lift-off to touchdown with zero velocity and acceleration at both
ends. Vertical (z): two quintic halves, lift-off -> apex at half the swing -> touchdown, each with zero
velocity and acceleration at its ends; the apex is ``max(liftoff_z, touchdown_z) + apex_height_m``.
``retarget`` moves the touchdown point mid-swing by re-planning the rest of the swing from the current
position, velocity and acceleration (so none of them jumps).

Positions [m], velocities [m/s], accelerations [m/s^2], world frame; time [s] since lift-off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tal_control.errors import MotionConfigError
from tal_core.errors import InputError

# Re-planning the rise to the apex needs some time; closer to mid-swing than this fraction of the swing,
# the rest of the swing goes straight to the new touchdown point.
_MIN_RISE_FRACTION = 0.1


@dataclass(frozen=True, eq=False)
class SwingSample:
    """Desired foot state at one time: position [m], velocity [m/s], acceleration [m/s^2], world frame."""

    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray


class _Quintic:
    """p(t) on [t0, t1] (vector valued) matching position, velocity and acceleration at both ends."""

    def __init__(self, t0: float, t1: float, start: tuple[np.ndarray, ...], end: tuple[np.ndarray, ...]):
        h = t1 - t0
        p0, v0, a0 = (np.asarray(x, dtype=float) for x in start)
        p1, v1, a1 = (np.asarray(x, dtype=float) for x in end)
        delta = p1 - p0
        c3 = (20.0 * delta - (8.0 * v1 + 12.0 * v0) * h - (3.0 * a0 - a1) * h**2) / (2.0 * h**3)
        c4 = (-30.0 * delta + (14.0 * v1 + 16.0 * v0) * h + (3.0 * a0 - 2.0 * a1) * h**2) / (2.0 * h**4)
        c5 = (12.0 * delta - 6.0 * (v1 + v0) * h + (a1 - a0) * h**2) / (2.0 * h**5)
        self.t0, self.t1 = t0, t1
        self.coefficients = np.array([p0, v0, 0.5 * a0, c3, c4, c5])  # (6, dim)

    def evaluate(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        tau = min(max(t, self.t0), self.t1) - self.t0
        c = self.coefficients
        p = c[0] + tau * (c[1] + tau * (c[2] + tau * (c[3] + tau * (c[4] + tau * c[5]))))
        v = c[1] + tau * (2.0 * c[2] + tau * (3.0 * c[3] + tau * (4.0 * c[4] + tau * 5.0 * c[5])))
        a = 2.0 * c[2] + tau * (6.0 * c[3] + tau * (12.0 * c[4] + tau * 20.0 * c[5]))
        return p, v, a


class _Piecewise:
    """Consecutive quintic pieces; re-planning truncates the last piece at the re-plan time."""

    def __init__(self, pieces: list[_Quintic]) -> None:
        self.pieces = pieces

    def evaluate(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        for piece in reversed(self.pieces):
            if t >= piece.t0:
                return piece.evaluate(t)
        return self.pieces[0].evaluate(t)

    def truncate(self, t: float) -> None:
        """Drop everything after ``t`` (pieces starting later are removed, the current one ends at t)."""
        self.pieces = [piece for piece in self.pieces if piece.t0 < t] or self.pieces[:1]
        self.pieces[-1].t1 = min(self.pieces[-1].t1, t)


def _rest(value: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position ``value`` with zero velocity and acceleration."""
    p = np.atleast_1d(np.asarray(value, dtype=float))
    return p, np.zeros_like(p), np.zeros_like(p)


def _checked_point(value: object, name: str) -> np.ndarray:
    try:
        point = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError) as error:
        raise InputError(f"swing trajectory: {name} is not numeric ({error})") from None
    if point.shape != (3,) or not np.all(np.isfinite(point)):
        raise InputError(f"swing trajectory: {name} must be 3 finite values [m], got {value!r}")
    return point


_MAX_CLEAR_FRACTION = 0.4  # horizontal motion starts at the latest at 40 % of the swing


class SwingTrajectory:
    """Desired swing foot motion from ``liftoff_xyz`` to ``touchdown_xyz`` [m] (world frame) in
    ``duration_s`` [s], rising to ``apex_height_m`` [m] above the higher of the two end points."""

    def __init__(self, liftoff_xyz: object, touchdown_xyz: object, duration_s: float,
                 apex_height_m: float, clear_z: float | None = None) -> None:
        """``clear_z`` [m]: world z the foot must reach before it moves horizontally. On soft ground the
        foot lifts off from below the undeformed surface; dragging it sideways through the ground would
        load it with the terrain's forces in swing. None: horizontal motion starts at lift-off."""
        if not (math.isfinite(duration_s) and duration_s > 0.0):
            raise MotionConfigError(f"swing trajectory: duration_s must be > 0, got {duration_s!r}")
        if not (math.isfinite(apex_height_m) and apex_height_m >= 0.0):
            raise MotionConfigError(f"swing trajectory: apex_height_m must be >= 0, got {apex_height_m!r}")
        self._liftoff = _checked_point(liftoff_xyz, "liftoff_xyz")
        self._touchdown = _checked_point(touchdown_xyz, "touchdown_xyz")
        self._duration = float(duration_s)
        self._apex_height = float(apex_height_m)
        self._retarget_count = 0
        half, end = 0.5 * self._duration, self._duration
        apex = self.apex_z
        self._z = _Piecewise([_Quintic(0.0, half, _rest(self._liftoff[2]), _rest(apex)),
                              _Quintic(half, end, _rest(apex), _rest(self._touchdown[2]))])
        start = self._time_to_clear(clear_z, half)
        xy_pieces = [] if start <= 0.0 else [_Quintic(0.0, start, _rest(self._liftoff[:2]), _rest(self._liftoff[:2]))]
        xy_pieces.append(_Quintic(start, end, _rest(self._liftoff[:2]), _rest(self._touchdown[:2])))
        self._xy = _Piecewise(xy_pieces)

    def _time_to_clear(self, clear_z: float | None, half: float) -> float:
        """First time [s] the rising z profile reaches ``clear_z`` (bisection), capped at 40 % of the swing."""
        if clear_z is None or not math.isfinite(clear_z) or self._liftoff[2] >= clear_z:
            return 0.0
        low, high = 0.0, half
        if float(self._z.evaluate(high)[0][0]) < clear_z:
            return _MAX_CLEAR_FRACTION * self._duration
        for _ in range(30):
            mid = 0.5 * (low + high)
            if float(self._z.evaluate(mid)[0][0]) < clear_z:
                low = mid
            else:
                high = mid
        return min(high, _MAX_CLEAR_FRACTION * self._duration)

    @property
    def duration_s(self) -> float:
        return self._duration

    @property
    def liftoff_position(self) -> np.ndarray:
        """(3,) [m] world frame, start of the swing."""
        return self._liftoff.copy()

    @property
    def touchdown_position(self) -> np.ndarray:
        """(3,) [m] world frame, current end of the swing (after any retarget)."""
        return self._touchdown.copy()

    @property
    def apex_z(self) -> float:
        """[m] world z of the apex planned for the current touchdown point."""
        return float(max(self._liftoff[2], self._touchdown[2]) + self._apex_height)

    @property
    def retarget_count(self) -> int:
        return self._retarget_count

    def sample(self, t_s: float) -> SwingSample:
        """Desired state at ``t_s`` [s] since lift-off; clamped to [0, duration] (at rest outside)."""
        if not math.isfinite(t_s):
            raise InputError(f"swing trajectory: time must be finite, got {t_s!r}")
        t = min(max(float(t_s), 0.0), self._duration)
        p_xy, v_xy, a_xy = self._xy.evaluate(t)
        p_z, v_z, a_z = self._z.evaluate(t)
        return SwingSample(np.concatenate([p_xy, p_z]), np.concatenate([v_xy, v_z]),
                           np.concatenate([a_xy, a_z]))

    def retarget(self, new_touchdown_xyz: object, t_s: float) -> None:
        """Re-plan the swing from its state at ``t_s`` [s] (0 <= t_s < duration) to end at
        ``new_touchdown_xyz`` [m] at the original touchdown time, at rest. The apex becomes
        ``max(liftoff_z, new touchdown z) + apex_height_m`` if the foot has not passed mid-swing."""
        target = _checked_point(new_touchdown_xyz, "new_touchdown_xyz")
        if not (math.isfinite(t_s) and 0.0 <= t_s < self._duration):
            raise InputError(f"swing trajectory: retarget time must be in [0, {self._duration:.4g}) s, "
                             f"got {t_s!r}")
        t = float(t_s)
        now = self.sample(t)
        end, half = self._duration, 0.5 * self._duration
        self._touchdown = target
        self._xy.truncate(t)
        self._xy.pieces.append(_Quintic(t, end, (now.position[:2], now.velocity[:2], now.acceleration[:2]),
                                        _rest(target[:2])))
        z_now = (now.position[2:], now.velocity[2:], now.acceleration[2:])
        self._z.truncate(t)
        if half - t >= _MIN_RISE_FRACTION * self._duration:
            apex = self.apex_z
            self._z.pieces.append(_Quintic(t, half, z_now, _rest(apex)))
            self._z.pieces.append(_Quintic(half, end, _rest(apex), _rest(target[2])))
        else:
            self._z.pieces.append(_Quintic(t, end, z_now, _rest(target[2])))
        self._retarget_count += 1
