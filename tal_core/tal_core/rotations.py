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
