"""Small rotation helpers shared by all packages (quaternions in ROS order x, y, z, w)."""

from __future__ import annotations

import math

import numpy as np


def rotation_from_quat_xyzw(quat: np.ndarray) -> np.ndarray:
    """Rotation matrix (e.g. world_R_base) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = np.asarray(quat, dtype=float).tolist()   # Python floats: scalar arithmetic is cheaper
    return np.array(
        [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
            [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
            [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
        ]
    )


def yaw_from_quat_xyzw(quat: np.ndarray) -> float:
    """Heading [rad] (rotation about world z) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = quat
    return float(np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for two 3-vectors: np.cross's arithmetic (bit for bit) without its ~25 us of axis bookkeeping."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis of arrays of 3-vectors (broadcast as numpy does), np.cross's arithmetic."""
    a, b = np.asarray(a), np.asarray(b)
    return a[..., _NEXT] * b[..., _AFTER] - a[..., _AFTER] * b[..., _NEXT]


_NEXT, _AFTER = np.array([1, 2, 0]), np.array([2, 0, 1])   # component i of a x b = a[i+1] b[i+2] - a[i+2] b[i+1]


def skew(vector: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix S(v) with S(v) w = v x w."""
    x, y, z = vector
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(rotation_vector: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector [rad] (axis times angle), Rodrigues' formula
    I + (sin a / a) K + ((1 - cos a) / a^2) K^2 with K = S(v), in scalar arithmetic (a 3 x 3 from numpy's
    small-array calls cost several times more; estimators call this every tick)."""
    x, y, z = float(rotation_vector[0]), float(rotation_vector[1]), float(rotation_vector[2])
    xx, yy, zz = x * x, y * y, z * z
    angle = math.sqrt(xx + yy + zz)
    if angle < 1e-8:
        a, b = 1.0, 0.5
    else:
        a, b = math.sin(angle) / angle, (1.0 - math.cos(angle)) / (angle * angle)
    # K^2 = v v^T - |v|^2 I
    xy, xz, yz = b * x * y, b * x * z, b * y * z
    ax, ay, az = a * x, a * y, a * z
    return np.array([[1.0 - b * (yy + zz), xy - az, xz + ay],
                     [xy + az, 1.0 - b * (xx + zz), yz - ax],
                     [xz - ay, yz + ax, 1.0 - b * (xx + yy)]])


def so3_log(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector [rad] of a rotation matrix (inverse of ``so3_exp`` for angles up to pi)."""
    r = rotation
    sx, sy, sz = 0.5 * (r[2, 1] - r[1, 2]), 0.5 * (r[0, 2] - r[2, 0]), 0.5 * (r[1, 0] - r[0, 1])
    cos_angle = min(max(0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0), -1.0), 1.0)
    sin_angle = math.sqrt(sx * sx + sy * sy + sz * sz)
    angle = math.atan2(sin_angle, cos_angle)  # accurate at both ends, unlike arccos near pi
    if angle < 1e-6:
        return np.array([sx, sy, sz], dtype=float)
    if math.pi - angle < 1e-4:
        # Near pi the antisymmetric part vanishes: the symmetric part is (1 - cos) a a^T; its largest
        # column gives the axis, the antisymmetric part its sign.
        axis_sin = np.array([sx, sy, sz], dtype=float)
        symmetric = 0.5 * (rotation + rotation.T) - cos_angle * np.eye(3)
        column = int(np.argmax(np.diag(symmetric)))
        axis = symmetric[:, column] / np.sqrt(symmetric[column, column] * (1.0 - cos_angle))
        if axis @ axis_sin < 0.0:
            axis = -axis
        return angle * axis
    scale = angle / sin_angle
    return np.array([scale * sx, scale * sy, scale * sz], dtype=float)


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation matrix closest to ``matrix`` in the Frobenius norm (polar decomposition)."""
    u, _, vt = np.linalg.svd(matrix)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def quat_xyzw_from_rotation(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix (Shepperd's method; scalar arithmetic)."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = np.asarray(rotation, dtype=float).tolist()
    trace = m00 + m11 + m22
    if trace > 0.0:
        s = 2.0 * math.sqrt(trace + 1.0)
        x, y, z, w = (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        x, y, z, w = 0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        x, y, z, w = (m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        x, y, z, w = (m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if w < 0.0:
        norm = -norm
    return np.array([x / norm, y / norm, z / norm, w / norm])
