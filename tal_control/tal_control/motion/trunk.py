"""Trunk (CoM and orientation) references: integrated velocity commands, terrain-following height and the
crawl's CoM shift over the support triangles.

* x, y, yaw: the commanded twist (vx, vy [m/s] in the horizontal frame, yaw rate [rad/s]) with rate-limited
  acceleration, integrated into a "neutral" CoM path (trapezoidal rule, so a velocity ramp integrates
  exactly); the path is kept within ``max_tracking_error_m`` of the measured CoM.
* height: the base origin ``nominal_height_m`` above the mean terrain height under the stance feet,
  through a critically damped, rate-limited filter. Roll, pitch: 0 (or the terrain pitch from the
  footholds); ``override`` replaces height, roll and pitch (VPA's body pose reference).
* CoM shift (statically stable gaits, i.e. the crawl): before each lift-off the CoM moves towards the
  centroid of the coming support triangle (the feet except the one about to swing). Sideways (horizontal
  frame y) it follows a periodic cubic spline over the gait phase through the centroids' lateral
  offsets, one waypoint at mid-swing of each leg (C2, a sway of about the centroid offset);
  fore-aft it centres the CoM over the support feet (low-pass over a quarter cycle against wobble).
  Gains ``com_shift_lateral_gain`` and ``com_shift_longitudinal_gain`` scale the two; the shift fades
  in over the first cycle of the gait (a preparation cycle without lift-offs) and out over one cycle.

World frame, z up; the horizontal frame is the base yaw only. Positions [m], velocities [m/s],
accelerations [m/s^2]; angles [rad], rates [rad/s], [rad/s^2]. Orientation: world_R_base = Rz Ry Rx.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from tal_control.errors import MotionConfigError
from tal_control.motion.gait import GaitParameters, GaitPhase
from tal_core.errors import InputError


@dataclass(frozen=True)
class TrunkParameters:
    """Trunk reference settings (units in the names). ``nominal_height_m``: base origin above the mean
    stance terrain; ``com_offset_base_m``: CoM in the base frame at the nominal pose."""

    nominal_height_m: float
    com_offset_base_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_speed_m_s: float = 1.0
    max_yaw_rate_rad_s: float = 1.0
    max_acceleration_m_s2: float = 0.5
    max_yaw_acceleration_rad_s2: float = 1.0
    height_bandwidth_rad_s: float = 4.0
    max_height_rate_m_s: float = 0.1
    attitude_bandwidth_rad_s: float = 4.0
    max_attitude_rate_rad_s: float = 0.3
    max_tracking_error_m: float = 0.15
    align_pitch_to_terrain: bool = False
    com_shift_lateral_gain: float = 1.0
    com_shift_longitudinal_gain: float = 1.0

    def __post_init__(self) -> None:
        offset = tuple(float(v) for v in self.com_offset_base_m)
        if len(offset) != 3 or not all(math.isfinite(v) for v in offset):
            raise MotionConfigError(f"trunk: com_offset_base_m must be 3 finite values, got {offset!r}")
        object.__setattr__(self, "com_offset_base_m", offset)
        for key, value in vars(self).items():
            if key in ("com_offset_base_m", "align_pitch_to_terrain"):
                continue
            lower_ok = value >= 0.0 if key.startswith("com_shift") else value > 0.0
            if not (math.isfinite(value) and lower_ok):
                raise MotionConfigError(f"trunk: {key} must be finite and "
                                        f"{'>= 0' if key.startswith('com_shift') else '> 0'}, got {value!r}")


@dataclass(frozen=True, eq=False)
class FeetMotion:
    """Support feet (4, 3) each [m], [m/s], [m/s^2], world frame: stance feet where they touched down
    (at rest), swing feet along their desired trajectories."""

    positions: np.ndarray
    velocities: np.ndarray
    accelerations: np.ndarray


@dataclass(frozen=True, eq=False)
class TrunkTarget:
    """Desired trunk state, world frame. ``com_shift`` [m] is the crawl shift included in com_position;
    ``command_velocity_world`` [m/s] and ``command_yaw_rate`` [rad/s] the rate-limited commanded twist."""

    com_position: np.ndarray
    com_velocity: np.ndarray
    com_acceleration: np.ndarray
    base_position: np.ndarray
    world_R_base: np.ndarray  # noqa: N815 (frame notation, as in the WBC references)
    rpy: np.ndarray
    angular_velocity: np.ndarray
    angular_acceleration: np.ndarray
    command_velocity_world: np.ndarray
    command_yaw_rate: float
    com_shift: np.ndarray
    stance_ground_height_m: float


@dataclass(frozen=True)
class TrunkOscillation:
    """Sinusoids added to the trunk's height [m] and roll [rad] references (thesis' aggressive trunk
    manoeuvres: 0.05 m at 1.8 Hz, 0.5 rad at 1.5 Hz), with their exact rates and accelerations, starting
    at ``start_time_s`` [s] from zero phase (so the reference is continuous). They bypass the reference's
    smoothing filters: the point is to excite the contacts."""

    height_amplitude_m: float = 0.0
    height_frequency_hz: float = 0.0
    roll_amplitude_rad: float = 0.0
    roll_frequency_hz: float = 0.0
    start_time_s: float = 0.0

    def __post_init__(self) -> None:
        for key, value in vars(self).items():
            if not (math.isfinite(value) and value >= 0.0):
                raise InputError(f"trunk oscillation: {key} must be finite and >= 0, got {value!r}")

    def offsets(self, t_s: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """((dz, dz/dt, d2z/dt2) [m, m/s, m/s^2], (roll, rate, acceleration) [rad, rad/s, rad/s^2]) at t_s."""
        tau = max(float(t_s) - self.start_time_s, 0.0)

        def sine(amplitude: float, frequency: float) -> tuple[float, float, float]:
            w = 2.0 * math.pi * frequency
            return (amplitude * math.sin(w * tau), amplitude * w * math.cos(w * tau),
                    -amplitude * w * w * math.sin(w * tau))

        if t_s < self.start_time_s:
            return (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
        return sine(self.height_amplitude_m, self.height_frequency_hz), sine(self.roll_amplitude_rad,
                                                                               self.roll_frequency_hz)


def rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """world_R_base = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _euler_rates_to_world(rpy: np.ndarray, rates: np.ndarray, accels: np.ndarray) -> tuple[np.ndarray, ...]:
    """Angular velocity and acceleration (world) from ZYX Euler angles, rates and second derivatives."""
    _, p, y = rpy
    dr, dp, dy = rates
    cp, sp, cy, sy = math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    E = np.array([[cy * cp, -sy, 0.0], [sy * cp, cy, 0.0], [-sp, 0.0, 1.0]])
    dE = np.array([[-sy * cp * dy - cy * sp * dp, -cy * dy, 0.0],
                   [cy * cp * dy - sy * sp * dp, -sy * dy, 0.0],
                   [-cp * dp, 0.0, 0.0]])
    return E @ rates, E @ accels + dE @ np.array([dr, dp, dy])


