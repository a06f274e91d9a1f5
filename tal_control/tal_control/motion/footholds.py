"""Raibert-style nominal footholds and terrain look-ups for them.

The nominal foothold of a swinging leg is where its hip will be at touchdown (the hip moved by the
commanded velocity over the remaining swing time and rotated by the commanded yaw rate about the trunk),
plus half the distance the hip travels during the next stance, ``v_hip_cmd * T_stance / 2`` (so the
foot is under the hip at mid-stance), plus the velocity feedback ``k (v - v_cmd)`` (Raibert 1986; the
reactive controller framework of Barasuol et al. 2013 uses the same rule). Its height comes from any
terrain height callback ``height(x, y)`` [m] (``Course.height``, ``HeightMapGrid.height_at`` or a
lambda). All positions and velocities are in the world frame [m, m/s]; the yaw rate is [rad/s].
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from tal_core.errors import InputError

HeightFunction = Callable[[float, float], "float | np.ndarray"]
NormalFunction = Callable[[float, float], "Sequence[float] | np.ndarray"]
DEFAULT_K_FEEDBACK = 0.05  # [s] Raibert velocity feedback gain
_UP = np.array([0.0, 0.0, 1.0])


def _vector2(value: object, name: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError) as error:
        raise InputError(f"foothold: {name} is not numeric ({error})") from None
    if array.shape != (2,) or not (math.isfinite(array[0]) and math.isfinite(array[1])):
        raise InputError(f"foothold: {name} must be 2 finite values (x, y), got {value!r}")
    return array


def _non_negative(value: float, name: str) -> float:
    if not (math.isfinite(value) and value >= 0.0):
        raise InputError(f"foothold: {name} must be a finite number >= 0, got {value!r}")
    return float(value)


def terrain_height(height_fn: HeightFunction | None, x: float, y: float, default_z: float) -> float:
    """Terrain height [m] at world (x, y) [m] from ``height_fn``; ``default_z`` if there is no function
    or it returns NaN (e.g. outside a heightmap). Accepts scalar or size-1 array results."""
    if height_fn is None:
        return float(default_z)
    try:
        z = float(np.asarray(height_fn(float(x), float(y)), dtype=float).reshape(-1)[0])
    except (TypeError, ValueError, IndexError) as error:
        raise InputError(f"terrain height callback failed at ({x:.3f}, {y:.3f}): {error}") from None
    return z if math.isfinite(z) else float(default_z)


def terrain_normal(normal_fn: NormalFunction | None, x: float, y: float) -> np.ndarray:
    """Unit terrain normal (3,) at world (x, y) [m] from ``normal_fn``; vertical if there is none or it
    returns a non-finite or zero vector."""
    if normal_fn is None:
        return _UP.copy()
    normal = np.asarray(normal_fn(float(x), float(y)), dtype=float).reshape(-1)
    norm = float(np.linalg.norm(normal)) if normal.shape == (3,) else 0.0
    if not (math.isfinite(norm) and norm > 1e-9):
        return _UP.copy()
    return normal / norm


def terrain_normals(normal_fn: NormalFunction | None, xy: np.ndarray) -> np.ndarray:
    """Unit terrain normals (n, 3) at world points ``xy`` (n, 2) [m], as ``terrain_normal`` gives each. A
    ``normal_fn`` with a ``many(xs, ys)`` method (n, 3) is asked once for all points (e.g.
    ``tal_core.heightmap.GridNormals``); a row it returns non-finite or zero is vertical."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    many = getattr(normal_fn, "many", None)
    if many is None:
        return np.array([terrain_normal(normal_fn, x, y) for x, y in xy]).reshape(-1, 3)
    normals = np.asarray(many(xy[:, 0], xy[:, 1]), dtype=float)
    if normals.shape != (len(xy), 3):
        raise InputError(f"terrain normals callback gave shape {normals.shape} for {len(xy)} points")
    norms = np.sqrt((normals * normals).sum(axis=1))
    bad = ~(np.isfinite(norms) & (norms > 1e-9))
    if bad.any():
        normals, norms = normals.copy(), norms.copy()
        normals[bad], norms[bad] = _UP, 1.0
    return normals / norms[:, None]


def hip_at_touchdown(hip_xy_world: object, commanded_vel_world_xy: object, yaw_rate: float,
                     swing_time_left_s: float, rotation_centre_xy_world: object | None = None) -> np.ndarray:
    """(2,) [m] where the hip will be at touchdown if the trunk follows the command: the rotation centre
    (trunk) moves by ``v_cmd * t_left`` and the hip turns about it by ``yaw_rate * t_left``. Without a
    rotation centre the yaw rate is ignored (the hip itself is the centre)."""
    hip = _vector2(hip_xy_world, "hip_xy_world")
    centre = hip if rotation_centre_xy_world is None else _vector2(rotation_centre_xy_world,
                                                                    "rotation_centre_xy_world")
    t_left = np.array([_non_negative(swing_time_left_s, "swing_time_left_s")])
    _finite(yaw_rate, "yaw_rate")
    return _hips_at_touchdown(hip[None], _vector2(commanded_vel_world_xy, "commanded_vel_world_xy"),
                              float(yaw_rate), t_left, centre)[0][0]


