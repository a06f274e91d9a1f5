"""Node ``cmd_vel_script``: plays a piecewise-constant velocity profile on ``cmd_vel`` in sim time.

Parameter ``profile`` is a flat list [t0, vx, vy, wz, t1, ...] (sim time [s], [m/s], [m/s], [rad/s]).
It follows the ``clock`` topic directly, publishing at most every ``period_s`` of sim time.
"""

from __future__ import annotations

from geometry_msgs.msg import Twist
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from tal_core.node_utils import declare, ns_from_stamp, run_node

from .cmd_vel_profile import command_at, parse_profile


class CmdVelScriptNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("cmd_vel_script", **kwargs)
        profile = declare(self, "profile", [0.0, 0.0, 0.0, 0.0],
                          "flat list of (t [s], vx [m/s], vy [m/s], yaw rate [rad/s]) segments")
        self.period_ns = round(declare(self, "period_s", 0.02, "[s] sim time between messages",
                                       low=0.001, high=10.0) * 1e9)
        self.segments = parse_profile(profile)
        self.pub = self.create_publisher(Twist, "cmd_vel", 10)
        self.create_subscription(Clock, "clock", self._on_clock, 10)
        self._last_ns: int | None = None

    def _on_clock(self, msg: Clock) -> None:
        now = ns_from_stamp(msg.clock)
        if self._last_ns is not None and now - self._last_ns < self.period_ns:
            return
        self._last_ns = now
        segment = command_at(self.segments, now * 1e-9)
        twist = Twist()
        twist.linear.x, twist.linear.y, twist.angular.z = segment.vx_m_s, segment.vy_m_s, segment.yaw_rate_rad_s
        self.pub.publish(twist)


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: CmdVelScriptNode(), args, name="cmd_vel_script")


if __name__ == "__main__":
    raise SystemExit(main())
