"""Node ``bag_player``: replays a rosbag2 MCAP bag into the graph (tal_core.ros.bag_io).

Parameters: ``bag`` (folder or .mcap file), ``rate`` (multiple of real time; 0 = as fast as possible,
with reliable keep-all publishers so that DDS paces the player to its readers), ``topics`` (subset; empty:
all), ``remap`` (["from:=to", ...]), ``start_offset_s`` (skip the first seconds of the bag), ``loop``,
``publish_clock`` (``clock`` from the recorded log times, so consumers under use_sim_time follow the
bag; a recorded ``/clock`` topic is then not played), ``summary_path``.

Messages go out as the recorded CDR bytes (no deserialisation), in file order, each once its log time
minus the bag's start is due at ``rate``. Unknown types are skipped (one warning per type); a truncated
bag is played up to its damage and the player says how much it read.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg

from tal_core.ros.bag_io import BagError, BagMessage, BagReader, message_class
from tal_core.ros.node_utils import declare, run_node, stamp_from_ns, write_summary

TICK_S = 0.001      # [s] wall-clock timer period of the player
BURST = 2000        # messages per tick at most when playing as fast as possible


class BagPlayerNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("bag_player", **kwargs)
        bag = declare(self, "bag", "", "bag folder or .mcap file to play")
        self.rate = declare(self, "rate", 1.0, "[-] multiple of real time; 0: as fast as possible", low=0.0,
                            high=1000.0, on_change=self._set_rate)
        topics = [t for t in declare(self, "topics", [""], "topics to play (empty: all)") if t]
        remaps = [r for r in declare(self, "remap", [""], "topic remappings 'from:=to'") if r]
        self.start_offset_ns = round(declare(self, "start_offset_s", 0.0, "[s] skip this much of the bag's start",
                                             low=0.0, high=1e6) * 1e9)
        self.loop = declare(self, "loop", False, "start again at the end",
                            on_change=lambda value: setattr(self, "loop", bool(value)))
        self.publish_clock = declare(self, "publish_clock", True, "publish clock from the recorded times")
        self.summary_path = declare(self, "summary_path", "", "JSON written at shutdown",
                                    on_change=lambda value: setattr(self, "summary_path", value))
        if not bag:
            raise ValueError("parameter 'bag' is required (a bag folder or .mcap file)")
        self.reader = BagReader(bag)  # BagError for a missing bag: a start-up error
        self.topics = set(topics) or None
        self.remap: dict[str, str] = {}
        for entry in remaps:
            source, sep, target = entry.partition(":=")
            if not sep or not source or not target:
                raise ValueError(f"parameter 'remap': '{entry}' is not 'from:=to'")
            self.remap[source] = target
        reliability = ReliabilityPolicy.RELIABLE
        history = HistoryPolicy.KEEP_ALL if self.rate == 0.0 else HistoryPolicy.KEEP_LAST
        self.qos = QoSProfile(history=history, depth=1000, reliability=reliability)
        self.pub_clock = self.create_publisher(ClockMsg, "clock", 10) if self.publish_clock else None
        self._topic_publishers: dict[str, object] = {}
        self._skipped_types: set[str] = set()
        self.published = 0
        self.loops = 0
        self.finished = False
        self._start()
        self.create_timer(TICK_S, self._tick, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f"bag_player: {bag} at {'max' if self.rate == 0 else self.rate}x"
                               f"{', looping' if self.loop else ''}")

    def _start(self) -> None:
        self._messages: Iterator[BagMessage] = self.reader.messages(self.topics, decode=False)
        self._next: BagMessage | None = None
        self._bag_start_ns: int | None = None
        self._wall_start = time.monotonic()
        self._last_clock_ns: int | None = None

    def _set_rate(self, rate: float) -> None:
        """Live: the playback goes on from where it is at the new rate (0 <-> > 0 changes the QoS: refused)."""
        if (rate == 0.0) != (self.rate == 0.0):
            raise ValueError("rate: switching to or from 0 (as fast as possible) changes the publishers' QoS; "
                             "restart the player")
        if self.rate > 0.0:
            now = time.monotonic()
            self._wall_start = now - (now - self._wall_start) * self.rate / rate
        self.rate = float(rate)

    def _publisher(self, topic: str, type_name: str):
        key = self.remap.get(topic, topic)
        if key not in self._topic_publishers:
            try:
                cls = message_class(type_name)
            except BagError as exc:
                if type_name not in self._skipped_types:
                    self._skipped_types.add(type_name)
                    self.get_logger().warn(f"not playing {topic}: {exc}")
                self._topic_publishers[key] = None
                return None
            self._topic_publishers[key] = self.create_publisher(cls, key, self.qos)
        return self._topic_publishers[key]

    def _tick(self) -> None:
        if self.finished:
            return
        elapsed_ns = (time.monotonic() - self._wall_start) * 1e9
        for _ in range(BURST):
            if self._next is None:
                self._next = next(self._messages, None)
                if self._next is None:
                    self._end_of_bag()
                    return
                if self._bag_start_ns is None:
                    self._bag_start_ns = self._next.log_time_ns + self.start_offset_ns
                if self._next.log_time_ns < self._bag_start_ns:
                    self._next = None
                    continue
            message = self._next
            if self.pub_clock is not None and message.topic == "/clock":
                self._next = None  # the player publishes clock itself, from the log times
                continue
            due = (message.log_time_ns - self._bag_start_ns) / self.rate if self.rate > 0.0 else 0.0
            if due > elapsed_ns:
                return
            self._next = None
            if self.pub_clock is not None and (self._last_clock_ns is None
                                               or message.log_time_ns > self._last_clock_ns):
                self.pub_clock.publish(ClockMsg(clock=stamp_from_ns(message.log_time_ns)))
                self._last_clock_ns = message.log_time_ns
            publisher = self._publisher(message.topic, message.type_name)
            if publisher is not None:
                publisher.publish(message.data)
                self.published += 1

    def _end_of_bag(self) -> None:
        report = self.reader.report
        if not report.complete:
            self.get_logger().warn(f"bag ended early: {report.error}")
        if self.loop and self.published > 0:
            self.loops += 1
            self._start()
            return
        self.finished = True
        self.get_logger().info(f"bag_player: done, {self.published} messages published")

    def summary(self) -> dict:
        return {"published": self.published, "loops": self.loops, "finished": self.finished,
                "complete": self.reader.report.complete, "read_error": self.reader.report.error,
                "skipped_types": sorted(self._skipped_types)}

    def destroy_node(self) -> None:
        write_summary(self.summary_path, self.summary())
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: BagPlayerNode(), args, until=lambda node: node.finished, name="bag_player")


if __name__ == "__main__":
    raise SystemExit(main())
