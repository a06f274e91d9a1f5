"""Node ``stand_controller``: joint PD hold of the nominal pose with gravity feed-forward.

Answers every control tick of the bridge. Control ticks lie on the sim-time grid t = k * control_period_s;
when a ``joint_states`` message reaches the next tick it publishes a ``joint_command`` stamped with that
joint-state stamp, which is what the bridge's lockstep protocol waits for.

The PD gains kp_nm_per_rad and kd_nms_per_rad are live (``ros2 param set``, from the next tick); robot and
control_period_s are read-only.
"""

from __future__ import annotations

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState

from tal_core.errors import InputError
from tal_core.robot_model import RobotModel
from tal_core.ros.node_utils import declare, ns_from_stamp, reaches_tick, run_node, tick_after
from tal_core.ticks import CLOCK_RESET_NS
from tal_msgs.msg import JointCommand

from .stand_hold import StandHold


class StandControllerNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("stand_controller", **kwargs)
        robot = declare(self, "robot", "hyq", "robot YAML: shipped name or path")
        kp = declare(self, "kp_nm_per_rad", 1500.0, "[N m/rad] joint stiffness; live", low=0.0, high=1e5,
                     on_change=lambda value: setattr(self.hold, "kp", float(value)))
        kd = declare(self, "kd_nms_per_rad", 40.0, "[N m s/rad] joint damping; live", low=0.0, high=1e4,
                     on_change=lambda value: setattr(self.hold, "kd", float(value)))
        period = declare(self, "control_period_s", 0.004, "[s] control tick", low=0.0005, high=0.1)
        self.model = RobotModel.from_name(robot)
        self.hold = StandHold(self.model, kp, kd)
        self.period_ns = round(period * 1e9)
        self.joint_names = list(self.model.description.joint_names)
        self._index = {name: i for i, name in enumerate(self.joint_names)}
        self._next_tick_ns = 0
        self._last_command: JointCommand | None = None
        self.rejected = 0
        self.commands_sent = 0
        self.pub = self.create_publisher(JointCommand, "joint_command", 10)
        self.create_subscription(JointState, "joint_states", self._on_joint_states, 10)

    def _on_joint_states(self, msg: JointState) -> None:
        stamp_ns = ns_from_stamp(msg.header.stamp)
        if self._last_command is not None and stamp_ns == ns_from_stamp(self._last_command.header.stamp):
            self.pub.publish(self._last_command)  # the driver repeats a state until a command arrives
            return
        if stamp_ns + CLOCK_RESET_NS < self._next_tick_ns:
            self.get_logger().warn("joint_states time jumped back (simulation restarted): resetting ticks")
            self._next_tick_ns = 0
        if not reaches_tick(stamp_ns, self._next_tick_ns):
            return
        try:
            q = self._canonical_positions(msg)
            fields = self.hold.command(q)
        except InputError as exc:
            self.rejected += 1
            self.get_logger().warn(f"rejected joint_states ({self.rejected} so far): {exc}",
                                   throttle_duration_sec=1.0)
            return
        cmd = JointCommand()
        cmd.header.stamp = msg.header.stamp
        cmd.name = self.joint_names
        for field, values in fields.items():
            setattr(cmd, field, values.tolist())
        self.pub.publish(cmd)
        self._last_command = cmd
        self.commands_sent += 1
        self._next_tick_ns = tick_after(stamp_ns, self.period_ns)

    def _canonical_positions(self, msg: JointState) -> np.ndarray:
        if len(msg.position) != len(msg.name):
            raise InputError(f"joint_states has {len(msg.name)} names but {len(msg.position)} positions")
        q = np.full(len(self.joint_names), np.nan)
        for name, value in zip(msg.name, msg.position):
            index = self._index.get(name)
            if index is None:
                raise InputError(f"joint_states names unknown joint '{name}'")
            q[index] = value
        if not np.all(np.isfinite(q)):
            raise InputError("joint_states lacks joints or has NaN positions")
        return q


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: StandControllerNode(), args, name="stand_controller")


if __name__ == "__main__":
    raise SystemExit(main())