def _xyz(xy: np.ndarray, z: float) -> np.ndarray:
    return np.array([xy[0], xy[1], z])


def _smoothstep(s: float) -> tuple[float, float, float]:
    """Quintic 0 -> 1 on s in [0, 1] and its first two derivatives with respect to s."""
    if s <= 0.0 or s >= 1.0:
        return (0.0 if s <= 0.0 else 1.0), 0.0, 0.0
    return s**3 * (10 - 15 * s + 6 * s**2), 30 * s**2 * (1 - s) ** 2, 60 * s * (1 - s) * (1 - 2 * s)


class _Follower:
    """Critically damped second-order filter of a scalar with a rate limit: value, rate, acceleration."""

    def __init__(self, value: float, omega: float, max_rate: float) -> None:
        self.value, self.rate, self.accel = float(value), 0.0, 0.0
        self._omega, self._max_rate = omega, max_rate

    def step(self, target: float, dt: float) -> None:
        if dt <= 0.0:
            return
        accel = self._omega**2 * (target - self.value) - 2.0 * self._omega * self.rate
        rate = min(self._max_rate, max(-self._max_rate, self.rate + accel * dt))
        self.accel = (rate - self.rate) / dt
        self.value += 0.5 * (self.rate + rate) * dt
        self.rate = rate


