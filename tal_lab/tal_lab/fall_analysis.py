"""Why a closed-loop run fell: the first control tick where the whole-body QP stopped delivering the trunk's
desired wrench, and which of its limits held it there.

On ViTAL's stairs at 0.4-0.5 m/s (stop 20) every fall began the same way, a few ticks before any visible roll:
the centroidal wrench of the QP's forces left the desired one by hundreds of newtons within one tick, with a
stance leg's joints at their torque limits and, on the swinging leg, a joint whose acceleration bound (the
joint-limit constraint) had closed. ``first_wrench_miss`` finds that tick in a log and names the limits, so that
every failed run of an experiment reports its first cause instead of only where the trunk hit the ground.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tal_control.wbc.swbc import joint_acceleration_bounds
from tal_core.errors import InputError
from tal_core.legs import LEGS, NUM_LEGS

FloatArray = NDArray[np.float64]
WRENCH_MISS_N = 300.0  # [N] force part of |W_wbc - W_des| that counts as a miss (HyQ weighs ~880 N)
SATURATION_FRACTION = 0.99  # [-] |tau| at this fraction of its limit counts as saturated
ACCELERATION_ROOM_RAD_S2 = 50.0  # [rad/s^2] a joint-limit acceleration bound this close to zero has closed
EPISODE_GAP_S = 0.5  # [s] misses closer than this belong to one episode


@dataclass(frozen=True)
class WrenchMiss:
    """The first miss: time [s], force and moment errors [N, N m], the planned stance legs, the joints at their
    torque limits and those whose acceleration bound had closed (by name), and the swing leg with the largest
    swing-task slack [m/s^2]."""

    t_s: float
    force_error_n: float
    moment_error_nm: float
    stance: tuple[str, ...]
    saturated: tuple[str, ...]
    at_joint_limit: tuple[str, ...]
    largest_slack_leg: str
    largest_slack: float

    def describe(self) -> str:
        return (
            f"t={self.t_s:.2f} s, stance {'+'.join(self.stance) or 'none'}: wrench off by {self.force_error_n:.0f} N "
            f"/ {self.moment_error_nm:.0f} N m; torque limits: {', '.join(self.saturated) or 'none'}; "
            f"joint-limit bounds closed: {', '.join(self.at_joint_limit) or 'none'}; largest swing slack "
            f"{self.largest_slack:.1f} m/s^2 ({self.largest_slack_leg})"
        )


def first_wrench_miss(
    t: FloatArray,
    wrench_des: FloatArray,
    wrench_wbc: FloatArray,
    stance: NDArray[np.bool_],
    tau: FloatArray,
    q: FloatArray,
    qd: FloatArray,
    slacks: FloatArray,
    torque_limits,
    joint_names: Sequence[str],
    position_limits: tuple[FloatArray, FloatArray],
    horizon_s: float,
    after_s: float = 1.5,
    threshold_n: float = WRENCH_MISS_N,
    last_episode: bool = False,
) -> WrenchMiss | None:
    """The first tick at or after ``after_s`` [s] where the force part of the QP's wrench error exceeds
    ``threshold_n`` [N], or None. With ``last_episode``, the first tick of the last episode of misses (misses
    less than ``EPISODE_GAP_S`` apart), and None unless it lasts to the end of the log: for a run that stopped
    at its fall, the onset of the fall rather than a transient the trot recovered from (a gait start).
    Arrays per tick: t (N,); wrenches (N, 6); stance (N, 4); tau, q, qd (N, 12) in the canonical joint order;
    slacks (N, 4, 3). ``torque_limits(q) -> (tau_min, tau_max)``; position limits (lower, upper) (12,) [rad];
    ``horizon_s`` [s] of the joint-limit constraint."""
    t = np.asarray(t, dtype=float)
    n = len(t)
    arrays = {
        "wrench_des": (wrench_des, (n, 6)),
        "wrench_wbc": (wrench_wbc, (n, 6)),
        "stance": (stance, (n, NUM_LEGS)),
        "tau": (tau, (n, 12)),
        "q": (q, (n, 12)),
        "qd": (qd, (n, 12)),
        "slacks": (slacks, (n, NUM_LEGS, 3)),
    }
    for name, (value, shape) in arrays.items():
        if np.shape(value) != shape:
            raise InputError(f"first_wrench_miss: {name} must have shape {shape}, got {np.shape(value)}")
    if len(joint_names) != 12:
        raise InputError(f"first_wrench_miss: need 12 joint names, got {len(joint_names)}")
    error = np.asarray(wrench_wbc, dtype=float) - np.asarray(wrench_des, dtype=float)
    force_error = np.linalg.norm(error[:, :3], axis=1)
    episodes = _miss_episode_ticks(t, force_error, after_s, threshold_n)
    if not episodes:
        return None
    k = int(episodes[0][0])
    if last_episode:
        if t[-1] - t[episodes[-1][-1]] > EPISODE_GAP_S:
            return None  # the misses ended before the log did
        k = int(episodes[-1][0])
    tau_min, tau_max = torque_limits(q[k])
    saturated = (tau[k] >= SATURATION_FRACTION * tau_max) | (tau[k] <= SATURATION_FRACTION * tau_min)
    qdd_min, qdd_max = joint_acceleration_bounds(q[k], qd[k], *position_limits, horizon_s)
    closed = np.minimum(qdd_max, -qdd_min) < ACCELERATION_ROOM_RAD_S2
    slack = np.abs(np.asarray(slacks[k], dtype=float)).max(axis=1)
    worst = int(np.argmax(slack))
    return WrenchMiss(
        t_s=float(t[k]),
        force_error_n=float(force_error[k]),
        moment_error_nm=float(np.linalg.norm(error[k, 3:])),
        stance=tuple(leg.name for leg in LEGS if stance[k][leg]),
        saturated=tuple(joint_names[j] for j in np.flatnonzero(saturated)),
        at_joint_limit=tuple(joint_names[j] for j in np.flatnonzero(closed)),
        largest_slack_leg=LEGS[worst].name,
        largest_slack=float(slack[worst]),
    )


@dataclass(frozen=True)
class MissEpisode:
    """One episode of wrench misses (misses less than ``EPISODE_GAP_S`` apart): first and last missing tick [s],
    the largest force error [N] in it, and whether the run went on past it (False: it lasted to the end of
    the log, i.e. a run that stopped at its fall)."""

    start_s: float
    end_s: float
    peak_force_error_n: float
    recovered: bool


def wrench_miss_episodes(
    t: FloatArray, wrench_des: FloatArray, wrench_wbc: FloatArray, after_s: float = 1.5,
    threshold_n: float = WRENCH_MISS_N,
) -> list[MissEpisode]:  # fmt: skip
    """Every episode in which the force part of the QP's wrench error exceeded ``threshold_n`` [N], at or
    after ``after_s`` [s]. On ViTAL's stairs (stop 28, 175 runs) the trot recovered from about five such
    episodes per run, in successful runs as often as before the falls: a miss is how a fall begins, not a
    sign that one will.
    Arrays per tick: t (N,) increasing [s]; wrenches (N, 6) [N, N m]."""
    t = np.asarray(t, dtype=float)
    n = len(t)
    for name, value in (("wrench_des", wrench_des), ("wrench_wbc", wrench_wbc)):
        if np.shape(value) != (n, 6):
            raise InputError(f"wrench_miss_episodes: {name} must have shape {(n, 6)}, got {np.shape(value)}")
    if n > 1 and not np.all(np.diff(t) > 0.0):
        raise InputError("wrench_miss_episodes: t must be strictly increasing")
    error = np.asarray(wrench_wbc, dtype=float) - np.asarray(wrench_des, dtype=float)
    force_error = np.linalg.norm(error[:, :3], axis=1)
    episodes = []
    for ticks in _miss_episode_ticks(t, force_error, after_s, threshold_n):
        end = float(t[ticks[-1]])
        episodes.append(MissEpisode(float(t[ticks[0]]), end, float(force_error[ticks].max()),
                                    recovered=float(t[-1]) - end > EPISODE_GAP_S))  # fmt: skip
    return episodes


def _miss_episode_ticks(t: FloatArray, force_error: FloatArray, after_s: float, threshold_n: float
                        ) -> list[NDArray[np.intp]]:  # fmt: skip
    """The tick indices of each episode of misses (force error [N] above ``threshold_n`` at or after ``after_s``
    [s]; misses less than ``EPISODE_GAP_S`` apart are one episode), in time order."""
    misses = np.flatnonzero((force_error > threshold_n) & (t >= after_s) & np.isfinite(force_error))
    if misses.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(t[misses]) > EPISODE_GAP_S)
    return np.split(misses, breaks + 1)


def first_wrench_miss_of_log(
    log, description, horizon_s: float, after_s: float = 1.5, last_episode: bool = False
) -> WrenchMiss | None:
    """``first_wrench_miss`` on a ``ClosedLoopLog`` of a robot ``description`` (RobotDescription)."""
    return first_wrench_miss(
        log.t,
        log.wrench_des,
        log.wrench_wbc,
        log.stance,
        log.tau_wbc,
        log.joint_position,
        log.joint_velocity,
        log.slacks,
        description.torque_limits,
        description.joint_names,
        (np.asarray(description.position_lower_rad), np.asarray(description.position_upper_rad)),
        horizon_s,
        after_s,
        last_episode=last_episode,
    )
