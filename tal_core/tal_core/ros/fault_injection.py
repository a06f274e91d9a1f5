"""Fault injection for graph tests: a lossy, corrupting relay between a publisher and its subscribers.

A relay sits on a remapped topic: the producer publishes ``joint_states``, the relay republishes on
``faulty/joint_states`` and the consumer is remapped to read that (``-r joint_states:=faulty/joint_states``).
Each message is passed, dropped or corrupted (positions replaced by NaN) as decided by a
``FaultSchedule``: of every ``period`` consecutive messages exactly ``count`` are picked, at positions
drawn from a seeded RNG, so a run drops exactly the asked fraction (over whole periods) and is
reproducible. Faults can start at a header stamp (the robot walks first, then the link degrades);
earlier messages pass untouched. The relay counts what it did.

The logic (``FaultSchedule``, ``FaultRelay``, ``corrupt_with_nan``) does not use rclpy; ``FaultRelayNode``
is the thin node around it (test support: no executable, tests create it in their graph's context).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

from rclpy.node import Node

from tal_core.ros.bag_io import message_class
from tal_core.ros.node_utils import declare

MAX_PERIOD = 1000  # [messages] the fraction is rounded to count / period with period at most this


class FaultSchedule:
    """Picks exactly ``fraction`` of a message stream, at random positions within each period.

    ``fraction`` is written as count / period (period <= MAX_PERIOD); in each block of ``period``
    consecutive messages exactly ``count`` are picked, their positions drawn without replacement by
    ``random.Random(seed)``. After n messages, ``picked`` is within ``count`` of ``fraction * n``.
    """

    def __init__(self, fraction: float, seed: int = 0) -> None:
        if not (math.isfinite(fraction) and 0.0 <= fraction <= 1.0):
            raise ValueError(f"fault fraction must be in [0, 1], got {fraction!r}")
        ratio = Fraction(fraction).limit_denominator(MAX_PERIOD)
        self.count, self.period = ratio.numerator, ratio.denominator
        self._rng = random.Random(seed)
        self._block: frozenset[int] = frozenset()
        self._index = 0
        self.seen = 0
        self.picked = 0

    @property
    def fraction(self) -> float:
        """The exact fraction applied (count / period)."""
        return self.count / self.period

    def next(self) -> bool:
        """Whether the next message of the stream is picked."""
        if self._index == 0:
            self._block = frozenset(self._rng.sample(range(self.period), self.count))
        picked = self._index in self._block
        self._index = (self._index + 1) % self.period
        self.seen += 1
        self.picked += int(picked)
        return picked


@dataclass
class FaultCounts:
    """What a relay did to its stream [messages], with the header stamps of the dropped and corrupted
    messages (tests are short; a relay meant to run for hours would keep counts only)."""

    received: int = 0
    eligible: int = 0        # received at or after the start stamp (the fractions apply to these)
    passed: int = 0
    dropped: int = 0
    corrupted: int = 0
    dropped_stamps_ns: list[int] = field(default_factory=list)
    corrupted_stamps_ns: list[int] = field(default_factory=list)

    def as_dict(self) -> dict[str, int]:
        return {"received": self.received, "eligible": self.eligible, "passed": self.passed,
                "dropped": self.dropped, "corrupted": self.corrupted}


def corrupt_with_nan(msg: Any) -> Any:
    """Replace the positions of ``msg`` by NaN, in place, and return it.

    sensor_msgs/JointState: every ``position``; nav_msgs/Odometry: ``pose.pose.position``. Other types
    raise TypeError (the relay checks this at start-up).
    """
    if hasattr(msg, "position") and hasattr(msg, "name"):           # sensor_msgs/JointState
        msg.position = [math.nan] * len(msg.position)
        return msg
    if hasattr(msg, "pose") and hasattr(msg.pose, "pose"):          # nav_msgs/Odometry
        msg.pose.pose.position.x = msg.pose.pose.position.y = msg.pose.pose.position.z = math.nan
        return msg
    raise TypeError(f"corrupt_with_nan: no positions to corrupt in {type(msg).__name__}")


def _stamp_ns(msg: Any) -> int | None:
    header = getattr(msg, "header", None)
    if header is None:
        return None
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


class FaultRelay:
    """Decides per message: drop (``drop_fraction``), else corrupt (``nan_fraction``), else pass.

    The two schedules are independent streams of the same seed family, so the drops do not change
    which messages are corrupted. Messages stamped before ``start_ns`` (header stamp [ns]) pass and do not
    advance the schedules; messages without a header are always eligible.
    """

    def __init__(self, drop_fraction: float = 0.0, nan_fraction: float = 0.0, seed: int = 0,
                 start_ns: int = 0) -> None:
        self.drops = FaultSchedule(drop_fraction, seed)
        self.nans = FaultSchedule(nan_fraction, seed + 1)
        self.start_ns = int(start_ns)
        self.counts = FaultCounts()

    def process(self, msg: Any) -> Any | None:
        """The message to forward (possibly corrupted), or None to drop it."""
        self.counts.received += 1
        stamp = _stamp_ns(msg)
        if stamp is not None and stamp < self.start_ns:
            self.counts.passed += 1
            return msg
        self.counts.eligible += 1
        drop = self.drops.next()
        corrupt = self.nans.next()
        if drop:
            self.counts.dropped += 1
            if stamp is not None:
                self.counts.dropped_stamps_ns.append(stamp)
            return None
        if corrupt:
            self.counts.corrupted += 1
            if stamp is not None:
                self.counts.corrupted_stamps_ns.append(stamp)
            msg = corrupt_with_nan(msg)
        self.counts.passed += 1
        return msg


class FaultRelayNode(Node):
    """Relays ``input_topic`` to ``output_topic`` through a ``FaultRelay``.

    Parameters: ``input_topic``, ``output_topic``, ``message_type`` ('pkg/msg/Type'), ``drop_fraction``,
    ``nan_fraction`` ([0, 1]), ``seed``, ``start_s`` (header-stamp time from which faults are injected),
    ``depth`` (QoS history depth of both sides, reliable).
    Pass ``node_name`` to run several relays in one process.
    """

    def __init__(self, node_name: str = "fault_relay", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        input_topic = declare(self, "input_topic", "joint_states", "topic to read")
        output_topic = declare(self, "output_topic", "faulty/joint_states", "topic to republish on")
        type_name = declare(self, "message_type", "sensor_msgs/msg/JointState", "'pkg/msg/Type' of both topics")
        drop = declare(self, "drop_fraction", 0.0, "[-] fraction of messages dropped", low=0.0, high=1.0)
        nan = declare(self, "nan_fraction", 0.0, "[-] fraction of messages whose positions become NaN",
                      low=0.0, high=1.0)
        seed = declare(self, "seed", 0, "[-] seed of the fault positions", low=0, high=2**31 - 1)
        start = declare(self, "start_s", 0.0, "[s] header stamp from which faults are injected (earlier "
                        "messages pass)", low=0.0, high=1e9)
        depth = declare(self, "depth", 10, "[-] QoS history depth (reliable)", low=1, high=10000)
        msg_type = message_class(type_name)
        if nan > 0.0:
            corrupt_with_nan(msg_type())  # raises TypeError at start-up for a type without positions
        self.relay = FaultRelay(drop, nan, seed, start_ns=round(start * 1e9))
        self._pub = self.create_publisher(msg_type, output_topic, depth)
        self.create_subscription(msg_type, input_topic, self._on_message, depth)
        self.get_logger().info(f"fault relay {input_topic} -> {output_topic}: drop {self.relay.drops.fraction:.3f}, "
                               f"NaN {self.relay.nans.fraction:.3f}, seed {seed}, from {start} s")

    @property
    def counts(self) -> FaultCounts:
        return self.relay.counts

    def matched_subscribers(self) -> int:
        """Subscriptions matched with the output (messages sent before a subscriber matched are lost)."""
        return self._pub.get_subscription_count()

    def _on_message(self, msg: Any) -> None:
        out = self.relay.process(msg)
        if out is not None:
            self._pub.publish(out)