def _finite(value: float, name: str) -> float:
    if not math.isfinite(value):
        raise InputError(f"foothold: {name} must be finite, got {value!r}")
    return float(value)


def _hips_at_touchdown(hips: np.ndarray, v_cmd: np.ndarray, yaw_rate: float, t_left: np.ndarray,
                       centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hips (n, 2) at touchdown and the arms (n, 2) from the rotation centre at touchdown to them."""
    angle = yaw_rate * t_left
    c, s = np.cos(angle), np.sin(angle)
    r = hips - centre
    arm = np.stack([c * r[:, 0] - s * r[:, 1], s * r[:, 0] + c * r[:, 1]], axis=1)
    return centre + v_cmd * t_left[:, None] + arm, arm


def raibert_footholds_xy(hips_xy_world: np.ndarray, base_lin_vel_world_xy: object,
                         commanded_vel_world_xy: object, yaw_rate: float, stance_duration_s: float,
                         swing_time_left_s: np.ndarray, k_feedback: float = DEFAULT_K_FEEDBACK, *,
                         rotation_centre_xy_world: object | None = None,
                         max_offset_m: float | None = None) -> np.ndarray:
    """Horizontal nominal footholds (n, 2) [m] of n legs at once (see ``nominal_foothold``);
    hips_xy_world (n, 2) [m], swing_time_left_s (n,) [s]."""
    hips = np.asarray(hips_xy_world, dtype=float)
    t_left = np.asarray(swing_time_left_s, dtype=float).reshape(-1)
    if hips.ndim != 2 or hips.shape[1] != 2 or t_left.shape != (hips.shape[0],):
        raise InputError(f"foothold: hips must be (n, 2) and times (n,), got {hips.shape}, {t_left.shape}")
    if not (np.isfinite(hips).all() and np.isfinite(t_left).all() and (t_left >= 0.0).all()):
        raise InputError("foothold: hips must be finite and swing times finite and >= 0")
    v = _vector2(base_lin_vel_world_xy, "base_lin_vel_world_xy")
    v_cmd = _vector2(commanded_vel_world_xy, "commanded_vel_world_xy")
    yaw_rate = _finite(yaw_rate, "yaw_rate")
    k = _non_negative(k_feedback, "k_feedback")
    t_stance = _non_negative(stance_duration_s, "stance_duration_s")
    if rotation_centre_xy_world is None:
        hips_td, v_hip_cmd = hips + v_cmd * t_left[:, None], np.broadcast_to(v_cmd, hips.shape)
    else:
        centre = _vector2(rotation_centre_xy_world, "rotation_centre_xy_world")
        hips_td, arm = _hips_at_touchdown(hips, v_cmd, yaw_rate, t_left, centre)
        v_hip_cmd = v_cmd + yaw_rate * np.stack([-arm[:, 1], arm[:, 0]], axis=1)
    offset = 0.5 * t_stance * v_hip_cmd + k * (v - v_cmd)
    if max_offset_m is not None:
        limit = _non_negative(max_offset_m, "max_offset_m")
        norm = np.linalg.norm(offset, axis=1, keepdims=True)
        offset = offset * np.minimum(1.0, limit / np.maximum(norm, 1e-12))
    return hips_td + offset


def nominal_foothold(hip_xy_world: object, base_lin_vel_world_xy: object, commanded_vel_world_xy: object,
                     yaw_rate: float, stance_duration_s: float, swing_time_left_s: float,
                     k_feedback: float = DEFAULT_K_FEEDBACK, *,
                     rotation_centre_xy_world: object | None = None,
                     height_fn: HeightFunction | None = None, default_z: float = 0.0,
                     max_offset_m: float | None = None) -> np.ndarray:
    """Nominal foothold (3,) [m], world frame: Raibert's rule, z from the terrain.

    hip_xy_world [m]: hip position now. base_lin_vel_world_xy [m/s]: measured trunk velocity.
    commanded_vel_world_xy [m/s]: commanded trunk velocity. yaw_rate [rad/s]: commanded yaw rate,
    applied about ``rotation_centre_xy_world`` [m] (the trunk; None: no rotation). stance_duration_s [s]:
    duration of the coming stance. swing_time_left_s [s]: time until touchdown. k_feedback [s]: velocity
    feedback gain. max_offset_m [m]: optional limit on the horizontal distance from the hip at
    touchdown (kinematic reach). z = ``height_fn(x, y)`` (``default_z`` without a function or off-map).
    """
    hip = _vector2(hip_xy_world, "hip_xy_world")
    t_left = _non_negative(swing_time_left_s, "swing_time_left_s")
    x, y = raibert_footholds_xy(hip[None], base_lin_vel_world_xy, commanded_vel_world_xy, yaw_rate,
                                stance_duration_s, np.array([t_left]), k_feedback,
                                rotation_centre_xy_world=rotation_centre_xy_world,
                                max_offset_m=max_offset_m)[0]
    return np.array([x, y, terrain_height(height_fn, x, y, default_z)])
