"""Measured data from a bag, as arrays on the joint-state time grid.

Signals (topic -> field, units and frames as in the graph's messages):
  joint_states: q [rad], qd [rad/s], effort = measured joint torque [N m], canonical joint order;
  imu: angular rate [rad/s] and specific force [m/s^2], base frame;
  ground_truth/odom (or state_estimate when the data has no ground truth): base position [m] and
      orientation (world frame), linear [m/s] and angular [rad/s] velocity (base frame, ROS convention);
  joint_command: the feed-forward torques sent [N m] (the robot driver holds the last one);
  cmd_vel: the velocity command [m/s, rad/s] (horizontal frame);
  ground_truth/contacts: per-leg contact flags and forces [N] (world frame), when available.

Stamps are header stamps (sim time). Out-of-order or repeated stamps are dropped and counted, never
silently used; a joint-state rate that is not steady, angles that look like degrees or a specific force
that does not look like m/s^2 are refused with the reason.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tal_core.robot_description import RobotDescription
from tal_core.ros.bag_io import BagError, BagReader

from . import cdr
from .errors import MeasuredDataError

LOG = logging.getLogger("tal.sim2real.measured")

TOPICS = {
    "joint_states": "/joint_states",
    "imu": "/imu",
    "ground_truth": "/ground_truth/odom",
    "state_estimate": "/state_estimate",
    "joint_command": "/joint_command",
    "cmd_vel": "/cmd_vel",
    "contacts": "/ground_truth/contacts",
}
MAX_ABS_JOINT_ANGLE_RAD = 2.0 * math.pi  # larger angles are degrees (or encoder counts), not radians
GRAVITY_M_S2 = 9.81


@dataclass
class BaseTrajectory:
    """Base state sampled on the joint-state grid: position [m] and quaternion (x, y, z, w) in the world
    frame, world_R_base (N, 3, 3) of that quaternion, linear [m/s] and angular [rad/s] velocity in the world
    frame; source topic."""

    position_m: np.ndarray
    quat_xyzw: np.ndarray
    world_R_base: np.ndarray
    lin_vel_world_m_s: np.ndarray
    ang_vel_world_rad_s: np.ndarray
    source: str


@dataclass
class MeasuredData:
    """A measured experiment on the joint-state time grid t_s [s] (N samples, steady rate dt_s [s]).

    Optional signals are None when the bag does not carry them; ``rejected`` counts dropped samples per
    topic (out of order, repeated stamps, non-finite values).
    """

    path: str
    joint_names: list[str]
    t_s: np.ndarray
    dt_s: float
    q_rad: np.ndarray
    qd_rad_s: np.ndarray
    effort_nm: np.ndarray | None
    gyro_rad_s: np.ndarray | None = None
    accel_m_s2: np.ndarray | None = None
    base: BaseTrajectory | None = None
    command_t_s: np.ndarray | None = None
    command_nm: np.ndarray | None = None
    cmd_vel_t_s: np.ndarray | None = None
    cmd_vel: np.ndarray | None = None
    contact_t_s: np.ndarray | None = None
    contact_in: np.ndarray | None = None
    contact_force_n: np.ndarray | None = None
    rejected: dict[str, int] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])

    def signals(self) -> set[str]:
        """Names of the signals present (used by the effect library's requirements)."""
        have = {"joint_states.position", "joint_states.velocity"}
        optional = {
            "joint_states.effort": self.effort_nm,
            "imu": self.gyro_rad_s,
            "base_state": self.base,
            "joint_command": self.command_nm,
            "cmd_vel": self.cmd_vel,
            "contacts": self.contact_in,
        }
        have |= {name for name, value in optional.items() if value is not None}
        if self.base is not None and self.base.source == TOPICS["ground_truth"]:
            have.add("ground_truth")
        return have

    def index_at(self, t_s: float) -> int:
        """Index of the last joint-state sample at or before t_s [s]."""
        return int(np.clip(np.searchsorted(self.t_s, t_s, side="right") - 1, 0, len(self.t_s) - 1))

    def command_in_force(self) -> np.ndarray:
        """(N, 12) torque command [N m] the driver applied during the physics step that ended at each
        joint-state sample (zero-order hold of the last command stamped at or before the step's start)."""
        if self.command_nm is None or self.command_t_s is None:
            raise MeasuredDataError(f"{self.path}: no joint_command in the bag")
        start = self.t_s - self.dt_s
        idx = np.searchsorted(self.command_t_s, start + 1e-9, side="right") - 1
        out = np.where(idx[:, None] >= 0, self.command_nm[np.clip(idx, 0, None)], 0.0)
        return out


def _stamp_s(msg) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def _keep_increasing(t: np.ndarray, topic: str, rejected: dict[str, int]) -> np.ndarray:
    """Mask of samples whose stamp increases strictly over the last kept one; counts the rest."""
    keep = np.zeros(len(t), dtype=bool)
    last = -math.inf
    for i, value in enumerate(t):
        if value > last:
            keep[i] = True
            last = value
    dropped = int((~keep).sum())
    if dropped:
        rejected[topic] = rejected.get(topic, 0) + dropped
        LOG.warning("%s: %d samples with out-of-order or repeated stamps dropped", topic, dropped)
    return keep


def load_measured(
    path: str | Path, description: RobotDescription, start_s: float | None = None, end_s: float | None = None
) -> MeasuredData:
    """Read a bag into MeasuredData (stamps relative to nothing: sim time as recorded).

    Raises MeasuredDataError for an unreadable bag, missing joint states, unknown joints or units that are
    not SI; optional signals that are absent stay None.
    """
    path = Path(path)
    try:
        reader = BagReader(path)
        buffers: dict[str, list] = {name: [] for name in TOPICS}
        by_topic = {topic: name for name, topic in TOPICS.items()}
        for record in reader.messages(list(TOPICS.values()), decode=False):
            # the types cdr.py knows straight from their bytes, the others (or a message that does not parse
            # there) by rclpy; a type rclpy does not know is skipped, as BagReader does
            message = cdr.decode(record.type_name, record.data)
            if message is None:
                message = reader.decode(record.type_name, record.data)
                if message is None:
                    continue
            name = by_topic[record.topic]
            # geometry_msgs/Twist has no header: keep its log time [s] with it
            buffers[name].append((record.log_time_ns * 1e-9, message) if name == "cmd_vel" else message)
    except (BagError, OSError) as exc:
        raise MeasuredDataError(f"{path}: cannot read the bag: {exc}") from exc
    if not reader.report.complete:
        LOG.warning("%s: bag truncated or corrupt, using the readable prefix (%s)", path, reader.report.error)
    if not buffers["joint_states"]:
        raise MeasuredDataError(f"{path}: no /joint_states messages; the workflow needs joint states")
    rejected: dict[str, int] = {}
    joints = _joint_arrays(buffers["joint_states"], description, rejected, str(path))
    t = joints["t"]
    window = np.ones(len(t), dtype=bool)
    if start_s is not None:
        window &= t >= start_s
    if end_s is not None:
        window &= t <= end_s
    for key in joints:
        if joints[key] is not None:
            joints[key] = joints[key][window]
    t = joints["t"]
    if len(t) < 10:
        raise MeasuredDataError(f"{path}: fewer than 10 joint-state samples in the window")
    steps = np.diff(t)
    dt = float(np.median(steps))
    irregular = np.abs(steps - dt) > 0.25 * dt
    if irregular.mean() > 0.01:
        raise MeasuredDataError(
            f"{path}: joint_states stamps are not at a steady rate ({100 * irregular.mean():.1f}% "
            f"of the steps differ from the median {dt * 1e3:.3f} ms by > 25%)"
        )
    data = MeasuredData(
        str(path), list(description.joint_names), t, dt, joints["q"], joints["qd"], joints["effort"], rejected=rejected
    )
    _attach_imu(data, buffers["imu"])
    source = "ground_truth" if buffers["ground_truth"] else "state_estimate"
    _attach_base(data, buffers[source], TOPICS[source])
    _attach_commands(data, buffers["joint_command"], description)
    if buffers["cmd_vel"]:
        data.cmd_vel_t_s = np.array([t_log for t_log, _ in buffers["cmd_vel"]])
        data.cmd_vel = np.array([[m.linear.x, m.linear.y, m.angular.z] for _, m in buffers["cmd_vel"]])
    _attach_contacts(data, buffers["contacts"])
    return data


def _joint_arrays(
    messages: list, description: RobotDescription, rejected: dict[str, int], where: str
) -> dict[str, np.ndarray | None]:
    names = list(messages[0].name)
    unknown = sorted(set(names) - set(description.joint_names))
    missing = sorted(set(description.joint_names) - set(names))
    if unknown or missing:
        raise MeasuredDataError(
            f"{where}: joint_states names do not match the robot: unknown {unknown}, missing {missing}"
        )
    order = [names.index(n) for n in description.joint_names]
    t = np.array([_stamp_s(m) for m in messages])
    has_effort = all(len(m.effort) == len(names) for m in messages)
    q = np.full((len(messages), len(order)), np.nan)
    qd = np.full_like(q, np.nan)
    effort = np.full_like(q, np.nan) if has_effort else None
    for i, m in enumerate(messages):
        if list(m.name) != names or len(m.position) != len(names) or len(m.velocity) != len(names):
            continue  # stays NaN: counted below
        q[i] = np.asarray(m.position)[order]
        qd[i] = np.asarray(m.velocity)[order]
        if effort is not None:
            effort[i] = np.asarray(m.effort)[order]
    finite = np.isfinite(q).all(1) & np.isfinite(qd).all(1)
    if effort is not None:
        finite &= np.isfinite(effort).all(1)
    if (~finite).any():
        rejected["/joint_states"] = rejected.get("/joint_states", 0) + int((~finite).sum())
        LOG.warning("/joint_states: %d samples with NaN, missing or reordered fields dropped", int((~finite).sum()))
    keep = finite.copy()
    keep[finite] = _keep_increasing(t[finite], "/joint_states", rejected)
    largest = float(np.max(np.abs(q[keep]))) if keep.any() else 0.0
    if largest > MAX_ABS_JOINT_ANGLE_RAD:
        raise MeasuredDataError(
            f"{where}: joint positions reach {largest:.1f}, beyond 2 pi: they are not in "
            "radians (degrees?); convert them (tal_core.ros.csv_import maps units)"
        )
    return {"t": t[keep], "q": q[keep], "qd": qd[keep], "effort": None if effort is None else effort[keep]}


def _attach_imu(data: MeasuredData, messages: list) -> None:
    if not messages:
        return
    t = np.array([_stamp_s(m) for m in messages])
    w = np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for m in messages])
    f = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z] for m in messages])
    keep = np.isfinite(w).all(1) & np.isfinite(f).all(1)
    keep[keep] = _keep_increasing(t[keep], "/imu", data.rejected)
    t, w, f = t[keep], w[keep], f[keep]
    mean_norm = float(np.linalg.norm(f.mean(axis=0)))
    if not 0.7 * GRAVITY_M_S2 < mean_norm < 1.3 * GRAVITY_M_S2:
        raise MeasuredDataError(
            f"{data.path}: the mean specific force is {mean_norm:.2f}, not ~9.81: the IMU "
            "acceleration is not in m/s^2 (in g?)"
        )
    data.gyro_rad_s = _resample(t, w, data.t_s)
    data.accel_m_s2 = _resample(t, f, data.t_s)