class _PeriodicBasis:
    """Periodic cubic spline basis over the gait phase with one knot per leg (at the leg's mid-swing):
    the curve through per-leg values v_j is sum_j b_j(phase) v_j, and sum_j b_j = 1."""

    def __init__(self, gait: GaitParameters) -> None:
        mids = (np.asarray(gait.phase_offsets) + 0.5 * (1.0 - gait.duty_factor)) % 1.0
        order = np.argsort(mids)
        knots = np.append(mids[order], mids[order][0] + 1.0)
        values = np.eye(len(mids))[order]
        spline = CubicSpline(knots, np.vstack([values, values[:1]]), bc_type="periodic")
        self._knots, self._c = knots, np.asarray(spline.c)  # c: (4 powers, intervals, legs)

    def __call__(self, cycle_phase: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Basis values (4,) and their first and second derivatives with respect to the phase."""
        x = (cycle_phase - self._knots[0]) % 1.0 + self._knots[0]
        i = min(int(np.searchsorted(self._knots, x, side="right")) - 1, self._c.shape[1] - 1)
        h = x - self._knots[i]
        c3, c2, c1, c0 = self._c[:, i]
        value = ((c3 * h + c2) * h + c1) * h + c0
        return value, (3.0 * c3 * h + 2.0 * c2) * h + c1, 6.0 * c3 * h + 2.0 * c2


class _ComShift:
    """The crawl's CoM shift (see the module docstring): an xy offset with its two derivatives.

    Lateral (horizontal frame y): the spline through the support-triangle centroids. Longitudinal (x):
    the offset of the feet centre from the neutral path, low-pass filtered (time constant a quarter
    cycle): centres the CoM over the feet, e.g. when the robot's CoM is not under its hips.
    """

    _OTHERS = (np.ones((4, 4)) - np.eye(4)) / 3.0  # row j: centroid of the feet except leg j

    def __init__(self) -> None:
        self._basis: _PeriodicBasis | None = None
        self._frequency, self._origin = 1.0, 0.0
        self._gait_start: float | None = None
        self._w_from, self._w_to, self._ramp_start, self._ramp_s = 0.0, 0.0, 0.0, 1.0
        self._long: float | None = None  # filtered longitudinal offset [m]

    def _weight(self, t: float) -> tuple[float, float, float]:
        s, ds, dds = _smoothstep((t - self._ramp_start) / self._ramp_s)
        span = self._w_to - self._w_from
        return self._w_from + span * s, span * ds / self._ramp_s, span * dds / self._ramp_s**2

    def _on_new_gait(self, t: float, gait: GaitParameters, start: float) -> None:
        self._w_from = self._weight(t)[0] if self._gait_start is not None else 0.0
        self._w_to = 1.0 if gait.is_statically_stable else 0.0
        self._ramp_start, self._ramp_s, self._gait_start = start, gait.cycle_duration_s, start
        if gait.is_statically_stable:  # otherwise keep the last crawl's clock while the shift fades out
            self._basis = _PeriodicBasis(gait)
            self._frequency, self._origin = gait.step_frequency_hz, start
            if self._w_from == 0.0:
                self._long = None

    def update(self, t: float, dt: float, phase: GaitPhase, feet: FeetMotion, neutral: tuple[np.ndarray, ...],
               yaw: float, gains: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Shift (2,) [m] and its first two time derivatives, world frame."""
        if self._gait_start is None or phase.gait_start_time_s != self._gait_start:
            self._on_new_gait(t, phase.gait, phase.gait_start_time_s)
        w, dw, ddw = self._weight(t)
        zero = np.zeros(2)
        if self._basis is None or (w == 0.0 and dw == 0.0):
            self._long = None
            return zero, zero, zero
        f = self._frequency
        b, db, ddb = self._basis((t - self._origin) * f)
        db, ddb = db * f, ddb * f * f
        p, v, a = feet.positions[:, :2], feet.velocities[:, :2], feet.accelerations[:, :2]
        c, dc, ddc = self._OTHERS @ p, self._OTHERS @ v, self._OTHERS @ a
        n, dn, ddn = neutral
        e_x, e_y = np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])
        lat = e_y @ (b @ c - n)
        d_lat = e_y @ (db @ c + b @ dc - dn)
        dd_lat = e_y @ (ddb @ c + 2.0 * db @ dc + b @ ddc - ddn)
        u, du = e_x @ (p.mean(axis=0) - n), e_x @ (v.mean(axis=0) - dn)
        tau = 0.25 / f  # [s] a quarter cycle
        if self._long is None:
            self._long = u
        self._long += dt * (u - self._long) / tau
        d_long = (u - self._long) / tau
        dd_long = (du - d_long) / tau
        g_lat, g_long = gains
        s = g_lat * lat * e_y + g_long * self._long * e_x
        ds = g_lat * d_lat * e_y + g_long * d_long * e_x
        dds = g_lat * dd_lat * e_y + g_long * dd_long * e_x
        return w * s, dw * s + w * ds, ddw * s + 2.0 * dw * ds + w * dds


