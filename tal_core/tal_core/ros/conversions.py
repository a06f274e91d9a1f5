"""Conversions between ROS messages and tal_core's plain arrays, for the thin node adapters only."""

from __future__ import annotations

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import JointState

from tal_core.errors import InputError
from tal_core.heightmap import HeightMapGrid
from tal_core.ros.cdr import CdrView
from tal_core.rotations import rotation_from_quat_xyzw
from tal_core.state import BaseState
from tal_msgs.msg import HeightMap


def base_state_from_odometry(msg: Odometry) -> BaseState:
    """Base state (world frame) from nav_msgs/Odometry whose twist is in child_frame_id (base), as in ROS."""
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    lin = msg.twist.twist.linear
    ang = msg.twist.twist.angular
    return _base_state(np.array([p.x, p.y, p.z, o.x, o.y, o.z, o.w, lin.x, lin.y, lin.z, ang.x, ang.y, ang.z]))


def base_state_from_odometry_view(view: CdrView) -> BaseState:
    """``base_state_from_odometry`` of a serialised nav_msgs/Odometry read in place (``CdrReader``)."""
    return _base_state(np.concatenate([view.vector("pose.pose.position"), view.quaternion("pose.pose.orientation"),
                                       view.vector("twist.twist.linear"), view.vector("twist.twist.angular")]))


def _base_state(values: np.ndarray) -> BaseState:
    """Position, quaternion (x, y, z, w) and the base-frame twist (linear, angular) as 13 values."""
    if not np.all(np.isfinite(values)):
        raise InputError("odometry has NaN or inf")
    quat = values[3:7]
    norm = float(np.linalg.norm(quat))
    if abs(norm - 1.0) > 1e-2:
        raise InputError(f"odometry orientation is not a unit quaternion (norm {norm:.4f})")
    quat = quat / norm
    world_R_base = rotation_from_quat_xyzw(quat)
    return BaseState(position=values[:3].copy(), quat_xyzw=quat,
                     linear_velocity=world_R_base @ values[7:10], angular_velocity=world_R_base @ values[10:13])


class JointStateReader:
    """Canonical joint arrays of serialised sensor_msgs/JointState messages read in place (``CdrReader``): the
    same ``joint_layout`` and ``canonical_joint_arrays`` as the message path, the layout worked out once per
    message layout (its names and lengths) instead of per message.

    ``__call__(view)`` gives (positions, velocities or None, efforts or None) in canonical order."""

    def __init__(self, index: dict[str, int], *, velocities_optional: bool = False, efforts: bool = False,
                 efforts_optional: bool = False) -> None:
        self.index = index
        self.options = {"velocities_optional": velocities_optional, "efforts": efforts,
                        "efforts_optional": efforts_optional}

    def _layout(self, msg: JointState) -> tuple[np.ndarray, bool, bool] | InputError:
        try:
            return joint_layout(msg, self.index, **self.options)
        except InputError as exc:  # every message of this layout gets the same error
            return exc

    def __call__(self, view: CdrView) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        layout = view.per_layout(self, self._layout)
        if isinstance(layout, InputError):
            raise layout
        targets, velocities, efforts = layout
        return canonical_joint_arrays(len(self.index), targets, view.array("position"),
                                      view.array("velocity") if velocities else None,
                                      view.array("effort") if efforts else None)


def joint_layout(msg: JointState, index: dict[str, int], *, velocities_optional: bool = False,
                 efforts: bool = False, efforts_optional: bool = False) -> tuple[np.ndarray, bool, bool]:
    """Where each named joint of a joint state goes in canonical order, and whether its velocities and (with
    ``efforts``) its efforts are read: what its names and lengths alone decide. InputError when a length
    differs from the names' or a joint is unknown. An empty velocity (effort) list is accepted when
    ``velocities_optional`` (``efforts_optional``) and gives None for them."""
    n = len(msg.name)
    no_velocities = velocities_optional and len(msg.velocity) == 0
    if len(msg.position) != n or (len(msg.velocity) != n and not no_velocities):
        raise InputError(f"joint_states has {n} names, {len(msg.position)} positions and "
                         f"{len(msg.velocity)} velocities")
    targets = []
    for name in msg.name:
        k = index.get(name)
        if k is None:
            raise InputError(f"joint_states names unknown joint '{name}'")
        targets.append(k)
    no_efforts = not efforts or (efforts_optional and len(msg.effort) == 0)
    if not no_efforts and len(msg.effort) != n:
        raise InputError(f"joint_states has {n} names and {len(msg.effort)} efforts")
    return np.array(targets, dtype=np.intp), not no_velocities, not no_efforts


def canonical_joint_arrays(size: int, targets: np.ndarray, positions, velocities=None, efforts=None
                           ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Positions, velocities (None: not given) and efforts (None: not read) in canonical order (``size``
    joints) from a joint state's arrays and its ``joint_layout`` targets; InputError when a joint is missing
    or a value is not finite."""
    q = np.full(size, np.nan)
    qd = np.full(size, np.nan)
    if len(targets):
        q[targets] = positions
        qd[targets] = 0.0 if velocities is None else velocities
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))):
        raise InputError("joint_states lacks joints or has NaN/inf values")
    tau = None
    if efforts is not None:
        tau = np.full(size, np.nan)
        if len(targets):
            tau[targets] = efforts
        if not np.all(np.isfinite(tau)):
            raise InputError("joint_states efforts have NaN/inf")
    return q, None if velocities is None else qd, tau


def canonical_joint_state(msg: JointState, index: dict[str, int],
                          velocities_optional: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """Joint positions [rad] and velocities [rad/s] in canonical order; InputError on bad content. With
    ``velocities_optional`` a message without velocities (an empty list) gives None for them."""
    targets, velocities, _ = joint_layout(msg, index, velocities_optional=velocities_optional)
    q, qd, _ = canonical_joint_arrays(len(index), targets, msg.position, msg.velocity if velocities else None)
    return q, qd


def heightmap_grid(msg: HeightMap) -> HeightMapGrid:
    """HeightMapGrid from a tal_msgs/HeightMap (same cell convention)."""
    heights = np.asarray(msg.heights, dtype=np.float32)
    if heights.size != msg.rows * msg.cols:
        raise InputError(f"heightmap has {heights.size} heights for {msg.rows} x {msg.cols} cells")
    return HeightMapGrid(center_xy=(msg.center.x, msg.center.y), yaw=msg.yaw, resolution_m=msg.resolution,
                         heights=heights.reshape(msg.rows, msg.cols))
