"""Small rotation helpers shared by all packages (quaternions in ROS order x, y, z, w)."""

from __future__ import annotations

import numpy as np


def rotation_from_quat_xyzw(quat: np.ndarray) -> np.ndarray:
    """Rotation matrix (e.g. world_R_base) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = quat
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
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def skew(vector: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix S(v) with S(v) w = v x w."""
    x, y, z = vector
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(rotation_vector: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector [rad] (axis times angle), Rodrigues' formula."""
    angle = float(np.linalg.norm(rotation_vector))
    k = skew(rotation_vector)
    if angle < 1e-8:
        return np.eye(3) + k + 0.5 * (k @ k)
    return np.eye(3) + (np.sin(angle) / angle) * k + ((1.0 - np.cos(angle)) / angle**2) * (k @ k)


def so3_log(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector [rad] of a rotation matrix (inverse of ``so3_exp`` for angles up to pi)."""
    axis_sin = 0.5 * np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0],
                               rotation[1, 0] - rotation[0, 1]])
    cos_angle = float(np.clip(0.5 * (np.trace(rotation) - 1.0), -1.0, 1.0))
    sin_angle = float(np.linalg.norm(axis_sin))
    angle = float(np.arctan2(sin_angle, cos_angle))  # accurate at both ends, unlike arccos near pi
    if angle < 1e-6:
        return axis_sin
    if np.pi - angle < 1e-4:
        # Near pi the antisymmetric part vanishes: the symmetric part is (1 - cos) a a^T; its largest
        # column gives the axis, the antisymmetric part its sign.
        symmetric = 0.5 * (rotation + rotation.T) - cos_angle * np.eye(3)
        column = int(np.argmax(np.diag(symmetric)))
        axis = symmetric[:, column] / np.sqrt(symmetric[column, column] * (1.0 - cos_angle))
        if axis @ axis_sin < 0.0:
            axis = -axis
        return angle * axis
    return angle / sin_angle * axis_sin


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation matrix closest to ``matrix`` in the Frobenius norm (polar decomposition)."""
    u, _, vt = np.linalg.svd(matrix)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def quat_xyzw_from_rotation(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix (Shepperd's method)."""
    m = rotation
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0.0:
        s = 2.0 * np.sqrt(trace + 1.0)
        quat = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s])
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        quat = np.array([0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s])
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        quat = np.array([(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        quat = np.array([(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s])
    quat /= np.linalg.norm(quat)
    return quat if quat[3] >= 0.0 else -quat