class TrunkReference:
    """Produces a ``TrunkTarget`` per control tick; starts from the measured CoM [m] and roll, pitch,
    yaw [rad] so the first target equals the current state."""

    def __init__(self, params: TrunkParameters, initial_com_xyz: Sequence[float],
                 initial_rpy: Sequence[float]) -> None:
        com = np.asarray(initial_com_xyz, dtype=float).reshape(-1)
        rpy = np.asarray(initial_rpy, dtype=float).reshape(-1)
        if com.shape != (3,) or rpy.shape != (3,) or not np.all(np.isfinite(np.concatenate([com, rpy]))):
            raise InputError(f"trunk: initial CoM and rpy must be 3 finite values each, got {com}, {rpy}")
        self.params = params
        self._offset = np.asarray(params.com_offset_base_m)
        self._xy, self._v_xy, self._a_xy = com[:2].copy(), np.zeros(2), np.zeros(2)
        self._yaw, self._yaw_rate, self._yaw_accel = float(rpy[2]), 0.0, 0.0
        base_z = com[2] - float((rotation_rpy(*rpy) @ self._offset)[2])
        self._height = _Follower(base_z, params.height_bandwidth_rad_s, params.max_height_rate_m_s)
        omega, max_rate = params.attitude_bandwidth_rad_s, params.max_attitude_rate_rad_s
        self._roll, self._pitch = (_Follower(angle, omega, max_rate) for angle in rpy[:2])
        self._override: tuple[float | None, float | None, float | None] = (None, None, None)
        self.oscillation: TrunkOscillation | None = None
        self._shift = _ComShift()
        self._last_shift = np.zeros(2)
        self._t_prev: float | None = None

    def override(self, base_height_m: float | None = None, roll: float | None = None,
                 pitch: float | None = None) -> None:
        """Replace the height (world z of the base origin [m]), roll and/or pitch [rad] targets (None keeps
        the default for that one) until ``clear_override``; the filters move smoothly to the new values."""
        for name, value in (("base_height_m", base_height_m), ("roll", roll), ("pitch", pitch)):
            if value is not None and not math.isfinite(value):
                raise InputError(f"trunk override: {name} must be finite, got {value!r}")
        self._override = (base_height_m, roll, pitch)

    def clear_override(self) -> None:
        self._override = (None, None, None)

    def update(self, t_s: float, cmd_vel: Sequence[float], phase: GaitPhase, feet: FeetMotion,
               footholds_ground: np.ndarray, measured_com_xyz: Sequence[float] | None = None) -> TrunkTarget:
        """Advance to ``t_s`` [s]. cmd_vel: (vx, vy [m/s] horizontal frame, yaw rate [rad/s]); taken as zero
        while the gait stands or prepares (no leg steps, so the trunk must not walk away from the feet).
        footholds_ground (4, 3) [m]: terrain points under the stance feet and at the swing targets."""
        cmd = np.asarray(cmd_vel, dtype=float).reshape(-1)
        if cmd.shape != (3,) or not np.all(np.isfinite(cmd)):
            raise InputError(f"trunk: cmd_vel must be 3 finite values (vx, vy, yaw rate), got {cmd_vel!r}")
        if self._t_prev is not None and t_s <= self._t_prev:
            raise InputError(f"trunk: time {t_s:.6f} s is not after the previous {self._t_prev:.6f} s")
        dt = 0.0 if self._t_prev is None else float(t_s) - self._t_prev
        self._t_prev = float(t_s)
        p = self.params
        if phase.gait.is_standing or phase.preparing:
            cmd = np.zeros(3)  # the feet do not step: do not walk the trunk away from them
        self._integrate_twist(cmd, dt)
        if measured_com_xyz is not None:
            error = self._xy + self._last_shift - np.asarray(measured_com_xyz, dtype=float)[:2]
            norm = float(np.linalg.norm(error))
            if norm > p.max_tracking_error_m:
                self._xy -= error * (1.0 - p.max_tracking_error_m / norm)

        stance = phase.stance
        ground = float(np.mean(footholds_ground[stance, 2])) if stance.any() else float(
            np.mean(footholds_ground[:, 2]))
        height, roll, pitch = self._override
        self._height.step(ground + p.nominal_height_m if height is None else height, dt)
        self._roll.step(0.0 if roll is None else roll, dt)
        self._pitch.step(self._terrain_pitch(footholds_ground) if pitch is None else pitch, dt)

        (dz, dz_rate, dz_accel), (d_roll, d_roll_rate, d_roll_accel) = (
            self.oscillation.offsets(t_s) if self.oscillation is not None else ((0.0,) * 3, (0.0,) * 3))
        rpy = np.array([self._roll.value + d_roll, self._pitch.value, self._yaw])
        world_R_base = rotation_rpy(*rpy)
        rates = np.array([self._roll.rate + d_roll_rate, self._pitch.rate, self._yaw_rate])
        accels = np.array([self._roll.accel + d_roll_accel, self._pitch.accel, self._yaw_accel])
        omega, domega = _euler_rates_to_world(rpy, rates, accels)
        shift, d_shift, dd_shift = self._shift.update(
            float(t_s), dt, phase, feet, (self._xy, self._v_xy, self._a_xy), self._yaw,
            (p.com_shift_lateral_gain, p.com_shift_longitudinal_gain))
        self._last_shift = shift
        offset_world = world_R_base @ self._offset
        base_z = self._height.value + dz
        com = _xyz(self._xy + shift, base_z + offset_world[2])
        return TrunkTarget(
            com_position=com,
            com_velocity=_xyz(self._v_xy + d_shift, self._height.rate + dz_rate),
            com_acceleration=_xyz(self._a_xy + dd_shift, self._height.accel + dz_accel),
            base_position=com - offset_world,
            world_R_base=world_R_base,
            rpy=rpy,
            angular_velocity=omega,
            angular_acceleration=domega,
            command_velocity_world=_xyz(self._v_xy, 0.0),
            command_yaw_rate=self._yaw_rate,
            com_shift=_xyz(shift, 0.0),
            stance_ground_height_m=ground,
        )

    def _integrate_twist(self, cmd: np.ndarray, dt: float) -> None:
        """Rate-limit the commanded twist and integrate it (trapezoidal) into x, y, yaw."""
        p = self.params
        if dt <= 0.0:
            return
        yaw_rate_cmd = min(p.max_yaw_rate_rad_s, max(-p.max_yaw_rate_rad_s, float(cmd[2])))
        d_rate = yaw_rate_cmd - self._yaw_rate
        limit = p.max_yaw_acceleration_rad_s2 * dt
        new_rate = self._yaw_rate + min(limit, max(-limit, d_rate))
        self._yaw_accel = (new_rate - self._yaw_rate) / dt
        self._yaw += 0.5 * (self._yaw_rate + new_rate) * dt
        self._yaw_rate = new_rate

        v_h = cmd[:2]
        speed = float(np.linalg.norm(v_h))
        if speed > p.max_speed_m_s:
            v_h = v_h * (p.max_speed_m_s / speed)
        c, s = math.cos(self._yaw), math.sin(self._yaw)
        target = np.array([c * v_h[0] - s * v_h[1], s * v_h[0] + c * v_h[1]])
        dv = target - self._v_xy
        norm, limit = float(np.linalg.norm(dv)), p.max_acceleration_m_s2 * dt
        if norm > limit:
            dv *= limit / norm
        self._a_xy = dv / dt
        self._xy = self._xy + 0.5 * (2.0 * self._v_xy + dv) * dt
        self._v_xy = self._v_xy + dv

    def _terrain_pitch(self, footholds_ground: np.ndarray) -> float:
        """Pitch [rad] aligning the trunk with the line from the hind to the front footholds (nose up,
        i.e. negative pitch, when the front feet are higher); 0 unless ``align_pitch_to_terrain``."""
        if not self.params.align_pitch_to_terrain:
            return 0.0
        front, hind = footholds_ground[:2].mean(axis=0), footholds_ground[2:].mean(axis=0)
        run = math.cos(self._yaw) * (front[0] - hind[0]) + math.sin(self._yaw) * (front[1] - hind[1])
        if run <= 1e-6:
            return 0.0
        return -math.atan2(front[2] - hind[2], run)
