"""Node ``bag_recorder``: records topics of the graph into a rosbag2 MCAP bag (tal_core.ros.bag_io).

Parameters: ``output`` (bag folder to create; empty: ``bags/<UTC timestamp>``), ``topics`` (names to
record; empty: every topic seen, re-discovered every ``discovery_period_s``), ``compression``
(zstd | lz4 | none, per chunk), ``chunk_size_bytes``, ``flush_period_s`` (the chunk in progress is written
this often, so a SIGKILL loses at most that much), ``summary_path``.

Subscriptions are raw: the CDR bytes are stored as received, never deserialised (fast, and exactly what
the publisher sent). The log time is the receive time on the node's clock: sim time under
``use_sim_time`` (what replays of lockstep runs want), else the system clock. SIGINT and SIGTERM close the
bag (summary, index, metadata.yaml). A topic whose type is not installed here cannot be subscribed and is
reported once.
"""

from __future__ import annotations

import time
from datetime import UTC, datetime
from pathlib import Path

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from tal_core.ros.bag_io import BagError, BagWriter, message_class
from tal_core.ros.node_utils import declare, run_node, write_summary

IGNORED_TOPICS = ("/rosout", "/parameter_events")


class BagRecorderNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("bag_recorder", **kwargs)
        output = declare(self, "output", "", "bag folder to create (empty: bags/<UTC timestamp>)")
        self.wanted = list(declare(self, "topics", [""], "topics to record (empty list or ['']: all)"))
        self.wanted = [t if t.startswith("/") else self._resolve(t) for t in self.wanted if t]
        compression = declare(self, "compression", "zstd", "chunk compression", choices=("zstd", "lz4", "none"))
        chunk = declare(self, "chunk_size_bytes", 1 << 20, "[B] chunk size before compression", low=1024,
                        high=1 << 30)
        flush_period = declare(self, "flush_period_s", 1.0, "[s] wall time between chunk flushes (bounds the "
                               "loss on SIGKILL)", low=0.01, high=60.0)
        discovery = declare(self, "discovery_period_s", 0.5, "[s] how often new topics are looked for",
                            low=0.05, high=60.0)
        self.summary_path = declare(self, "summary_path", "", "JSON written at shutdown (counts, bytes)",
                                    on_change=lambda value: setattr(self, "summary_path", value))
        path = Path(output) if output else Path("bags") / datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
        self.writer = BagWriter(path, compression=compression, chunk_size=chunk)
        self.bytes_written = 0
        self.unsupported: set[str] = set()
        self._subscribed: dict[str, str] = {}
        self._wall_start = time.monotonic()
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(flush_period, self.writer.flush, clock=steady)
        self.create_timer(discovery, self._discover, clock=steady)
        self._discover()
        self.get_logger().info(f"bag_recorder: writing {path} ({compression}), topics: "
                               f"{self.wanted or 'all'}")

    def _resolve(self, name: str) -> str:
        return self.resolve_topic_name(name)

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subscribed or topic in IGNORED_TOPICS or topic in self.unsupported:
                continue
            if self.wanted and topic not in self.wanted:
                continue
            type_name = types[0]
            try:
                cls = message_class(type_name)
                self.writer.add_topic(topic, type_name)
            except BagError as exc:
                self.unsupported.add(topic)
                self.get_logger().warn(f"not recording {topic}: {exc}")
                continue
            # A deep queue (a recorder that drops is worse than one that lags); reliable only when every
            # publisher is, since a reliable reader never matches a best-effort writer.
            publishers = self.get_publishers_info_by_topic(topic)
            reliable = bool(publishers) and all(
                info.qos_profile.reliability == ReliabilityPolicy.RELIABLE for info in publishers)
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                             reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT)
            self.create_subscription(cls, topic, self._callback(topic), qos, raw=True)
            self._subscribed[topic] = type_name
            self.get_logger().info(f"recording {topic} [{type_name}]")

    def _callback(self, topic: str):
        write = self.writer.write
        clock = self.get_clock()
        # Off sim time the node clock is the system clock: time.time_ns() reads it without building an
        # rclpy Time per message (a measurable share of the recorder's CPU at 6 k messages/s).
        sim_time = self.get_parameter("use_sim_time").value

        def on_message(data: bytes) -> None:
            try:
                write(topic, data, clock.now().nanoseconds if sim_time else time.time_ns())
            except BagError as exc:
                self.get_logger().error(f"dropping a {topic} message: {exc}", throttle_duration_sec=1.0)
                return
            self.bytes_written += len(data)
        return on_message

    def summary(self) -> dict:
        return {"bag": str(self.writer.path), "messages": self.writer.message_count,
                "bytes": self.bytes_written, "topics": dict(self._subscribed),
                "unsupported": sorted(self.unsupported),
                "wall_time_s": round(time.monotonic() - self._wall_start, 3)}

    def destroy_node(self) -> None:
        self.writer.close()
        write_summary(self.summary_path, self.summary())
        self.get_logger().info(f"bag closed: {self.writer.message_count} messages in {self.writer.path}")
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: BagRecorderNode(), args, name="bag_recorder")


if __name__ == "__main__":
    raise SystemExit(main())