def _attach_base(data: MeasuredData, messages: list, topic: str) -> None:
    if not messages:
        return
    t = np.array([_stamp_s(m) for m in messages])
    pos = np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z] for m in messages])
    quat = np.array(
        [
            [m.pose.pose.orientation.x, m.pose.pose.orientation.y, m.pose.pose.orientation.z, m.pose.pose.orientation.w]
            for m in messages
        ]
    )
    lin_b = np.array([[m.twist.twist.linear.x, m.twist.twist.linear.y, m.twist.twist.linear.z] for m in messages])
    ang_b = np.array([[m.twist.twist.angular.x, m.twist.twist.angular.y, m.twist.twist.angular.z] for m in messages])
    keep = np.isfinite(pos).all(1) & np.isfinite(quat).all(1) & np.isfinite(lin_b).all(1) & np.isfinite(ang_b).all(1)
    norms = np.linalg.norm(quat, axis=1)
    bad_quat = keep & (np.abs(norms - 1.0) > 1e-3)
    if bad_quat.any():
        data.rejected[topic] = data.rejected.get(topic, 0) + int(bad_quat.sum())
        LOG.warning("%s: %d samples with a non-unit quaternion dropped", topic, int(bad_quat.sum()))
    keep &= ~bad_quat
    keep[keep] = _keep_increasing(t[keep], topic, data.rejected)
    t, pos, quat, lin_b, ang_b = t[keep], pos[keep], quat[keep], lin_b[keep], ang_b[keep]
    # Nearest sample for the orientation (the grids coincide in practice), interpolation for the rest.
    nearest = np.clip(np.searchsorted(t, data.t_s), 0, len(t) - 1)
    quat_g = quat[nearest]
    rotations = rotations_from_quat_xyzw(quat_g)
    lin_w = np.einsum("nij,nj->ni", rotations, _resample(t, lin_b, data.t_s))
    ang_w = np.einsum("nij,nj->ni", rotations, _resample(t, ang_b, data.t_s))
    data.base = BaseTrajectory(_resample(t, pos, data.t_s), quat_g, rotations, lin_w, ang_w, topic)


