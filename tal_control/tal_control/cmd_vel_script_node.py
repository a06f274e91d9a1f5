"""Node ``cmd_vel_script``: plays a piecewise-constant velocity profile in sim time.

Parameter ``profile`` is a flat list [t0, vx, vy, wz, t1, ...] (sim time [s], [m/s], [m/s], [rad/s]).
It follows the ``clock`` topic directly.

It always publishes geometry_msgs/Twist on ``cmd_vel`` when the clock passes each period_s (as a teleop
would, and what recorders keep). With ``stamped`` (default) it also publishes geometry_msgs/TwistStamped on
``cmd_vel_stamped``, each stamped with the sim time from which it applies, ``lead_s`` of sim time ahead of
the clock on the absolute grid k * period_s plus every segment start. The wbc applies those from their
first control tick at or after the stamp (and ignores the Twist while they come), so a lockstep run does
not depend on when this process gets the CPU; a Twist is applied at whichever tick follows its arrival.
Reliable, transient local (a late transient-local subscriber gets the recent ones; the wbc subscribes
volatile, to match any publisher).

``profile`` is live (``ros2 param set``): the Twist follows the new profile at once; stamped commands
already published (up to ``lead_s`` ahead) stay, the new profile applies to the stamps published after.
period_s, stamped and lead_s are read-only.
"""

from __future__ import annotations

from geometry_msgs.msg import Twist, TwistStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from tal_core.errors import InputError
from tal_core.ros.node_utils import declare, ns_from_stamp, run_node, stamp_from_ns

from .cmd_vel_profile import command_at, parse_profile, stamps_due

STAMPED_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


class CmdVelScriptNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("cmd_vel_script", **kwargs)
        profile = declare(self, "profile", [0.0, 0.0, 0.0, 0.0],
                          "flat list of (t [s], vx [m/s], vy [m/s], yaw rate [rad/s]) segments; live",
                          on_change=self._set_profile)
        self.period_ns = round(declare(self, "period_s", 0.02, "[s] sim time between messages",
                                       low=0.001, high=10.0) * 1e9)
        self.stamped = declare(self, "stamped", True, "also publish TwistStamped on cmd_vel_stamped ahead of the "
                               "clock (deterministic in lockstep)")
        self.lead_ns = round(declare(self, "lead_s", 0.1, "[s] stamped: sim time ahead of the clock at which "
                                     "commands are published", low=0.0, high=10.0) * 1e9)
        self.segments = parse_profile(profile)
        self.pub = self.create_publisher(Twist, "cmd_vel", 10)
        if self.stamped:
            self.pub_stamped = self.create_publisher(TwistStamped, "cmd_vel_stamped", STAMPED_QOS)
        self.create_subscription(Clock, "clock", self._on_clock, 10)
        self._last_ns: int | None = None        # unstamped: clock of the last message
        self._published_ns: int | None = None   # stamped: stamp of the last message

    def _set_profile(self, profile: list[float]) -> None:
        try:
            self.segments = parse_profile(profile)
        except InputError as exc:
            raise ValueError(f"parameter 'profile': {exc}") from exc

    def _twist(self, t_ns: int) -> Twist:
        segment = command_at(self.segments, t_ns * 1e-9)
        twist = Twist()
        twist.linear.x, twist.linear.y, twist.angular.z = segment.vx_m_s, segment.vy_m_s, segment.yaw_rate_rad_s
        return twist

    def _on_clock(self, msg: Clock) -> None:
        now = ns_from_stamp(msg.clock)
        if self.stamped:
            self._publish_stamped(now)
        if self._last_ns is not None and now - self._last_ns < self.period_ns:
            return
        self._last_ns = now
        self.pub.publish(self._twist(now))

    def _publish_stamped(self, now_ns: int) -> None:
        stamps = []
        if self._published_ns is None or now_ns < self._published_ns - self.lead_ns:
            stamps.append(now_ns)  # the first clock (or a restarted one): the command in force now
            self._published_ns = now_ns
        stamps += stamps_due(self.segments, self.period_ns, self._published_ns, now_ns + self.lead_ns)
        for stamp in stamps:
            out = TwistStamped(twist=self._twist(stamp))
            out.header.stamp = stamp_from_ns(stamp)
            out.header.frame_id = "horizontal"
            self.pub_stamped.publish(out)
            self._published_ns = stamp


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: CmdVelScriptNode(), args, name="cmd_vel_script")


if __name__ == "__main__":
    raise SystemExit(main())
