"""Validation and zero-order hold of joint commands, independent of ROS.

The robot driver keeps the last valid command and evaluates, at every physics step,
    tau = effort + kp * (position - q) + kd * (velocity - qd)
in the robot's canonical joint order. Invalid commands are rejected with a reason and never replace
the held command. Before any valid command arrives the joints are damped (tau = -kd_safe * qd).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .errors import CommandRejectedError


@dataclass(frozen=True)
class HeldCommand:
    """A validated command in canonical joint order (arrays of length n_joints)."""

    stamp_ns: int
    effort: np.ndarray          # [N m]
    position: np.ndarray | None  # [rad]
    velocity: np.ndarray | None  # [rad/s]
    kp: np.ndarray | None        # [N m/rad]
    kd: np.ndarray | None        # [N m s/rad]


class JointCommandHold:
    """Validates incoming joint commands and holds the last valid one."""

    def __init__(self, joint_names: Sequence[str], safe_damping_nms_per_rad: float = 5.0) -> None:
        self.joint_names = tuple(joint_names)
        self._index = {name: i for i, name in enumerate(self.joint_names)}
        self.safe_damping = float(safe_damping_nms_per_rad)
        self.held: HeldCommand | None = None
        self.rejections: Counter[str] = Counter()
        self.accepted = 0

    @property
    def rejected_total(self) -> int:
        return sum(self.rejections.values())

    def submit(self, stamp_ns: int, names: Sequence[str], effort: Sequence[float],
               position: Sequence[float] = (), velocity: Sequence[float] = (),
               kp: Sequence[float] = (), kd: Sequence[float] = ()) -> HeldCommand:
        """Validate a command and hold it; raises CommandRejectedError (and counts it) when invalid."""
        try:
            command = self._validate(stamp_ns, names, effort, position, velocity, kp, kd)
        except CommandRejectedError as exc:
            self.rejections[exc.reason] += 1
            raise
        self.held = command
        self.accepted += 1
        return command

    def torque(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """Commanded joint torque [N m] for joint positions q [rad] and velocities qd [rad/s]."""
        cmd = self.held
        if cmd is None:
            return -self.safe_damping * qd
        tau = cmd.effort.copy()
        if cmd.kp is not None and cmd.position is not None:
            tau += cmd.kp * (cmd.position - q)
        if cmd.kd is not None:
            target = cmd.velocity if cmd.velocity is not None else 0.0
            tau += cmd.kd * (target - qd)
        return tau

    def _validate(self, stamp_ns: int, names: Sequence[str], effort: Sequence[float],
                  position: Sequence[float], velocity: Sequence[float],
                  kp: Sequence[float], kd: Sequence[float]) -> HeldCommand:
        n = len(names)
        if n == 0:
            raise CommandRejectedError("empty", "joint command has no joint names")
        unknown = [name for name in names if name not in self._index]
        if unknown:
            raise CommandRejectedError("unknown_joint", f"joint command names unknown joint(s) {unknown}")
        if len(set(names)) != n:
            raise CommandRejectedError("duplicate_joint", f"joint command repeats joint names: {list(names)}")
        if self.held is not None and stamp_ns < self.held.stamp_ns:
            raise CommandRejectedError(
                "out_of_order",
                f"joint command stamp {stamp_ns} ns is older than the held command ({self.held.stamp_ns} ns)")
        order = np.array([self._index[name] for name in names])
        fields = {"effort": effort, "position": position, "velocity": velocity, "kp": kp, "kd": kd}
        canonical: dict[str, np.ndarray | None] = {}
        for field_name, values in fields.items():
            if len(values) == 0 and field_name != "effort":
                canonical[field_name] = None
                continue
            if len(values) != n:
                raise CommandRejectedError(
                    "wrong_size", f"joint command field '{field_name}' has {len(values)} values for {n} names")
            array = np.asarray(values, dtype=float)
            if not np.all(np.isfinite(array)):
                raise CommandRejectedError("non_finite", f"joint command field '{field_name}' has NaN or inf")
            full = np.zeros(len(self.joint_names))
            full[order] = array
            canonical[field_name] = full
        if canonical["kp"] is not None and canonical["position"] is None:
            raise CommandRejectedError("wrong_size", "joint command gives kp without position targets")
        for gain in ("kp", "kd"):
            values = canonical[gain]
            if values is not None and np.any(values < 0.0):
                raise CommandRejectedError("negative_gain", f"joint command field '{gain}' has negative gains")
        if n != len(self.joint_names):
            # Joints not named keep zero effort and no PD term: make that explicit rather than silent.
            raise CommandRejectedError(
                "wrong_size", f"joint command names {n} joints, the robot has {len(self.joint_names)}")
        return HeldCommand(stamp_ns=stamp_ns, effort=canonical["effort"],  # type: ignore[arg-type]
                           position=canonical["position"], velocity=canonical["velocity"],
                           kp=canonical["kp"], kd=canonical["kd"])