def rotations_from_quat_xyzw(quat: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of (N, 4) unit quaternions (x, y, z, w), vectorised."""
    x, y, z, w = (quat[:, i] for i in range(4))
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        1,
    )


def _attach_commands(data: MeasuredData, messages: list, description: RobotDescription) -> None:
    if not messages:
        return
    names = list(messages[0].name)
    unknown = sorted(set(names) - set(description.joint_names))
    if unknown:
        raise MeasuredDataError(f"{data.path}: joint_command names joints the robot lacks: {unknown}")
    order = {n: i for i, n in enumerate(description.joint_names)}
    t = np.array([_stamp_s(m) for m in messages])
    tau = np.zeros((len(messages), len(order)))
    finite = np.ones(len(messages), dtype=bool)
    for i, m in enumerate(messages):
        if len(m.effort) != len(m.name) or not np.all(np.isfinite(m.effort)):
            finite[i] = False
            continue
        for name, value in zip(m.name, m.effort):
            tau[i, order[name]] = value
    if (~finite).any():
        data.rejected["/joint_command"] = data.rejected.get("/joint_command", 0) + int((~finite).sum())
    keep = finite.copy()
    keep[finite] = _keep_increasing(t[finite], "/joint_command", data.rejected)
    data.command_t_s, data.command_nm = t[keep], tau[keep]


def _attach_contacts(data: MeasuredData, messages: list) -> None:
    if not messages:
        return
    t = np.array([_stamp_s(m) for m in messages])
    inside = np.array([list(m.in_contact) for m in messages], dtype=bool)
    force = np.array([[[f.x, f.y, f.z] for f in m.force] for m in messages]) if hasattr(messages[0], "force") else None
    keep = _keep_increasing(t, "/ground_truth/contacts", data.rejected)
    data.contact_t_s, data.contact_in = t[keep], inside[keep]
    data.contact_force_n = None if force is None else force[keep]


def _resample(t_src: np.ndarray, values: np.ndarray, t_dst: np.ndarray) -> np.ndarray:
    """Linear interpolation per column onto t_dst (held at the ends)."""
    return np.stack([np.interp(t_dst, t_src, values[:, k]) for k in range(values.shape[1])], axis=1)


def white_noise_std(x: np.ndarray) -> float:
    """White-noise level of a signal sampled much faster than it changes (joint angles, rates, torques),
    from its second differences: std(d2 x) = sqrt(6) sigma for white noise. The median absolute deviation
    keeps the occasional step (a 250 Hz command update) from counting as noise."""
    d2 = np.diff(x, n=2, axis=0).ravel()
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return 1.4826 * mad / math.sqrt(6.0)
