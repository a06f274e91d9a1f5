"""Conversions between ROS messages and tal_core's plain arrays, for the thin node adapters only."""

from __future__ import annotations

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import JointState

from tal_core.errors import InputError
from tal_core.heightmap import HeightMapGrid
from tal_core.rotations import rotation_from_quat_xyzw
from tal_core.state import BaseState
from tal_msgs.msg import HeightMap


def base_state_from_odometry(msg: Odometry) -> BaseState:
    """Base state (world frame) from nav_msgs/Odometry whose twist is in child_frame_id (base), as in ROS."""
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    position = np.array([p.x, p.y, p.z])
    quat = np.array([o.x, o.y, o.z, o.w])
    lin = msg.twist.twist.linear
    ang = msg.twist.twist.angular
    values = np.concatenate([position, quat, [lin.x, lin.y, lin.z, ang.x, ang.y, ang.z]])
    if not np.all(np.isfinite(values)):
        raise InputError("odometry has NaN or inf")
    norm = float(np.linalg.norm(quat))
    if abs(norm - 1.0) > 1e-2:
        raise InputError(f"odometry orientation is not a unit quaternion (norm {norm:.4f})")
    quat = quat / norm
    world_R_base = rotation_from_quat_xyzw(quat)
    return BaseState(position=position, quat_xyzw=quat,
                     linear_velocity=world_R_base @ np.array([lin.x, lin.y, lin.z]),
                     angular_velocity=world_R_base @ np.array([ang.x, ang.y, ang.z]))


def canonical_joint_state(msg: JointState, index: dict[str, int],
                          velocities_optional: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """Joint positions [rad] and velocities [rad/s] in canonical order; InputError on bad content. With
    ``velocities_optional`` a message without velocities (an empty list) gives None for them."""
    n = len(index)
    no_velocities = velocities_optional and len(msg.velocity) == 0
    if len(msg.position) != len(msg.name) or (len(msg.velocity) != len(msg.name) and not no_velocities):
        raise InputError(f"joint_states has {len(msg.name)} names, {len(msg.position)} positions and "
                         f"{len(msg.velocity)} velocities")
    q = np.full(n, np.nan)
    qd = np.full(n, np.nan)
    velocities = [0.0] * len(msg.name) if no_velocities else msg.velocity
    for name, position, velocity in zip(msg.name, msg.position, velocities):
        k = index.get(name)
        if k is None:
            raise InputError(f"joint_states names unknown joint '{name}'")
        q[k], qd[k] = position, velocity
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))):
        raise InputError("joint_states lacks joints or has NaN/inf values")
    return q, None if no_velocities else qd


def heightmap_grid(msg: HeightMap) -> HeightMapGrid:
    """HeightMapGrid from a tal_msgs/HeightMap (same cell convention)."""
    heights = np.asarray(msg.heights, dtype=np.float32)
    if heights.size != msg.rows * msg.cols:
        raise InputError(f"heightmap has {heights.size} heights for {msg.rows} x {msg.cols} cells")
    return HeightMapGrid(center_xy=(msg.center.x, msg.center.y), yaw=msg.yaw, resolution_m=msg.resolution,
                         heights=heights.reshape(msg.rows, msg.cols))


def heightmap_normal(grid: HeightMapGrid, x: float, y: float) -> np.ndarray:
    """Unit terrain normal (world) from central differences of the heightmap; up where unknown."""
    h = grid.resolution_m
    dzdx = (grid.height_at(x + h, y) - grid.height_at(x - h, y)) / (2 * h)
    dzdy = (grid.height_at(x, y + h) - grid.height_at(x, y - h)) / (2 * h)
    normal = np.array([-float(dzdx), -float(dzdy), 1.0])
    if not np.all(np.isfinite(normal)):
        return np.array([0.0, 0.0, 1.0])
    return normal / np.linalg.norm(normal)
